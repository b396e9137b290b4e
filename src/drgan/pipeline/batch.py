"""Many samples in one command: ``python -m drgan.pipeline batch=samples.csv [STAGE.KEY=VALUE ...]``.

``samples.csv`` has one row per sample (a synthesis batch, a temperature, a time point: one folder each), columns
``name`` and ``dir`` and optionally ``annotated`` (an annotated set scored at the end, as ``annotated=`` of one run).
Each sample is one pipeline run (every other word of the command line applies to all of them) into
``STUDY/NAME/``, ``STUDY`` being ``out=`` (default runs/studies/<the CSV's name>). Every sample's inputs are checked
before the first stage of any runs (a missing folder names its row). Locally the samples run one after the other, or
``parallel=N`` at a time (each its own process, its console in ``STUDY/NAME/pipeline.log``); with ``launcher=slurm``
all are submitted at once, and a last job waits for all of them. Then the study summary, ``STUDY/summary.md``,
``summary.csv`` and ``sizes.png``: per sample its particles, median diameter with its 95 % interval over images, the
10th-90th percentiles and the segmenter's closed-loop size error; the figure puts their size distributions side by
side. A failed sample does not stop the others; the summary names it. Rerun the same command to resume them all.
MLflow: one experiment ``study_<study>``, a study run, each sample's parent run below it, its stages below that.
"""

from __future__ import annotations

import csv
import io
import json
import math
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drgan.core.errors import ConfigError, DataError, DrganError
from drgan.core.io import write_bytes, write_with
from drgan.pipeline import slurm
from drgan.pipeline.settings import Settings, parse_settings
from drgan.pipeline.stages import check_inputs, check_stage_settings

BATCH_KEYS = ("batch", "parallel")
SUMMARY = "summary"  # only=summary: the study summary alone (the last SLURM job)
STUDY_RUN_FILE = "mlflow_study_run_id.txt"
COLUMNS = ("name", "dir", "annotated")


@dataclass(frozen=True)
class Sample:
    name: str
    dir: Path
    annotated: Path | None
    row: int  # its line in the CSV (for messages)


@dataclass(frozen=True)
class Batch:
    csv: Path
    study: str
    out: Path
    parallel: int
    samples: list[Sample]
    words: list[str]  # the command line's words for every sample (without batch, parallel, out, only=summary)
    only_summary: bool
    launcher: str
    mlflow: bool


def is_batch(argv: Sequence[str]) -> bool:
    return any(w.split("=", 1)[0] == "batch" for w in argv)


def read_samples(path: Path) -> list[Sample]:
    """The rows of ``path``; every error names the file, the row and what was expected."""
    if not path.is_file():
        raise DataError(f"pipeline: batch={path}: no such file (expected a CSV with columns name, dir[, annotated])")
    rows = list(csv.DictReader(io.StringIO(path.read_text(encoding="utf-8-sig"))))
    header = [c.strip() for c in (rows[0].keys() if rows else [])]
    if not rows or "name" not in header or "dir" not in header:
        raise DataError(
            f"pipeline: batch={path}: expected a header row with columns name and dir (and optionally annotated) "
            f"and one row per sample; found {header or 'no rows'}"
        )
    unknown = [c for c in header if c not in COLUMNS]
    if unknown:
        raise DataError(f"pipeline: batch={path}: unknown column(s) {unknown} (the columns: {', '.join(COLUMNS)})")
    base = path.parent
    samples, seen = [], set()
    for number, row in enumerate(rows, 2):
        row = {k.strip(): (v or "").strip() for k, v in row.items() if k}
        name, folder = row.get("name", ""), row.get("dir", "")
        if not name or not folder:
            raise DataError(f"pipeline: batch={path}, line {number}: every row needs a name and a dir")
        if name in seen:
            raise DataError(f"pipeline: batch={path}, line {number}: the name {name!r} is taken by an earlier row")
        seen.add(name)
        directory = _from_csv(base, folder)
        if not directory.is_dir():
            raise DataError(
                f"pipeline: batch={path}, line {number} ({name}): dir={folder}: no such folder (expected a folder "
                "of images; a relative path is read from the CSV's folder)"
            )
        annotated = _from_csv(base, row["annotated"]) if row.get("annotated") else None
        samples.append(Sample(name, directory, annotated, number))
    return samples


def _from_csv(base: Path, text: str) -> Path:
    """A path of the CSV: absolute as it is, relative from the CSV's folder."""
    return Path(text) if Path(text).is_absolute() else (base / text).expanduser().resolve()


def parse_batch(argv: Sequence[str]) -> Batch:
    own: dict[str, str] = {}
    words = []
    for word in argv:
        key, _, value = word.partition("=")
        if key in (*BATCH_KEYS, "out", "only") and (key != "only" or value == SUMMARY):
            own[key] = value
        elif key in ("data.dir", "name", "annotated"):
            raise ConfigError(f"pipeline: {key}= with batch=: each sample's comes from its row of the CSV")
        else:
            words.append(word)
    path = Path(own["batch"]).expanduser().resolve()
    try:
        parallel = int(own.get("parallel", "1"))
    except ValueError:
        parallel = 0
    if parallel < 1:
        raise ConfigError(f"pipeline: parallel={own.get('parallel')!r}: expected how many samples run at once (>= 1)")
    study = path.stem
    out = Path(own["out"]).expanduser().resolve() if own.get("out") else Path("runs/studies").resolve() / study
    launcher = next((w.split("=", 1)[1] for w in words if w.startswith("launcher=")), "local")
    mlflow = next((w.split("=", 1)[1] for w in words if w.startswith("mlflow=")), "true").lower() in ("true", "1")
    return Batch(path, study, out, parallel, read_samples(path), words, "only" in own, launcher, mlflow)


def sample_settings(b: Batch, sample: Sample, parent_run: str | None) -> Settings:
    return parse_settings(sample_words(b, sample, parent_run))


def sample_words(b: Batch, sample: Sample, parent_run: str | None) -> list[str]:
    return [
        f"data.dir={sample.dir}", f"name={sample.name}", f"out={b.out / sample.name}",
        *([f"annotated={sample.annotated}"] if sample.annotated else []),
        f"experiment=study_{b.study}", *([f"parent_run={parent_run}"] if parent_run else []), *b.words,
    ]  # fmt: skip


def run_batch(
    argv: Sequence[str], run: Callable[[Settings, Callable], dict], echo: Callable[[str], None] = print
) -> dict:
    """Every sample's pipeline (``run``: drgan.pipeline.runner.run; or their submission), then the study summary;
    the summary's content."""
    b = parse_batch(argv)
    if b.only_summary:  # the last SLURM job of a batch: the summary, and the study run closed
        summary = write_summary(b)
        done = all(row.get("state") == "done" for row in summary["samples"])
        StudyRun(b).finish(summary, "FINISHED" if done else "FAILED")
        return summary
    settings = [sample_settings(b, sample, None) for sample in b.samples]  # names and keys, before anything runs
    for s in settings:
        check_inputs(s)
    check_stage_settings(settings[0])  # the same stage keys for every sample
    if b.launcher == "slurm":
        slurm.require_tools()
    study = StudyRun(b)
    settings = [sample_settings(b, sample, study.run_id) for sample in b.samples]
    echo(f"study {b.study}: {len(settings)} samples into {b.out}")
    if b.launcher == "slurm":
        return _submit_batch(b, settings, echo)
    failures = _run_local(b, settings, run, echo)
    summary = write_summary(b, failures)
    study.finish(summary, "FAILED" if failures else "FINISHED")
    echo(f"study {b.study}: the summary: {b.out / 'summary.md'}")
    return summary


def _run_local(b: Batch, settings: list[Settings], run: Callable, echo: Callable[[str], None]) -> dict[str, str]:
    """The samples' pipelines, ``b.parallel`` at a time; sample -> why it failed."""
    failures: dict[str, str] = {}
    if b.parallel == 1:
        for s in settings:
            echo(f"study {b.study}: sample {s.name}")
            try:
                run(s, echo)
            except DrganError as error:
                failures[s.name] = str(error)
                echo(f"study {b.study}: sample {s.name} failed: {error}")
        return failures
    waiting, running = list(zip(b.samples, settings)), {}
    while waiting or running:
        while waiting and len(running) < b.parallel:
            sample, s = waiting.pop(0)
            log = s.out / "pipeline.log"
            log.parent.mkdir(parents=True, exist_ok=True)
            handle = open(log, "ab")
            words = sample_words(b, sample, s.parent_run)
            process = subprocess.Popen([*slurm.python_command(), *words], stdout=handle, stderr=subprocess.STDOUT)
            running[s.name] = (process, handle)
            echo(f"study {b.study}: sample {s.name} started (its console: {log})")
        time.sleep(1.0)
        for name, (process, handle) in list(running.items()):
            if process.poll() is not None:
                handle.close()
                del running[name]
                if process.returncode:
                    failures[name] = f"exit code {process.returncode} (its console: {b.out / name / 'pipeline.log'})"
                echo(f"study {b.study}: sample {name} " + ("done" if not process.returncode else "failed"))
    return failures


def _submit_batch(b: Batch, settings: list[Settings], echo: Callable[[str], None]) -> dict:
    from drgan.pipeline.submit import submit_run

    finals = []
    for s in settings:
        echo(f"study {b.study}: sample {s.name}")
        ids = submit_run(s, echo)
        finals += ids[-1:]
    workdir = Path.cwd()
    folder = b.out / "slurm"
    words = [*slurm.python_command(), f"batch={b.csv}", f"out={b.out}", *b.words, f"only={SUMMARY}"]
    words = [w for w in words if not w.startswith("launcher=")]
    script = slurm.job_script(folder / "summary.sh", workdir, words)
    requests = settings[0].slurm
    options = [o for o in requests.job_options("analyze") if not o.startswith("--gpus")] if requests else []
    job = slurm.submit(script, f"drgan-study-{b.study}", options, str(folder / "summary-%j.log"), workdir, finals,
                       "afterany")  # fmt: skip
    echo(
        f"study {b.study}: the summary: job {job}, after {len(finals)} sample job(s); it writes {b.out / 'summary.md'}"
    )
    return {"jobs": finals, "summary_job": job}


# --- the study's MLflow run ----------------------------------------------------------------------------------


class StudyRun:
    """The study's MLflow run (experiment study_<study>; its id in STUDY/mlflow_study_run_id.txt, so a rerun and the
    summary job continue it). Store errors only warn, as the pipeline's own tracking."""

    def __init__(self, b: Batch):
        self.client = self.run_id = None
        if not b.mlflow:
            return
        try:
            import mlflow

            from drgan.launch.loggers import tracking_store
            from drgan.pipeline.tracking import experiment_id_of

            uri, _ = tracking_store([])
            self.client = mlflow.MlflowClient(tracking_uri=uri)
            id_file = b.out / STUDY_RUN_FILE
            if id_file.is_file():
                self.run_id = id_file.read_text().strip()
                self.client.update_run(self.run_id, status="RUNNING")
            else:
                experiment = experiment_id_of(self.client, uri, f"study_{b.study}")
                run = self.client.create_run(experiment, run_name=b.study,
                                             tags={"batch": str(b.csv), "output_dir": str(b.out)})  # fmt: skip
                self.run_id = run.info.run_id
                write_bytes(id_file, self.run_id.encode())
        except Exception as error:  # noqa: BLE001  (a tracking store must never stop a study)
            print(f"warning: MLflow: no study run ({str(error).splitlines()[0]})", file=sys.stderr)
            self.client = self.run_id = None

    def finish(self, summary: dict, status: str) -> None:
        if self.client is None:
            return
        try:
            for row in summary.get("samples", []):
                if isinstance(row.get("median"), float) and math.isfinite(row["median"]):
                    self.client.log_metric(self.run_id, f"median_diameter/{row['sample']}", row["median"])
            for name in ("summary.md", "summary.csv", "sizes.png"):
                path = Path(summary["out"]) / name
                if path.is_file():
                    self.client.log_artifact(self.run_id, str(path))
            self.client.set_terminated(self.run_id, status)
        except Exception as error:  # noqa: BLE001
            print(f"warning: MLflow: study run not closed ({str(error).splitlines()[0]})", file=sys.stderr)


# --- the study summary -----------------------------------------------------------------------------------------


def sample_row(name: str, folder: Path) -> dict:
    """One sample's line of the study: its analyze and segment outputs read back (empty where they are missing)."""
    stats = (json.loads((folder / "analyze" / "summary.json").read_text()) if (folder / "analyze" / "summary.json").is_file() else {})  # fmt: skip
    row = {"sample": name, "images": stats.get("images"), "unit": stats.get("unit", "px")}
    # the sizes the sample's report gives: the classical ones where its analyze trusted them (particles_classical.csv)
    classical = stats.get("trusted") == "classical" and (stats.get("classical") or {}).get("statistics")
    row["sizes"] = "classical" if classical else "segmenter"
    given = classical or stats.get("statistics") or {}
    median = given.get("median_diameter") or {}
    row["median"], row["low"], row["high"] = (median.get(k) for k in ("value", "low", "high"))
    row["particles"] = (given.get("count") or {}).get("value")
    diameters = (
        sized_diameters(folder / "analyze" / "particles_classical.csv", row["unit"], "half_contrast_diameter")
        if classical
        else sized_diameters(folder / "analyze" / "particles.csv", row["unit"])
    )
    row["p10"], row["p90"] = (float(np.percentile(diameters, q)) if diameters.size else None for q in (10, 90))
    row["sized"] = int(diameters.size)
    check = stats.get("closed_loop") or {}
    row["closed_loop_median_error"] = (check.get("median_error") or {}).get("value")
    state = json.loads((folder / "pipeline.json").read_text()) if (folder / "pipeline.json").is_file() else {}
    stage_states = {k: v.get("state") for k, v in (state.get("stages") or {}).items()}
    row["state"] = "done" if stage_states.get("analyze") == "done" else (
        next((f"{k} {v}" for k, v in stage_states.items() if v != "done"), "not started"))  # fmt: skip
    row["diameters"] = diameters
    return row


def sized_diameters(path: Path, unit: str, name: str = "equivalent_diameter") -> np.ndarray:
    """The diameters (column NAME_UNIT) of an analyze particle table's particles not cut by the border."""
    from drgan.metrics.statistics import read_particle_table

    sized = [p.whole().diameter for p in read_particle_table(path, f"{name}_{unit}").values()]
    values = np.concatenate(sized) if sized else np.zeros(0)
    return values[np.isfinite(values)]


def _cell(value, fmt: str = "{:.1f}") -> str:
    return "–" if not isinstance(value, (int, float)) or value != value else fmt.format(value)


def write_summary(b: Batch, failures: dict[str, str] | None = None) -> dict:
    """STUDY/summary.md, summary.csv and sizes.png from the samples' folders; returns what they hold."""
    rows = [sample_row(s.name, b.out / s.name) for s in b.samples]
    failures = failures or {}
    units = {r["unit"] for r in rows if r["median"] is not None}
    lines = [
        f"# Study {b.study}: {len(rows)} samples ({b.csv})", "",
        "Median equivalent diameter per sample with its 95 % bootstrap interval over the sample's images, the 10th-90th "
        "percentiles of its sized particles (not cut by the image border), and the segmenter's own median-diameter "
        "error on held-out generated images (closed loop: how far its sizes can be trusted). sizes: whose sizes the "
        "sample's report gives (the segmenter's, or the classical segmentation's where its analyze trusted those). "
        "Each sample's report: NAME/report.md.", "",
        "| sample | state | images | particles | median diameter [95 %] | p10-p90 | unit | sizes | closed-loop median "
        "error |",
        "|---|---|---|---|---|---|---|---|---|",
    ]  # fmt: skip
    for r in rows:
        state = "failed" if r["sample"] in failures else r["state"]
        lines.append(
            f"| {r['sample']} | {state} | {_cell(r['images'], '{:.0f}')} | {_cell(r['particles'], '{:.0f}')} | "
            f"{_cell(r['median'])} [{_cell(r['low'])}, {_cell(r['high'])}] | {_cell(r['p10'])}-{_cell(r['p90'])} | "
            f"{r['unit']} | {r['sizes']} | {_cell(r['closed_loop_median_error'], '{:+.1%}')} |"
        )
    if len(units) > 1:
        lines += ["", f"Units differ between samples ({', '.join(sorted(units))}): compare only those in one unit."]
    for name, why in failures.items():
        lines += ["", f"- {name} failed: {why}"]
    if (b.out / "sizes.png").exists() or any(r["diameters"].size for r in rows):
        lines += ["", "![size distributions](sizes.png)"]
    write_bytes(b.out / "summary.md", ("\n".join(lines) + "\n").encode())
    fields = ["sample", "state", "images", "particles", "sized", "median", "low", "high", "p10", "p90", "unit",
              "sizes", "closed_loop_median_error"]  # fmt: skip
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    write_bytes(b.out / "summary.csv", buf.getvalue().encode())
    if any(r["diameters"].size for r in rows):
        _figure(b.out / "sizes.png", rows)
    return {"out": str(b.out), "samples": [{k: v for k, v in r.items() if k != "diameters"} for r in rows]}


def _figure(path: Path, rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [r for r in rows if r["diameters"].size]
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.2))
    for r in shown:
        d = np.sort(r["diameters"])
        left.step(d, np.arange(1, d.size + 1) / d.size, where="post", label=f"{r['sample']} ({d.size})")
    unit = shown[0]["unit"]
    left.set_xlabel(f"equivalent diameter ({unit})")
    left.set_ylabel("fraction of particles below")
    left.legend(fontsize=8)
    y = np.arange(len(shown))
    right.boxplot([r["diameters"] for r in shown], positions=y, orientation="horizontal", whis=(10, 90), showfliers=False,
                  widths=0.5)  # fmt: skip
    for i, r in enumerate(shown):
        if isinstance(r["low"], float) and r["low"] == r["low"]:
            right.errorbar(r["median"], i, xerr=[[r["median"] - r["low"]], [r["high"] - r["median"]]], fmt="o",
                           color="C3", capsize=4)  # fmt: skip
    right.set_yticks(y, [r["sample"] for r in shown])
    right.set_xlabel(f"equivalent diameter ({unit}); box: quartiles, whiskers 10-90 %, red: median [95 %]")
    fig.tight_layout()
    write_with(path, lambda handle: fig.savefig(handle, format="png", dpi=110))
    plt.close(fig)
