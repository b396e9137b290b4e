"""The pipeline on SLURM (launcher=slurm), many samples at once (batch=), and the checks before anything is submitted.

The tests marked ``slurm`` run tiny pipelines through a real scheduler: `make test-slurm` (and .ci/run) starts a
one-node SLURM on the machine first (scripts/slurm_local.sh); without one they are skipped, saying why. The others run
in the default suite: the settings, the errors before submission, the batch file, the study summary."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from drgan.core.errors import ConfigError, DataError
from drgan.pipeline import batch, parse_settings, slurm
from drgan.pipeline.submit import job_words, submit_run

ROOT = Path(__file__).parent.parent


def _tiny() -> list[str]:
    import importlib.util

    spec = importlib.util.spec_from_file_location("drgan_benchmark_pipeline", ROOT / "benchmarks" / "pipeline.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


BENCH = _tiny()
# every job asks for one CPU and a little memory: the one-node test cluster has 2 CPUs and no GPU
SMALL = ["slurm.gpus=0", "slurm.cpus=1", "slurm.mem=2G", "slurm.time=30"]


def _images(folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    Image.fromarray((rng.random((32, 32)) * 255).astype(np.uint8)).save(folder / "a.png")


# --- settings and the checks before anything is submitted (no SLURM needed) ----------------------------------


def test_slurm_requests_come_from_the_config_then_every_stage_then_one_stage(tmp_path):
    _images(tmp_path / "im")
    s = parse_settings([f"data.dir={tmp_path / 'im'}", "name=x", "launcher=slurm", "slurm.gpus=0",
                        "slurm.train.gpus=2", "slurm.partition=gpu", "slurm.profile.partition=cpu",
                        "slurm.train.time=12:00:00", "slurm.options=[--constraint=a100,--exclusive]"])  # fmt: skip
    r = s.slurm.stages
    assert (r["train"].gpus, r["segment"].gpus, r["profile"].gpus) == (2, 0, 0)
    assert (r["train"].partition, r["profile"].partition) == ("gpu", "cpu")
    assert r["train"].time == "12:00:00" and r["analyze"].time == "2:00:00"  # the YAML's where nothing is given
    options = s.slurm.job_options("train")
    assert "--gpus=2" in options and "--partition=gpu" in options and options[-2:] == ["--constraint=a100",
                                                                                         "--exclusive"]  # fmt: skip
    defaults = parse_settings([f"data.dir={tmp_path / 'im'}", "name=x"]).slurm.stages
    assert defaults["train"].gpus == 1 and defaults["profile"].gpus == 0  # the GPU where the GAN and U-Net train


@pytest.mark.parametrize(
    "word, message",
    [
        ("slurm.train.gpu=1", "slurm.train.gpu: not a resource key"),
        ("slurm.nodes=2", "slurm.nodes: not a SLURM setting"),
        ("slurm.train.mem=lots", "expected sbatch's --mem"),
        ("slurm.time=two hours", "expected sbatch's --time"),
        ("slurm.cpus=0", "cpus >= 1"),
        ("slurm.shards=0", "slurm.shards"),
        ("launcher=pbs", "launcher='pbs': expected one of local, slurm"),
        ("shard=0/2", "expected only=generate"),
    ],
)
def test_bad_slurm_settings_are_refused_naming_the_key(tmp_path, word, message):
    _images(tmp_path / "im")
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        parse_settings([f"data.dir={tmp_path / 'im'}", "name=x", "launcher=slurm", word])


def test_without_sbatch_on_the_path_nothing_is_submitted_and_the_message_names_it(tmp_path, monkeypatch):
    _images(tmp_path / "im")
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    s = parse_settings([f"data.dir={tmp_path / 'im'}", "name=x", f"out={tmp_path / 'run'}", "launcher=slurm"])
    with pytest.raises(ConfigError, match="sbatch, squeue, scontrol not on the PATH"):
        submit_run(s)
    assert not (tmp_path / "run").exists()


def test_a_jobs_command_repeats_the_users_words_with_absolute_inputs_and_one_stage(tmp_path):
    _images(tmp_path / "im")
    argv = [f"data.dir={tmp_path / 'im'}", "name=x", "launcher=slurm", "redo=train", "slurm.gpus=0",
            "train.seed=3", "+generate.foo=1", "mlflow=false"]  # fmt: skip
    words = job_words(parse_settings(argv), "segment")
    assert words[:3] == [sys.executable, "-m", "drgan.pipeline"]
    assert f"data.dir={(tmp_path / 'im').resolve()}" in words and f"out={Path('runs/pipeline/x').resolve()}" in words
    assert "train.seed=3" in words and "+generate.foo=1" in words and "mlflow=false" in words
    assert not any(w.startswith(("slurm.", "redo=", "launcher=slurm")) for w in words)
    assert words[-2:] == ["launcher=local", "only=segment"]
    parse_settings(words[3:])  # the job's own words parse


def test_only_runs_one_stage_and_refuses_when_the_one_before_is_not_done(tmp_path):
    from drgan.core.errors import DrganError
    from drgan.pipeline import run

    _images(tmp_path / "im")
    s = parse_settings([f"data.dir={tmp_path / 'im'}", "name=x", f"out={tmp_path / 'run'}", "mlflow=false",
                        "only=generate"])  # fmt: skip
    with pytest.raises(DrganError, match="only=generate: the stage before it, profile, is not done"):
        run(s, echo=lambda line: None)


def _csv(path: Path, rows: list[dict]) -> Path:
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return path


def test_a_batch_file_is_checked_row_by_row_before_anything_runs(tmp_path):
    _images(tmp_path / "a")
    good = _csv(tmp_path / "study.csv", [{"name": "s1", "dir": "a"}, {"name": "s2", "dir": str(tmp_path / "a")}])
    samples = batch.read_samples(good)
    assert [s.name for s in samples] == ["s1", "s2"] and samples[0].dir == (tmp_path / "a").resolve()
    missing = _csv(tmp_path / "m.csv", [{"name": "s1", "dir": "a"}, {"name": "s2", "dir": "nowhere"}])
    with pytest.raises(DataError, match=r"line 3 \(s2\): dir=nowhere: no such folder"):
        batch.run_batch([f"batch={missing}", f"out={tmp_path / 'study'}"], run=None)
    assert not (tmp_path / "study").exists()
    twice = _csv(tmp_path / "t.csv", [{"name": "s1", "dir": "a"}, {"name": "s1", "dir": "a"}])
    with pytest.raises(DataError, match="the name 's1' is taken"):
        batch.read_samples(twice)
    columns = _csv(tmp_path / "c.csv", [{"sample": "s1", "folder": "a"}])
    with pytest.raises(DataError, match="expected a header row with columns name and dir"):
        batch.read_samples(columns)
    with pytest.raises(ConfigError, match="data.dir= with batch="):
        batch.parse_batch([f"batch={good}", f"data.dir={tmp_path}"])


def _fake_sample(folder: Path, diameters: list[float], check: float, classical: list[float] | None = None) -> None:
    (folder / "analyze").mkdir(parents=True)
    whole = {"axis_ratio": 1.0, "touches_border": "False", "sized": "True"}
    rows = [{"id": i, "image": "a", "equivalent_diameter_px": d, **whole} for i, d in enumerate(diameters)]
    cut = {"axis_ratio": 1.0, "touches_border": "True", "sized": "False"}  # cut by the border: counted, not sized
    rows.append({"id": 99, "image": "a", "equivalent_diameter_px": 500.0, **cut})
    _csv(folder / "analyze" / "particles.csv", rows)
    median = float(np.median(diameters))
    summary = {"images": 2, "unit": "px", "closed_loop": {"median_error": {"value": check}},
               "statistics": {"count": {"value": len(diameters) + 1},
                              "median_diameter": {"value": median, "low": median - 1.0, "high": median + 1.0}}}  # fmt: skip
    if classical:  # its analyze trusted the classical sizes (particles_classical.csv, diameters at half contrast)
        rows = [{"id": i, "image": "a", "half_contrast_diameter_px": d, **whole} for i, d in enumerate(classical)]
        _csv(folder / "analyze" / "particles_classical.csv", rows)
        middle = float(np.median(classical))
        summary["trusted"] = "classical"
        summary["classical"] = {"statistics": {"count": {"value": len(classical)},
                                               "median_diameter": {"value": middle, "low": middle, "high": middle}}}  # fmt: skip
    (folder / "analyze" / "summary.json").write_text(json.dumps(summary))
    (folder / "pipeline.json").write_text(json.dumps({"stages": {"analyze": {"state": "done"}}}))


def test_the_study_summary_compares_the_samples_sizes_from_their_folders(tmp_path):
    _images(tmp_path / "a")
    study = tmp_path / "study"
    _fake_sample(study / "small", [10.0, 11.0, 12.0, 13.0, 14.0], 0.05)
    _fake_sample(study / "large", [20.0, 22.0, 24.0, 26.0, 28.0, 30.0], -0.02)
    _fake_sample(study / "merged", [40.0, 44.0], 0.01, classical=[20.0, 21.0, 22.0])
    rows = [{"name": "small", "dir": "a"}, {"name": "large", "dir": "a"}, {"name": "merged", "dir": "a"},
            {"name": "lost", "dir": "a"}]  # fmt: skip
    b = batch.parse_batch([f"batch={_csv(tmp_path / 'study.csv', rows)}", f"out={study}"])
    summary = batch.write_summary(b, {"lost": "exit code 1"})
    by = {r["sample"]: r for r in summary["samples"]}
    assert by["small"]["median"] == 12.0 and by["large"]["sized"] == 6  # the border particle is not sized
    assert by["small"]["p10"] == pytest.approx(np.percentile([10, 11, 12, 13, 14], 10))
    assert by["lost"]["median"] is None
    text = (study / "summary.md").read_text()
    assert "| small | done | 2 | 6 | 12.0 [11.0, 13.0] | 10.4-13.6 | px | segmenter | +5.0% |" in text
    # a sample whose report trusts the classical sizes: those in the study too
    assert by["merged"]["median"] == 21.0 and by["merged"]["sized"] == 3 and by["merged"]["sizes"] == "classical"
    assert "| lost | failed |" in text and "- lost failed: exit code 1" in text
    assert (study / "sizes.png").stat().st_size > 10_000
    table = list(csv.DictReader(open(study / "summary.csv")))
    assert [r["sample"] for r in table] == ["small", "large", "merged", "lost"] and float(table[1]["median"]) == 25.0


# --- through a real SLURM ---------------------------------------------------------------------------------


def _slurm_up() -> str | None:
    """None when a SLURM takes jobs here (started by scripts/slurm_local.sh where needed), else why not."""
    if shutil.which("sinfo") and subprocess.run(["sinfo", "-h"], capture_output=True).returncode == 0:
        return None
    if os.geteuid() != 0:
        return "no SLURM here and not root to start one (run `sudo bash scripts/slurm_local.sh`, then the tests)"
    started = subprocess.run(["bash", str(ROOT / "scripts" / "slurm_local.sh")], capture_output=True, text=True)
    if started.returncode != 0:
        return f"slurmctld could not start here: {(started.stderr or started.stdout).strip()[-300:]}"
    return None


@pytest.fixture(scope="module")
def cluster():
    why = _slurm_up()
    if why:
        pytest.skip(why)


@pytest.fixture(scope="module")
def tiny_set(tmp_path_factory):
    return BENCH.tiny_set(tmp_path_factory.mktemp("tiny") / "set")


def _pipeline(cwd: Path, argv: list[str], env: dict | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
    result = subprocess.run([sys.executable, "-m", "drgan.pipeline", *argv], cwd=cwd, env=env, capture_output=True,
                            text=True, timeout=600)  # fmt: skip
    return result


def _wait(out: Path, stages: list[str], timeout: float = 600.0) -> dict:
    """pipeline.json once each of ``stages`` is done and every job of the run has ended, or a stage's job has ended
    without it (SLURM forgets nothing for an hour). A job marks its stage done a moment before it exits, so done alone
    would race its COMPLETED."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        state = json.loads((out / "pipeline.json").read_text()) if (out / "pipeline.json").is_file() else {}
        records = [(state.get("stages") or {}).get(s, {}) for s in stages]
        jobs = [r.get("job") for r in records if r.get("state") != "done"]
        if all(r.get("state") == "done" for r in records):
            every = [r["job"] for r in (state.get("stages") or {}).values() if r.get("job")]
            if not any(st.active for st in slurm.job_states(every).values()):
                return state
            time.sleep(1.0)
            continue
        if jobs and all(j and not st.active for j, st in slurm.job_states([j for j in jobs if j]).items()):
            return state
        time.sleep(1.0)
    raise AssertionError(f"{out}: stages {stages} not finished in {timeout:.0f} s")


def _files(folder: Path, pattern: str) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.glob(pattern))}


@pytest.mark.slurm
def test_a_tiny_pipeline_through_slurm_matches_the_same_run_made_locally(cluster, tiny_set, tmp_path):
    words = [f"data.dir={tiny_set / 'images'}", f"annotated={tiny_set}", "name=tiny", "mlflow=false", "progress=2",
             *BENCH.TINY]  # fmt: skip
    submitted = _pipeline(tmp_path, [*words, f"out={tmp_path / 'slurm'}", "launcher=slurm", *SMALL])
    assert submitted.returncode == 0, submitted.stderr[-3000:]
    assert "6 job(s) submitted to SLURM" in submitted.stdout
    local = _pipeline(tmp_path, [*words, f"out={tmp_path / 'local'}"])  # meanwhile, the same settings here
    assert local.returncode == 0, local.stderr[-3000:]
    state = _wait(tmp_path / "slurm", ["evaluate"])
    stages = state["stages"]
    assert [stages[s]["state"] for s in stages] == ["done"] * 6, stages
    jobs = [stages[s]["job"] for s in stages]
    assert len(set(jobs)) == 6 and all(st.state == "COMPLETED" for st in slurm.job_states(jobs).values())
    status = _pipeline(tmp_path, [*words, f"out={tmp_path / 'slurm'}", "launcher=slurm", *SMALL, "status"])
    assert status.returncode == 0 and f"| train | done | {stages['train']['job']} | COMPLETED |" in status.stdout
    # the same commands as the local run's, but for the folder
    ours = json.loads((tmp_path / "local" / "pipeline.json").read_text())["stages"]
    for name in stages:
        assert [a.replace(str(tmp_path / "slurm"), "OUT") for a in stages[name]["args"]] == [
            a.replace(str(tmp_path / "local"), "OUT") for a in ours[name]["args"]
        ]
    # the same results: the exact labels and the particles alike; images up to the float rounding of two GAN
    # trainings (a parallel reduction's order: two local runs differ there too), at most 1 grey level in 1 % of pixels
    for sub in ("generate/masks", "generate/labels"):
        assert _files(tmp_path / "slurm" / sub, "*.png") == _files(tmp_path / "local" / sub, "*.png")
    a, b = (_files(tmp_path / run / "generate" / "images", "*.png") for run in ("slurm", "local"))
    assert a.keys() == b.keys()
    diff = np.concatenate([np.abs(_grey(a[k]) - _grey(b[k])).ravel() for k in a])
    assert diff.max() <= 1 and (diff > 0).mean() < 0.01
    for name in ("analyze/particles.csv", "evaluate/results.csv"):
        assert (tmp_path / "slurm" / name).read_text() == (tmp_path / "local" / name).read_text().replace(
            str(tmp_path / "local"), str(tmp_path / "slurm")
        )
    assert "report.md" in os.listdir(tmp_path / "slurm") and (tmp_path / "slurm" / "slurm" / "train.sh").is_file()


def _close(a, b, rel: float = 1e-7) -> bool:
    """Two JSON values equal, their floats up to ``rel``."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_close(a[k], b[k], rel) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_close(x, y, rel) for x, y in zip(a, b))
    if isinstance(a, float) or isinstance(b, float):
        return isinstance(a, (int, float)) and isinstance(b, (int, float)) and abs(a - b) <= rel * max(abs(a), abs(b))
    return a == b


def _grey(data: bytes) -> np.ndarray:
    import io

    return np.asarray(Image.open(io.BytesIO(data)), dtype=np.int16)


@pytest.mark.slurm
def test_a_training_job_cancelled_mid_way_resumes_from_its_checkpoint_on_the_rerun(cluster, tiny_set, tmp_path):
    out = tmp_path / "run"
    words = [f"data.dir={tiny_set / 'images'}", "name=tinyc", f"out={out}", "mlflow=false", "launcher=slurm", *SMALL,
             *BENCH.TINY, "train.trainer.max_epochs=6", "train.data.steps_per_epoch=6",
             "~train.callbacks.early_stopping"]  # fmt: skip
    first = _pipeline(tmp_path, words)
    assert first.returncode == 0, first.stderr[-3000:]
    again = _pipeline(tmp_path, words)  # while its jobs run: refused, naming them
    assert again.returncode == 1 and "is submitted already" in again.stderr
    last = out / "train" / "checkpoints" / "last.ckpt"
    deadline = time.time() + 300
    while time.time() < deadline and not last.is_file():
        time.sleep(0.2)
    assert last.is_file(), "train wrote no last.ckpt"
    state = json.loads((out / "pipeline.json").read_text())["stages"]
    train_job, later = state["train"]["job"], [state[s]["job"] for s in ("generate", "segment", "analyze")]
    subprocess.run(["scancel", train_job], check=True)
    state = _wait(out, ["train"])
    assert slurm.job_states([train_job])[train_job].state == "CANCELLED"
    assert state["stages"]["train"]["state"] != "done"
    deadline = time.time() + 60  # the jobs after it: cancelled by SLURM, their dependency never satisfied
    while time.time() < deadline and any(st.active for st in slurm.job_states(later).values()):
        time.sleep(0.5)
    assert not any(st.active for st in slurm.job_states(later).values())
    resumed = _pipeline(tmp_path, words)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "profile" not in resumed.stdout.split("submitted")[0].split("train:")[0]  # the done profile is not redone
    state = _wait(out, ["analyze"])
    assert all(state["stages"][s]["state"] == "done" for s in ("profile", "train", "generate", "segment", "analyze"))
    killed = (out / "slurm" / f"train-{train_job}.log").read_text()
    assert "pipeline: interrupted; run the same command again to resume" in killed  # SIGTERM: stopped cleanly
    log = Path(state["stages"]["train"]["log"]).read_text()
    assert "train: resuming" in log and f"Restored all states from the checkpoint at {last}" in log
    metrics = json.loads((out / "train" / "metrics.json").read_text())
    assert metrics["epoch"] == 6  # every epoch, none twice


@pytest.mark.slurm
def test_a_two_sample_batch_on_slurm_with_a_sharded_generate_and_its_study_summary(cluster, tiny_set, tmp_path):
    other = BENCH.tiny_set(tmp_path / "other", seed=0, n_train=3)  # another sample: one image more
    table = _csv(tmp_path / "samples.csv", [{"name": "first", "dir": str(tiny_set / "images")},
                                            {"name": "second", "dir": str(other / "images")}])  # fmt: skip
    study = tmp_path / "study"
    store = f"sqlite:///{tmp_path / 'mlflow.db'}"
    words = [f"batch={table}", f"out={study}", "launcher=slurm", *SMALL, "slurm.shards=2", *BENCH.TINY]
    submitted = _pipeline(tmp_path, words, env={"MLFLOW_TRACKING_URI": store})
    assert submitted.returncode == 0, submitted.stderr[-3000:]
    assert "after the 2 shards of job array" in submitted.stdout and "the summary: job" in submitted.stdout
    deadline = time.time() + 900
    while time.time() < deadline and not (study / "summary.md").is_file():
        time.sleep(1.0)
    assert (study / "summary.md").is_file(), "no study summary"
    time.sleep(2.0)
    summary = (study / "summary.md").read_text()  # (the tiny segmenter's numbers mean nothing: the plumbing)
    assert "| first | done | 3 |" in summary and "| second | done | 4 |" in summary, summary
    for name in ("first", "second"):
        assert (study / name / "generate" / "manifest_shard_1.json").is_file()  # rendered by the array's two tasks

    # the two shards' set is the one a single generate makes from the same GAN
    args = json.loads((study / "first" / "pipeline.json").read_text())["stages"]["generate"]["args"]
    single = [a if not a.startswith("out=") else f"out={tmp_path / 'single'}" for a in args]
    done = subprocess.run([sys.executable, "-m", "drgan.generate", *single], cwd=tmp_path, capture_output=True,
                          text=True, timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    manifest = json.loads((study / "first" / "generate" / "manifest.json").read_text())
    ours = json.loads((tmp_path / "single" / "manifest.json").read_text())
    assert manifest["entries"] == ours["entries"] and len(ours["entries"]) == 41  # 40 pairs, 1 background
    for entry in ours["entries"]:  # every file of the set (the shards may render a few beyond it): images, masks
        for kind, path in entry["files"].items():  # and labels byte for byte; the records' measured floats (contrast,
            a, b = (study / "first" / "generate" / path), (tmp_path / "single" / path)  # ...) up to the rounding of
            if kind == "meta":  # a reduction over the job's 1 thread against this process's 2
                assert _close(json.loads(a.read_text()), json.loads(b.read_text())), path
            else:
                assert a.read_bytes() == b.read_bytes(), path

    # one MLflow store: the study run, each sample's run below it, the stages below those
    import mlflow

    client = mlflow.MlflowClient(tracking_uri=store)
    experiment = client.get_experiment_by_name("study_samples")
    runs = client.search_runs([experiment.experiment_id], max_results=100)
    by_id = {r.info.run_id: r for r in runs}
    top = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    assert [r.info.run_name for r in top] == ["samples"] and top[0].info.status == "FINISHED"  # closed by the summary
    samples = [r for r in runs if r.data.tags.get("mlflow.parentRunId") == top[0].info.run_id]
    assert sorted(r.info.run_name for r in samples) == ["first", "second"]
    for sample in samples:
        stages = [r.info.run_name for r in runs if r.data.tags.get("mlflow.parentRunId") == sample.info.run_id]
        # profile, generate, analyze by the pipeline; train and segment log their own runs, named by the stage too;
        # a segment seed retried by the agreement check (the tiny U-Net may be weak) is one more run, named by its seed
        metrics = json.loads((study / sample.info.run_name / "segment" / "metrics.json").read_text())
        retries = [f"segment/seed={a['seed']}" for a in metrics["agreement"]["attempts"][1:]]
        assert sorted(stages) == sorted(["profile", "train", "generate", "segment", "analyze", *retries])
        assert by_id[sample.info.run_id].info.status == "FINISHED"


@pytest.mark.slurm
def test_an_unknown_partition_or_a_request_the_cluster_cannot_run_is_refused_before_any_job(cluster, tmp_path):
    _images(tmp_path / "im")
    base = [f"data.dir={tmp_path / 'im'}", "name=x", f"out={tmp_path / 'run'}", "mlflow=false", "launcher=slurm"]
    before = subprocess.run(["squeue", "-h", "-o", "%i"], capture_output=True, text=True).stdout
    wrong = _pipeline(tmp_path, [*base, *SMALL, "slurm.train.partition=nowhere"])
    assert wrong.returncode == 1 and "slurm.train.partition=nowhere: no such partition" in wrong.stderr
    too_big = _pipeline(tmp_path, [*base, *SMALL, "slurm.train.gpus=1"])  # the test node has no GPU
    assert too_big.returncode == 1 and "the train stage's SLURM request" in too_big.stderr, too_big.stderr
    assert "slurm.train.gpus=0" in too_big.stderr
    after = subprocess.run(["squeue", "-h", "-o", "%i"], capture_output=True, text=True).stdout
    assert before == after and not (tmp_path / "run" / "slurm").exists()


@pytest.mark.slow  # two tiny pipelines side by side (~2 min on 2 cores)
def test_a_local_batch_runs_two_samples_side_by_side_and_resumes_to_the_same_summary(tiny_set, tmp_path):
    table = _csv(tmp_path / "samples.csv", [{"name": "one", "dir": str(tiny_set / "images"), "annotated": str(tiny_set)},
                                            {"name": "two", "dir": str(tiny_set / "images")}])  # fmt: skip
    study = tmp_path / "study"
    words = [f"batch={table}", f"out={study}", "parallel=2", "mlflow=false", *BENCH.TINY]
    done = _pipeline(tmp_path, words)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "sample one started" in done.stdout and "sample two started" in done.stdout
    assert done.stdout.index("sample two started") < done.stdout.index("sample one done")  # side by side
    assert "[6/6] evaluate: done" in (study / "one" / "pipeline.log").read_text()
    assert "[5/5] analyze: done" in (study / "two" / "pipeline.log").read_text()
    summary = (study / "summary.md").read_text()
    assert "| one | done | 3 |" in summary and "| two | done | 3 |" in summary
    again = _pipeline(tmp_path, words)  # everything done: skipped, the same summary
    assert again.returncode == 0 and (study / "summary.md").read_text() == summary
    assert "done (" in (study / "one" / "pipeline.log").read_text().split("[1/6] profile:")[-1]


def test_close_compares_json_records_up_to_float_rounding():
    assert _close({"a": [1.0, {"b": 2.0}], "s": "x"}, {"a": [1.0 + 1e-12, {"b": 2.0}], "s": "x"})
    assert not _close({"a": [1.0]}, {"a": [1.001]}) and not _close({"a": 1}, {"b": 1}) and not _close("x", "y")
