"""drgan.pipeline: settings routed to their stage, inputs refused before any stage runs, resuming after a kill between
and inside stages, and (slow) a tiny real pipeline whose stage outputs equal the single commands'."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from drgan import pipeline
from drgan.core.errors import ConfigError, DataError, DrganError
from drgan.pipeline import runner, stage_table, stages, tracking


def images_folder(folder: Path, n: int = 3, seed: int = 0) -> Path:
    """Bright discs on a dark film, 64 px: enough for the checks that read images (no stage runs on them here)."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for i in range(n):
        image = (0.2 + 0.02 * rng.standard_normal((64, 64))).clip(0, 1)
        image[20:30, 20:30] = 0.8
        Image.fromarray((image * 255).astype(np.uint8)).save(folder / f"im{i}.png")
    return folder


# --- settings ----------------------------------------------------------------------------------------------


def test_stage_keys_are_routed_to_their_stage_and_replace_the_configs_defaults(tmp_path):
    s = pipeline.parse_settings(
        [
            f"data.dir={tmp_path}",
            "name=mine",
            "train.callbacks.early_stopping.max_minutes=30",  # replaces the pipeline config's 90
            "segment.model.normalize=none",
            "+generate.shard=0/2",
            "~train.callbacks.sample_grid",
            "annotated=/x/y",
        ]
    )
    assert s.name == "mine" and s.out == (Path("runs/pipeline") / "mine").resolve() and s.annotated == Path("/x/y")
    assert s.stages["train"] == {
        "trainer.max_epochs": "5", "callbacks.early_stopping.max_minutes": "30", "renderer.spp": "16",
        "~callbacks.sample_grid": None,
    }  # fmt: skip
    assert s.stages["segment"] == {"model.normalize": "none"}
    assert s.stages["generate"] == {"n": "500", "renderer.spp": "16", "sampled_spp": "64", "+shard": "0/2"}
    built = {st.name: st for st in stages.build_stages(s, parent_run="abc")}
    assert "model.normalize=none" in built["segment"].settings and "model.normalize=none" not in built["train"].settings
    assert "~callbacks.sample_grid" in built["train"].settings and "+shard=0/2" in built["generate"].settings
    assert "parent_run=abc" in built["train"].wired and "parent_run=abc" in built["segment"].wired
    assert built["evaluate"].wired[1] == "data=/x/y" and "subset=all" in built["evaluate"].wired  # no split.json


@pytest.mark.parametrize(
    "argv, match",
    [
        (["name=mine"], "give data.dir"),
        (["data.dir=/d", "name=my run"], "name='my run'"),
        (["data.dir=/d", "name=tio2_sem"], "a material drgan ships has that name"),
        (["data.dir=/d", "name=m", "trian.seed=1"], "trian.seed: not a setting"),
        (["data.dir=/d", "name=m", "redo=trian"], "redo='trian'"),
        (["data.dir=/d", "name=m", "train.hydra.run.dir=/elsewhere"], "train.hydra.run.dir is set by the pipeline"),
        (["data.dir=/d", "name=m", "segment"], "expected KEY=VALUE"),
        (["data.dir=/d", "name=m", "progress=often"], "progress='often': expected seconds between progress lines"),
        (["data.dir=/d", "name=m", "progress=-5"], "progress=-5: expected seconds"),
        (["data.dir=/d", "name=m", "mlflow=maybe"], "mlflow='maybe': expected true or false"),
        (["data.dir=/d", "name=m", "launcher=cluster"], "launcher='cluster': expected one of local, slurm"),
    ],
)
def test_bad_settings_are_refused_with_the_key_named(argv, match):
    with pytest.raises(ConfigError, match=match):
        pipeline.parse_settings(argv)


def test_the_pipelines_own_values_read_as_yaml_values():
    """A command line's value of the pipeline's own keys reads as Hydra reads a stage's: null or nothing is null,
    numbers are numbers, a number where a name is expected is its text."""
    given = pipeline.parse_settings(
        ["data.dir=/d", "name=2024", "out=", "annotated=null", "progress=0.5", "mlflow=false"]
    )
    assert (given.name, given.annotated, given.progress, given.mlflow) == ("2024", None, 0.5, False)
    assert given.out == (Path("runs/pipeline") / "2024").resolve()


# --- inputs, before any stage runs --------------------------------------------------------------------------


@pytest.fixture
def no_stage_runs(monkeypatch):
    calls = []
    monkeypatch.setattr(runner, "run_stage", lambda stage, *rest: calls.append(stage.name) or 0)
    return calls


def settings(tmp_path, *extra):
    return pipeline.parse_settings(
        [f"data.dir={tmp_path / 'images'}", "name=t", f"out={tmp_path / 'out'}", "mlflow=false", *extra]
    )


def test_a_bad_folder_is_refused_before_any_stage_runs(tmp_path, no_stage_runs):
    with pytest.raises(DataError, match="no such folder"):
        pipeline.run(settings(tmp_path))
    (tmp_path / "images").mkdir()
    with pytest.raises(DataError, match="holds no image files"):
        pipeline.run(settings(tmp_path))
    assert no_stage_runs == [] and not (tmp_path / "out").exists()


def test_a_typo_in_a_stage_key_fails_in_seconds_not_after_the_gan(tmp_path, no_stage_runs):
    images_folder(tmp_path / "images")
    with pytest.raises(ConfigError, match="segment settings.*do not fit drgan.segment"):
        pipeline.run(settings(tmp_path, "segment.modle.lr=0.1"))
    assert no_stage_runs == []


def test_annotated_images_that_train_are_refused(tmp_path, no_stage_runs):
    images_folder(tmp_path / "images")
    annotated = tmp_path / "annotated"
    images_folder(annotated / "images", n=2, seed=7)
    (annotated / "masks").mkdir()
    shutil.copy(tmp_path / "images" / "im1.png", annotated / "images" / "copy.png")  # the same file, renamed
    with pytest.raises(DataError, match="1 of its scored image.*training images too"):
        pipeline.run(settings(tmp_path, f"annotated={annotated}"))
    assert no_stage_runs == []
    # The same folder with a split.json whose train ids leave that image out: it is only scored, never trained on.
    (tmp_path / "split.json").write_text(json.dumps({"train": ["im0", "im2"], "test": ["im1"]}))
    assert stages.check_inputs(settings(tmp_path, f"annotated={annotated}"))["training_images"] == 2


# --- resuming (the stages faked: each writes its done file, or is "killed") -----------------------------------


class FakeStages:
    """Stands in for the stage processes: records each command, writes the stage's done file, and can be told to
    die in a stage (after writing a last.ckpt, as a killed drgan.train leaves one)."""

    def __init__(self, monkeypatch, real: tuple[str, ...] = ()):
        self.calls: list[list[str]] = []
        self.die_in: str | None = None
        self.real, self.run_stage = real, runner.run_stage  # the stages in ``real`` run their own process
        monkeypatch.setattr(runner, "run_stage", self)
        monkeypatch.setattr(runner, "check_stage_settings", lambda s: None)

    def __call__(self, stage, *rest):
        self.calls.append([stage.name, *stage.command()[3:]])
        if stage.name in self.real:
            return self.run_stage(stage, *rest)
        if stage.name == self.die_in:
            (stage.folder / "checkpoints").mkdir(parents=True, exist_ok=True)
            (stage.folder / "checkpoints" / "last.ckpt").write_bytes(b"x")
            return -signal.SIGKILL
        stage.done_file.parent.mkdir(parents=True, exist_ok=True)
        stage.done_file.write_text("{}")
        return 0

    def names(self):
        return [c[0] for c in self.calls]


def test_redo_of_a_stage_this_run_does_not_have_is_refused_by_name(tmp_path, no_stage_runs):
    images_folder(tmp_path / "images")
    with pytest.raises(ConfigError, match="redo=evaluate: this run has no such stage.*annotated=DIR"):
        pipeline.run(settings(tmp_path, "redo=evaluate"), echo=lambda line: None)
    assert no_stage_runs == []


def test_the_pixel_size_the_profile_read_reaches_analyze_and_the_report(tmp_path, monkeypatch):
    """analyze measures in nm when the profile read a pixel size from the images' metadata: its command gets it, and
    report.md shows the command as it ran (not as it was built before the profile ran)."""
    images_folder(tmp_path / "images")
    fake = FakeStages(monkeypatch)
    profiled = tmp_path / "out" / "profile" / "profile.json"

    def stage_with_profile(stage, *rest):
        code = FakeStages.__call__(fake, stage, *rest)
        if stage.name == "profile":
            profiled.parent.mkdir(parents=True, exist_ok=True)
            profiled.write_text(json.dumps({"pixel_size": {"nm_per_px": 2.5}}))
        return code

    monkeypatch.setattr(runner, "run_stage", stage_with_profile)
    pipeline.run(settings(tmp_path), echo=lambda line: None)
    analyze = next(call for call in fake.calls if call[0] == "analyze")
    assert "nm_per_px=2.5" in analyze
    assert "nm_per_px=2.5" in (tmp_path / "out" / "report.md").read_text()


def test_a_rerun_skips_done_stages_and_resumes_the_killed_one(tmp_path, monkeypatch):
    images_folder(tmp_path / "images")
    fake = FakeStages(monkeypatch)
    fake.die_in = "segment"
    with pytest.raises(DrganError, match="stage segment failed"):
        pipeline.run(settings(tmp_path), echo=lambda line: None)
    assert fake.names() == ["profile", "train", "generate", "segment"]
    state = json.loads((tmp_path / "out" / "pipeline.json").read_text())["stages"]
    assert [state[s]["state"] for s in ("profile", "train", "generate", "segment")] == ["done"] * 3 + ["failed"]

    fake.calls, fake.die_in = [], None
    lines = []
    pipeline.run(settings(tmp_path), echo=lines.append)
    assert fake.names() == ["segment", "analyze"]  # done stages skipped
    assert "ckpt_path=last" in fake.calls[0]  # the killed segmenter resumes from its checkpoint
    assert any("[2/5] train: done" in line and "skipped" in line for line in lines)
    assert (tmp_path / "out" / "report.md").is_file()

    fake.calls = []
    pipeline.run(settings(tmp_path), echo=lambda line: None)
    assert fake.calls == []  # everything done: nothing runs again


def test_changed_settings_of_a_done_stage_stop_the_rerun_and_redo_runs_it_again(tmp_path, monkeypatch):
    images_folder(tmp_path / "images")
    fake = FakeStages(monkeypatch)
    pipeline.run(settings(tmp_path), echo=lambda line: None)
    fake.calls = []
    with pytest.raises(ConfigError, match=r"stage segment is done with other settings \(now model.normalize=none\)"):
        pipeline.run(settings(tmp_path, "segment.model.normalize=none"), echo=lambda line: None)
    assert fake.calls == []
    pipeline.run(settings(tmp_path, "segment.model.normalize=none", "redo=segment"), echo=lambda line: None)
    assert fake.names() == ["segment", "analyze"] and "model.normalize=none" in fake.calls[0]


def test_a_stage_done_before_the_pipeline_wired_a_key_stays_done(tmp_path, monkeypatch, capsys):
    images_folder(tmp_path / "images")
    fake = FakeStages(monkeypatch)
    pipeline.run(settings(tmp_path), echo=lambda line: None)
    record = tmp_path / "out" / "pipeline.json"
    state = json.loads(record.read_text())
    args = state["stages"]["analyze"]["args"]
    state["stages"]["analyze"]["args"] = [a for a in args if not a.startswith("profile=")]  # an older drgan's record
    record.write_text(json.dumps(state))
    fake.calls = []
    pipeline.run(settings(tmp_path), echo=lambda line: None)
    assert fake.calls == [] and "analyze was done by an older drgan without profile=" in capsys.readouterr().err
    # a value the record holds otherwise is a changed setting, not a new key
    state["stages"]["analyze"]["args"] = ["profile=elsewhere" if a.startswith("profile=") else a for a in args]
    record.write_text(json.dumps(state))
    with pytest.raises(ConfigError, match="stage analyze is done with other settings"):
        pipeline.run(settings(tmp_path), echo=lambda line: None)


def test_corrected_outlines_added_to_a_finished_run_fine_tune_and_analyze_again(tmp_path, monkeypatch):
    """corrected=DIR on a finished run: the finetune stage runs, and analyze, done before it with segment's segmenter,
    runs again after it with the fine-tuned one (a done stage after one that runs is run again); nothing else reruns.
    A corrected image that is not in the folder is refused before anything runs."""
    from drgan.data.imagej import write_label_tiff

    images_folder(tmp_path / "images")
    fake = FakeStages(monkeypatch)
    pipeline.run(settings(tmp_path), echo=lambda line: None)
    labels = np.zeros((64, 64), np.int32)
    labels[20:30, 20:30] = 1
    write_label_tiff(tmp_path / "fixes" / "nope.tif", labels)
    with pytest.raises(DataError, match="no image for 1 requested id"):
        pipeline.run(settings(tmp_path, f"corrected={tmp_path / 'fixes'}"), echo=lambda line: None)
    (tmp_path / "fixes" / "nope.tif").rename(tmp_path / "fixes" / "im1.tif")
    fake.calls, lines = [], []
    pipeline.run(settings(tmp_path, f"corrected={tmp_path / 'fixes'}"), echo=lines.append)
    assert fake.names() == ["finetune", "analyze"]
    assert any("analyze is done, but a stage before it will run" in line for line in lines)
    assert f"model={tmp_path / 'out' / 'finetune' / 'checkpoints' / 'last.ckpt'}" in fake.calls[1]
    fake.calls = []
    pipeline.run(settings(tmp_path, f"corrected={tmp_path / 'fixes'}"), echo=lambda line: None)
    assert fake.calls == []


def test_two_pipelines_on_one_folder_are_refused(tmp_path):
    with tracking.folder_lock(tmp_path / "out"):
        with pytest.raises(ConfigError, match="another drgan.pipeline is running"):
            with tracking.folder_lock(tmp_path / "out"):
                pass


# --- the table of stages -------------------------------------------------------------------------------------


def test_the_stages_commands_and_keys_are_those_of_the_table(tmp_path):
    """stage_table.PIPELINE, read by build_stages and parse_settings: each stage's command, done file and refused keys
    as the pipeline has always given them (pinned here: a change of the table that changes a command fails)."""
    s = pipeline.parse_settings(
        [f"data.dir={tmp_path / 'images'}", "name=t", f"out={tmp_path / 'o'}", f"annotated={tmp_path / 'a'}",
         "train.seed=3", "analyze.inference.tile=64"]
    )  # fmt: skip
    o, data, conf = tmp_path / "o", s.data_dir, tmp_path / "o" / "drgan_conf"
    model = f"model={o / 'segment' / 'checkpoints' / 'last.ckpt'}"
    logged = ["logger.mlflow.experiment_name=pipeline_t", "parent_run=P"]
    named = {n: [logged[0], f"logger.mlflow.run_name={n}", logged[1]] for n in ("train", "segment", "finetune")}
    built = {st.name: (st.module, st.recorded(), st.done_file) for st in stages.build_stages(s, "P", nm_per_px=2.5)}
    assert built == {
        "profile": ("drgan.profile", [f"data.dir={data}", "name=t", f"out={o / 'profile'}", f"conf_dir={conf}",
                                      "overwrite=true"], conf / "material" / "t.yaml"),
        "train": ("drgan.train", ["material=t", "run_name=t", f"hydra.run.dir={o / 'train'}",
                                  f"hydra.searchpath=[file://{conf}]", *named["train"],
                                  "trainer.max_epochs=5", "callbacks.early_stopping.max_minutes=90", "renderer.spp=16", "seed=3"],
                  o / "train" / "metrics.json"),
        "generate": ("drgan.generate", [f"ckpt={o / 'train'}", f"out={o / 'generate'}", "n=500", "renderer.spp=16", "sampled_spp=64"],
                     o / "generate" / "manifest.json"),
        "segment": ("drgan.segment", [f"data={o / 'generate'}", f"out={o / 'segment'}", "name=t", "run_name=t",
                                      f"agreement.images={data}", f"agreement.reference={o / 'profile' / 'labels'}",
                                      *named["segment"]], o / "segment" / "metrics.json"),
        "analyze": ("drgan.analyze", [model, f"images={data}", f"out={o / 'analyze'}", f"profile={o / 'profile'}", "nm_per_px=2.5",
                                      "inference.tile=64"], o / "analyze" / "particles.csv"),
        "evaluate": ("drgan.evaluate", [model, f"data={tmp_path / 'a'}", f"out={o / 'evaluate'}",
                                        f"reported={o / 'analyze'}", "subset=all"],
                     o / "evaluate" / "results.md"),
    }  # fmt: skip
    assert stage_table.PIPELINE_KEYS == {
        "profile": ("data.dir", "name", "out", "conf_dir", "overwrite"),
        "train": ("material", "run_name", "hydra.run.dir", "hydra.searchpath", "parent_run", "ckpt_path"),
        "generate": ("ckpt", "out"),
        "segment": (
            "data",
            "real",
            "out",
            "name",
            "run_name",
            "agreement.images",
            "agreement.reference",
            "parent_run",
            "ckpt_path",
        ),
        "finetune": (
            "finetune",
            "data",
            "real",
            "corrected",
            "correction.images",
            "out",
            "name",
            "run_name",
            "parent_run",
            "ckpt_path",
        ),
        "analyze": ("model", "images", "out", "profile"),
        "evaluate": ("model", "models", "data", "out", "reported"),
    }
    assert pipeline.STAGES == stage_table.STAGES == ("profile", "train", "generate", "segment", "finetune",
                                                      "analyze", "evaluate")  # fmt: skip
    assert "finetune" not in built  # without corrected=: no such stage, analyze uses segment's segmenter
    # corrected=DIR: the finetune stage fine-tunes segment's segmenter, and analyze and evaluate use the fine-tuned one
    fixed = pipeline.parse_settings([*s.argv, f"corrected={tmp_path / 'fixes'}"])
    with_fixes = {st.name: (st.module, st.recorded()) for st in stages.build_stages(fixed, "P")}
    assert with_fixes["finetune"] == (
        "drgan.segment", [f"finetune={o / 'segment'}", f"data={o / 'generate'}", f"corrected={tmp_path / 'fixes'}",
                          f"correction.images={data}", f"out={o / 'finetune'}", "name=t", "run_name=t_finetune",
                          *named["finetune"]])  # fmt: skip
    tuned = f"model={o / 'finetune' / 'checkpoints' / 'last.ckpt'}"
    assert with_fixes["analyze"][1][0] == tuned and with_fixes["evaluate"][1][0] == tuned
    assert list(with_fixes) == ["profile", "train", "generate", "segment", "finetune", "analyze", "evaluate"]
    (o / "train" / "checkpoints").mkdir(parents=True)
    (o / "train" / "checkpoints" / "last.ckpt").write_bytes(b"x")
    resumed = {st.name: st.resume() for st in stages.build_stages(s, None) if st.spec.resumes}
    assert resumed == {"train": ["ckpt_path=last"], "segment": []}  # only train has a checkpoint


# --- a toy stage, added as CONTRIBUTING.md says ---------------------------------------------------------------

TOY_STAGE = '''"""A toy pipeline stage: counts the lines of the particle table that analyze wrote."""

import json
import sys
from pathlib import Path

args = dict(arg.split("=", 1) for arg in sys.argv[1:])
out = Path(args["out"])
out.mkdir(parents=True, exist_ok=True)
lines = len(Path(args["particles"]).read_text().splitlines())
(out / "count.json").write_text(json.dumps({"lines": lines, "greeting": args.get("greeting", "hello")}))
'''


def toy_summary(folder: Path) -> dict:
    counted = json.loads((folder / "count.json").read_text()) if (folder / "count.json").is_file() else {}
    if not counted:
        return {}
    return {
        "line": f"{counted['lines']} line(s) counted, {counted['greeting']}",
        "metrics": {"toy/lines": counted["lines"]},
    }


TOY = stage_table.StageSpec(
    "toy",
    wire=lambda c: [f"particles={c.folder('analyze') / 'particles.csv'}", f"out={c.folder('toy')}"],
    keys=("particles", "out"),
    done=lambda c: c.folder("toy") / "count.json",
    summary=toy_summary,
    what="counts the lines of the particle table",
    links=(("the count", "count.json"), ("a figure it never drew", "lines.png")),
    module="drgan_toy_pipeline_stage",
)


def test_a_new_pipeline_stage_is_one_entry_in_the_table(tmp_path, monkeypatch):
    """CONTRIBUTING.md, "a pipeline stage": its module (here a script outside drgan) and one entry in
    stage_table.PIPELINE, after analyze, are the whole change. The toy stage runs as its own process on what analyze
    wrote, takes its STAGE.KEY=VALUE, refuses the keys the pipeline sets, is skipped once done, runs again with
    redo=toy, and report.md and pipeline.json summarise it. (The stages before it are faked, as above.)"""
    (tmp_path / "drgan_toy_pipeline_stage.py").write_text(TOY_STAGE)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    after = stage_table.STAGES.index("analyze") + 1
    monkeypatch.setattr(stage_table, "PIPELINE", [*stage_table.PIPELINE[:after], TOY, *stage_table.PIPELINE[after:]])
    assert pipeline.STAGES == ("profile", "train", "generate", "segment", "finetune", "analyze", "toy", "evaluate")
    with pytest.raises(ConfigError, match="toy.out is set by the pipeline.*python -m drgan_toy_pipeline_stage"):
        settings(tmp_path, "toy.out=/elsewhere")

    images_folder(tmp_path / "images")
    fake = FakeStages(monkeypatch, real=("toy",))
    lines = []
    pipeline.run(settings(tmp_path, "toy.greeting=hi"), echo=lines.append)
    out = tmp_path / "out"
    particles = out / "analyze" / "particles.csv"
    assert fake.names() == ["profile", "train", "generate", "segment", "analyze", "toy"]
    assert fake.calls[-1] == ["toy", f"particles={particles}", f"out={out / 'toy'}", "greeting=hi"]
    assert json.loads((out / "toy" / "count.json").read_text()) == {"lines": 1, "greeting": "hi"}  # its own process
    assert "[6/6] toy: done in" in lines[-2] and lines[-2].endswith(": 1 line(s) counted, hi")
    record = json.loads((out / "pipeline.json").read_text())["stages"]["toy"]
    assert record["state"] == "done" and record["summary"]["line"] == "1 line(s) counted, hi"
    report = (out / "report.md").read_text()
    assert "| [toy](#toy) | done |" in report and "| 1 line(s) counted, hi |" in report
    section = report.split("\n## toy\n")[1]
    assert section.startswith("\ncounts the lines of the particle table.\n\n**1 line(s) counted, hi**\n")
    assert "Look at: [the count](toy/count.json).\n" in section and "lines.png" not in section
    assert f"python -m drgan_toy_pipeline_stage particles={particles} out={out / 'toy'} greeting=hi\n" in section

    fake.calls, lines = [], []
    pipeline.run(settings(tmp_path, "toy.greeting=hi"), echo=lines.append)
    assert fake.calls == [] and any(line.startswith("[6/6] toy: done (") and "skipped" in line for line in lines)

    pipeline.run(settings(tmp_path, "toy.greeting=again", "redo=toy"), echo=lines.append)
    assert fake.names() == ["toy"]
    assert json.loads((out / "toy" / "count.json").read_text())["greeting"] == "again"


# --- the real thing, tiny (slow) ---------------------------------------------------------------------------


def _benchmark_tiny() -> list[str]:
    """The tiny chain's settings, as benchmarks/pipeline.py --tiny runs them (one list for both)."""
    import importlib.util

    path = Path(__file__).parent.parent / "benchmarks" / "pipeline.py"
    spec = importlib.util.spec_from_file_location("drgan_benchmark_pipeline", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return list(module.TINY)


TINY = _benchmark_tiny()


def _run_pipeline(cwd: Path, argv: list[str], wait: bool = True):
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}
    command = [sys.executable, "-m", "drgan.pipeline", *argv]
    if wait:
        return subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=900)
    return subprocess.Popen(command, cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _images(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((folder / "images").glob("*.png"))}


@pytest.mark.slow  # a whole tiny pipeline (~1 min) plus a killed and resumed generation and one stage by hand
def test_a_tiny_pipeline_killed_inside_a_stage_resumes_to_the_single_commands_result(tmp_path):
    sys.path.insert(0, str(Path(__file__).parent))
    from test_profile import synthetic

    folder = tmp_path / "images"
    folder.mkdir()
    rng = np.random.default_rng(4)
    for i in range(3):
        Image.fromarray((synthetic("bright", rng)[0] * 255).round().astype(np.uint8)).save(folder / f"im{i}.png")
    argv = [f"data.dir={folder}", "name=tiny", f"out={tmp_path / 'run'}", "mlflow=false", *TINY]
    done = _run_pipeline(tmp_path, argv)
    assert done.returncode == 0, done.stderr[-3000:]
    run = tmp_path / "run"
    state = json.loads((run / "pipeline.json").read_text())
    ran = ["profile", "train", "generate", "segment", "analyze"]  # no corrected outlines: no finetune stage
    assert [s for s in pipeline.STAGES if s in state["stages"]] == ran
    assert [state["stages"][s]["state"] for s in ran] == ["done"] * 5
    assert "[5/5] analyze: done" in done.stdout and (run / "analyze" / "particles.csv").is_file()
    page = (run / "report.html").read_text()  # the report for any browser: the stages' figures inside it
    assert "<table>" in page and page.count("data:image/png;base64,") >= 3 and 'src="http' not in page
    reference = _images(run / "generate")

    # Killed while generating (a SIGKILL of the pipeline takes its stage along), then rerun: the same pairs.
    process = _run_pipeline(tmp_path, [*argv, "redo=generate"], wait=False)
    deadline = time.time() + 300

    def generating() -> bool:  # the redo has removed the old pairs and the stage has written some new ones
        record = json.loads((run / "pipeline.json").read_text())["stages"].get("generate", {})
        return record.get("state") == "running" and len(list((run / "generate" / "images").glob("syn_*.png"))) >= 3

    while time.time() < deadline and not generating():
        time.sleep(0.02)
    process.kill()
    process.wait()
    time.sleep(1.0)  # the stage dies with its parent
    partial = len(list((run / "generate" / "images").glob("syn_*.png")))
    assert 3 <= partial < len([k for k in reference if k.startswith("syn_")])
    again = _run_pipeline(tmp_path, argv)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "[3/5] generate: resuming" in again.stdout and "[2/5] train: done" in again.stdout
    assert _images(run / "generate") == reference

    # The stage's command as the report prints it, run by hand into another folder: the same pairs.
    generate = json.loads((run / "pipeline.json").read_text())["stages"]["generate"]["args"]
    by_hand = [a if not a.startswith("out=") else f"out={tmp_path / 'by_hand'}" for a in generate]
    single = subprocess.run([sys.executable, "-m", "drgan.generate", *by_hand], cwd=tmp_path, capture_output=True,
                            text=True, timeout=600)  # fmt: skip
    assert single.returncode == 0, single.stderr[-3000:]
    assert _images(tmp_path / "by_hand") == reference


def test_the_report_says_which_contact_weight_the_segmenter_trained_with_and_why(tmp_path):
    from drgan.pipeline.report import segment_summary

    metrics = {"epoch": 12, "stop_reason": "max_epochs", "val/dsc": 0.9, "split_calibration": None,
               "contact_weight": {"value": 10.0, "why": "auto: 10, bright particles"}}  # fmt: skip
    (tmp_path / "metrics.json").write_text(json.dumps(metrics))
    assert "contact weight 10 (auto: 10, bright particles)" in segment_summary(tmp_path)["line"]
    metrics.pop("contact_weight")  # a run from before the key: the line without it
    (tmp_path / "metrics.json").write_text(json.dumps(metrics))
    assert "contact weight" not in segment_summary(tmp_path)["line"]


def test_the_report_shows_the_generated_sets_noise_against_the_real_and_its_spp(tmp_path):
    from drgan.pipeline.report import generate_summary

    manifest = {"counts": {"synthetic": 1000, "dropped": 7, "background": 200, "partial_background": 0},
                "config": {"grey_spread": True, "renderer": {"spp": 16}}}  # fmt: skip
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    before = generate_summary(tmp_path)  # a set from before the noise check: the line without it
    assert "noise" not in before["line"] and before["spp"] == 16 and before["noise"] is None
    noise = {"background": {"real": 0.01, "generated": 0.058, "ratio": 5.8},
             "particles": {"real": 0.03, "generated": None, "ratio": None}}  # fmt: skip
    (tmp_path / "noise_check.json").write_text(json.dumps(noise))
    summary = generate_summary(tmp_path)
    assert summary["line"].endswith("; fine noise background 5.8 x real")  # particles not measured: left out
    assert summary["metrics"]["generate/noise_background_x_real"] == 5.8
    assert "generate/noise_particles_x_real" not in summary["metrics"]


# --- progress lines ----------------------------------------------------------------------------------------

SLOW_STAGE = '''"""A toy stage that reports eight steps of work through drgan.core.progress, as the real stages do."""

import sys
import time
from pathlib import Path

from drgan.core.progress import Task

args = dict(arg.split("=", 1) for arg in sys.argv[1:])
with Task("counting", 8, "steps") as task:
    for step in range(8):
        time.sleep(0.4)
        task.advance()
out = Path(args["out"])
out.mkdir(parents=True, exist_ok=True)
(out / "done.txt").write_text("8")
'''


def test_the_pipeline_says_what_a_running_stage_does_its_time_left_and_the_runs_end(tmp_path, monkeypatch):
    """While a stage runs, the pipeline prints a line every `progress` seconds: the stage's own task from its progress
    file (count, share, time so far and left), and the whole run's estimated time left and end (the later stages'
    typical times at this run's pace)."""
    (tmp_path / "drgan_toy_slow_stage.py").write_text(SLOW_STAGE)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    slow = stage_table.StageSpec(
        "slow", wire=lambda c: [f"out={c.folder('slow')}"], keys=("out",), done=lambda c: c.folder("slow") / "done.txt",
        summary=lambda folder: {}, what="counts slowly", module="drgan_toy_slow_stage", typical_minutes=1.0,
    )  # fmt: skip
    after = stage_table.STAGES.index("analyze") + 1
    monkeypatch.setattr(stage_table, "PIPELINE", [*stage_table.PIPELINE[:after], slow, *stage_table.PIPELINE[after:]])
    images_folder(tmp_path / "images")
    FakeStages(monkeypatch, real=("slow",))
    lines: list[str] = []
    pipeline.run(settings(tmp_path, "progress=0.25"), echo=lines.append)
    ticks = [line for line in lines if line.startswith("[6/6] slow: ") and "the whole run" in line]
    pattern = (r"\[6/6\] slow: counting [1-7]/8 steps \(\d+ %\), \d+ s in the stage, ~\d+ s left; the whole run: "
               r"~\d+ s left, ends ~\d\d:\d\d \(estimate\)")  # fmt: skip
    reported = [line for line in ticks if re.fullmatch(pattern, line)]
    assert reported, ticks
    # the stage is the last: the whole run's time left is the stage's own estimate
    for line in reported:
        own, whole = re.findall(r"~(\d+) s left", line)
        assert own == whole
    assert json.loads((tmp_path / "out" / "slow" / "progress.json").read_text())["finished"] is True


def test_the_whole_runs_estimate_scales_the_later_stages_by_the_runs_pace():
    from drgan.core.progress import Report
    from drgan.pipeline import progress_line

    # done stages took twice their typical time: the rest is expected at that pace
    factor = progress_line.pace([(60.0, 150.0), (600.0, 1170.0)])
    assert factor == pytest.approx(1320 / 660)
    assert progress_line.pace([]) == 1.0 and progress_line.pace([(60.0, 6000.0)]) == 8.0  # kept within range
    report = Report("rendering pairs", 250, 1000, "pairs", 80.0, 300.0)
    assert progress_line.stage_left(report, 300.0, 100.0, factor) == 300.0  # the stage's own estimate first
    assert progress_line.stage_left(None, 300.0, 100.0, factor) == 500.0  # else its scaled typical time less run
    assert progress_line.stage_left(None, 300.0, 900.0, factor) == 0.0
    finished = Report("segmenting", 3, 3, "images", 20.0, 0.0, finished=True)  # between tasks: the typical time again
    assert progress_line.stage_left(finished, 300.0, 100.0, factor) == 500.0
    assert progress_line.whole_left(300.0, [60.0 * factor, 60.0 * factor]) == pytest.approx(300.0 + 240.0)
    line = progress_line.line(3, 6, "generate", report, 80.0, 300.0, 540.0, now=0.0)
    assert line.startswith("[3/6] generate: rendering pairs 250/1000 pairs (25 %), 80 s in the stage, ~5.0 min left; "
                           "the whole run: ~9.0 min left, ends ~")  # fmt: skip
    line = progress_line.line(1, 6, "profile", finished, 25.0, 35.0, 900.0, now=0.0)
    assert line.startswith("[1/6] profile: segmenting 3/3 images done, 25 s in the stage, ~35 s left; the whole run: ")


def test_a_quick_profile_of_a_small_folder_does_not_shorten_the_gans_estimate(tmp_path):
    """The profile reads every image (its time is the folder's size), the GAN's is its settings': a 10-s profile of 4
    small images sets no pace, so the estimate of the run left when the GAN starts is the typical times as they are;
    a GAN that took twice its typical time doubles the estimate of the paced stages after it, not of analyze."""
    images_folder(tmp_path / "images")
    s = settings(tmp_path, "progress=1")
    built = stages.build_stages(s, None)
    state = tracking.State(tmp_path / "state.json")
    lines: list[str] = []
    typical = {st.name: 60.0 * st.spec.typical_minutes for st in built}
    state.update("profile", state="done", seconds=10.0)
    runner._Watch(built, state, 2, time.perf_counter(), lines.append).tick()
    expected = sum(typical[n] for n in ("train", "generate", "segment", "analyze"))
    whole = re.search(r"the whole run: ~([\d.]+) (s|min) left", lines[-1])
    assert float(whole.group(1)) * (60 if whole.group(2) == "min" else 1) == pytest.approx(expected, abs=6)

    state.update("train", state="done", seconds=2 * typical["train"])
    runner._Watch(built, state, 3, time.perf_counter(), lines.append).tick()
    expected = 2 * (typical["generate"] + typical["segment"]) + typical["analyze"]
    whole = re.search(r"the whole run: ~([\d.]+) (s|min) left", lines[-1])
    assert float(whole.group(1)) * (60 if whole.group(2) == "min" else 1) == pytest.approx(expected, abs=6)


def test_the_report_says_when_the_count_on_the_users_images_moved_the_split(tmp_path):
    from drgan.pipeline.report import segment_summary

    was = {"split_seeds": "hmaxima", "split_depth": 4.0, "split_core": 0.5}
    guard = {"images": 4, "classical": 274, "chosen_count": 217, "count": 285, "moved": True, "from": was}
    calibration = {"split_seeds": "hmaxima", "split_depth": 1.0, "split_core": 0.5, "real_count": guard}
    metrics = {"epoch": 12, "stop_reason": "max_epochs", "val/dsc": 0.9, "split_calibration": calibration}
    (tmp_path / "metrics.json").write_text(json.dumps(metrics))
    line = segment_summary(tmp_path)["line"]
    assert "split depth 1.0 core 0.5 (depth 4.0 core 0.5 on the generated pairs counted 217" in line
    assert "against the classical 274" in line
    guard["moved"] = False
    (tmp_path / "metrics.json").write_text(json.dumps(metrics))
    assert "counted" not in segment_summary(tmp_path)["line"]
