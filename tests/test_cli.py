"""The `drgan` console command: stages as subcommands, their help with every setting's comment, unknown names."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from drgan import cli


def test_drgan_help_lists_every_stage(capsys):
    assert cli.main(["--help"]) == 0
    text = capsys.readouterr().out
    for name in ("pipeline", "profile", "train", "generate", "segment", "evaluate", "analyze"):
        assert f"\n  {name} " in text
    assert "drgan pipeline data.dir=" in text


def test_a_stage_help_says_what_it_does_and_lists_its_keys_with_comments(capsys):
    assert cli.main(["generate", "--help"]) == 0
    text = capsys.readouterr().out
    assert "a synthetic segmentation training set" in text  # the module's docstring
    assert "grey_spread: auto" in text and "# each image takes the background and particle grey" in text
    assert cli.main(["pipeline", "-h"]) == 0
    assert "redo:" in capsys.readouterr().out


def test_python_m_a_stage_help_is_drgans_help_with_its_usage_first_and_python_m_drgan_is_the_command():
    """`python -m drgan.generate --help` prints what `drgan generate --help` does (not Hydra's generic help), each
    opening with its usage line; `python -m drgan` is the console command."""
    by_module = subprocess.run([sys.executable, "-m", "drgan.generate", "--help"], capture_output=True, text=True)
    by_command = subprocess.run([sys.executable, "-m", "drgan", "generate", "--help"], capture_output=True, text=True)
    assert by_module.returncode == by_command.returncode == 0
    assert by_module.stdout.startswith("usage: python -m drgan.generate [KEY=VALUE ...]")
    assert by_command.stdout.startswith("usage: drgan generate [KEY=VALUE ...]")
    body = by_module.stdout.split("\n", 1)[1].split("Settings (")[0]
    assert body == by_command.stdout.split("\n", 1)[1].split("Settings (")[0] and "synthetic segmentation" in body
    assert "grey_spread: auto" in by_module.stdout and "Powered by Hydra" not in by_module.stdout
    pipeline = subprocess.run([sys.executable, "-m", "drgan", "pipeline", "--help"], capture_output=True, text=True)
    first = pipeline.stdout.split("\n\n")[1]  # what the command does, for a user: no module names of the code
    assert pipeline.stdout.startswith("usage: drgan pipeline") and "from a folder of images" in first
    assert "stage_table" not in first


def test_an_unknown_stage_is_named_with_the_stages(capsys):
    assert cli.main(["trian"]) == 2
    assert "no stage 'trian'" in capsys.readouterr().err


def test_a_subcommand_runs_the_stage_as_its_module_does():
    """`drgan pipeline` with a bad setting fails as `python -m drgan.pipeline` does: its message, exit code 1."""
    done = subprocess.run([sys.executable, "-m", "drgan.cli", "pipeline", "name=x"], capture_output=True, text=True)
    assert done.returncode == 1 and "give data.dir" in done.stderr and "Traceback" not in done.stderr


def test_a_users_mistake_prints_its_message_and_no_traceback(tmp_path):
    """The issue's own example: a paper material without its images. Its message, exit code 1, nothing of Hydra's."""
    done = subprocess.run(
        [sys.executable, "-m", "drgan.train", "material=sio2_him", "placement=poisson", f"hydra.run.dir={tmp_path}"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    output = done.stdout + done.stderr
    assert done.returncode == 1 and "data.dir is not set: material=sio2_him" in output
    assert "Traceback" not in output and "Error executing job" not in output


TOY_STAGE = '''"""A toy stage: writes its greeting into its run folder."""

from pathlib import Path

from drgan.core.errors import ConfigError
from drgan.launch.runtime import stage_main


@stage_main(config_path=".", config_name="toy")
def main(cfg):
    if not cfg.greeting:
        raise ConfigError("greeting is empty")
    Path(cfg.out).write_text(cfg.greeting)


if __name__ == "__main__":
    main()
'''


def test_a_new_stage_is_one_entry_in_the_registry(tmp_path, monkeypatch, capsys):
    """CONTRIBUTING.md, "a stage": its module (started by runtime.stage_main), its config file and one entry in
    cli.COMMANDS make `drgan toy --help` and `drgan toy KEY=VALUE` work; nothing else is edited (monkeypatch: the
    entry and the module's path go away after the test)."""
    (tmp_path / "drgan_toy_stage.py").write_text(TOY_STAGE)
    conf = tmp_path / "toy.yaml"
    conf.write_text("# what the toy says\ngreeting: hello\n# the file it writes\nout: ???\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", list(sys.argv))
    monkeypatch.setitem(cli.COMMANDS, "toy", ("drgan_toy_stage", str(conf), "a toy stage"))

    assert cli.main(["--help"]) == 0
    assert "\n  toy " in capsys.readouterr().out
    assert cli.main(["toy", "--help"]) == 0
    text = capsys.readouterr().out
    assert "A toy stage: writes its greeting" in text and "# what the toy says\ngreeting: hello" in text

    out = tmp_path / "said.txt"
    assert cli.main(["toy", "greeting=hi", f"out={out}", f"hydra.run.dir={tmp_path / 'run'}"]) == 0
    assert out.read_text() == "hi"
    assert cli.main(["toy", "greeting=", f"out={out}", f"hydra.run.dir={tmp_path / 'run'}"]) == 1
    assert "error: greeting is empty" in capsys.readouterr().err


def test_every_stage_of_the_registry_is_in_a_layer_of_the_import_contracts():
    """pyproject.toml's import contracts name the entry points' layer; a stage added to cli.COMMANDS and not there
    would escape `lint-imports`."""
    text = (Path(cli.__file__).resolve().parents[2] / "pyproject.toml").read_text()
    layers = text.split("[tool.importlinter]")[1].split("layers = [")[1].split("]")[0]  # tomllib is Python 3.11+
    named = set(re.findall(r"drgan[\w.]*", layers))
    missing = [module for module, _, _ in cli.COMMANDS.values() if module not in named]
    assert not missing, f"add {missing} to the entry points' layer in pyproject.toml"


def test_the_package_top_level_holds_only_what_a_user_runs():
    """src/drgan/'s modules are the console command and the registry's stages and tools; the plumbing they share
    lives in packages (core, launch, profiling, ...), so a new helper module at the top level fails here."""
    commands = {module.split(".")[1] for module, _, _ in cli.COMMANDS.values()}
    top = {path.stem for path in cli.PACKAGE.glob("*.py")} - {"__init__", "__main__", "cli"}
    assert top <= commands, f"not a stage or tool of cli.COMMANDS: {sorted(top - commands)} (move it into a package)"
    assert {"profile", "train", "generate", "segment", "analyze", "evaluate"} <= top
