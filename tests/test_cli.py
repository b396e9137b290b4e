"""The `drgan` console command: stages as subcommands, their help with every setting's comment, unknown names."""

from __future__ import annotations

import subprocess
import sys

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
