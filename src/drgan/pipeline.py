"""`python -m drgan.pipeline data.dir=DIR name=NAME [annotated=DATASET]`: from a folder of images to particle numbers.

Runs the stages a user would run by hand, each as its own command (``python -m drgan.STAGE``, a child process) into
its own folder under ``out`` (default runs/pipeline/NAME):

    profile/    drgan.profile   the images' polarity, sizes, noise ...; the material in drgan_conf/material/NAME.yaml
    train/      drgan.train     the GAN with that material (material=NAME, found on the pipeline's search path)
    generate/   drgan.generate  1,000 annotated pairs and real background patches from the best epoch
    segment/    drgan.segment   the segmenter trained on them
    analyze/    drgan.analyze   particles.csv, histograms, overlays of every image of DIR
    evaluate/   drgan.evaluate  (annotated=DATASET only) scores and statistics against its masks

and writes ``report.md`` (what each stage chose and why, with links to its figures) and ``pipeline.json`` (each
stage's command, times and state). The settings a stage gets are its own defaults (the best measured; the pipeline's
config adds a few, conf/pipeline/pipeline.yaml) plus what the command line gives it as ``STAGE.KEY=VALUE``.

Resuming: run the same command again. A stage is done when its process exited 0 (recorded in pipeline.json) and its
main output exists; done stages are skipped, the first that is not resumes (drgan.train and drgan.segment from their
``last.ckpt``, drgan.generate from the pairs already written), so a kill at any moment loses at most the step in
progress. A done stage whose settings have changed since is not rerun silently: the pipeline stops and names the
difference; ``redo=STAGE`` runs that stage and every later one again. Two pipelines on one folder are refused.

Before any stage runs, the inputs are checked: the folder holds images, the name is usable, every STAGE key names a
stage and composes with that stage's config (a typo fails in seconds, not after the GAN), and the annotated images
are none of the images training reads (compared by content).
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from drgan.errors import ConfigError, DataError, DrganError
from drgan.io import write_bytes, write_json

log = logging.getLogger("drgan.pipeline")

CONFIG = Path(__file__).parent / "conf" / "pipeline" / "pipeline.yaml"
STAGES = ("profile", "train", "generate", "segment", "analyze", "evaluate")
OWN_KEYS = ("data.dir", "name", "annotated", "out", "redo", "mlflow")
STATE_FILE = "pipeline.json"
REPORT_FILE = "report.md"
LOCK_FILE = ".pipeline.lock"
RESUME_KEY = "ckpt_path"  # the resume flag a stage gets when it has a checkpoint; not a setting


# --- settings ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Settings:
    data_dir: Path
    name: str
    annotated: Path | None
    out: Path
    redo: str | None
    mlflow: bool
    stages: dict[str, dict[str, str]]  # stage -> {override key (with +/++/~ prefix): value}, in order


def _value_text(value) -> str:
    """A YAML default as the text of a Hydra override value."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(_value_text(v) for v in value) + "]"
    return str(value)


def _split_override(text: str) -> tuple[str, str | None]:
    """``key=value`` -> (key, value); ``~key`` (a deletion) -> (``~key``, None)."""
    if text.startswith("~") and "=" not in text:
        return text, None
    if "=" not in text:
        raise ConfigError(f"pipeline: {text!r}: expected KEY=VALUE (e.g. data.dir=/path/to/images or train.seed=1)")
    key, value = text.split("=", 1)
    return key, value


def _stage_key(key: str) -> tuple[str, str] | None:
    """(stage, the key as that stage's command takes it) for ``[+|++|~]STAGE.KEY``; None for the pipeline's own."""
    prefix = re.match(r"^(\+\+|\+|~)?", key).group(0)
    rest = key[len(prefix) :]
    stage, dot, inner = rest.partition(".")
    if dot and stage in STAGES:
        if not inner:
            raise ConfigError(f"pipeline: {key!r}: expected {stage}.KEY=VALUE")
        return stage, prefix + inner
    return None


def parse_settings(argv: Sequence[str], config_path: Path = CONFIG) -> Settings:
    """The pipeline's settings from its YAML and the command line (``KEY=VALUE`` words); checks names, not files."""
    base = yaml.safe_load(config_path.read_text())
    own = {"data.dir": base["data"]["dir"], **{k: base[k] for k in OWN_KEYS if k != "data.dir"}}
    stages: dict[str, dict[str, str]] = {
        s: {str(k): _value_text(v) for k, v in (base["stages"].get(s) or {}).items()} for s in STAGES
    }
    for word in argv:
        key, value = _split_override(word)
        routed = _stage_key(key)
        if routed is not None:
            stage, inner = routed
            stages[stage].pop(inner.lstrip("+~"), None)  # one value per key: the command line's replaces the YAML's
            stages[stage][inner] = value
        elif key in OWN_KEYS:
            own[key] = value
        else:
            raise ConfigError(
                f"pipeline: {key}: not a setting of the pipeline ({', '.join(OWN_KEYS)}) nor a stage's key "
                f"(STAGE.KEY=VALUE with STAGE one of {', '.join(STAGES)}; e.g. train.seed=1)"
            )
    if not own["data.dir"]:
        raise ConfigError("pipeline: give data.dir=DIR (the folder of your images)")
    name = own["name"]
    if not name or not re.fullmatch(r"[A-Za-z0-9_\-]+", str(name)):
        raise ConfigError(f"pipeline: name={name!r}: expected a name of letters, digits, _ or - (e.g. name=my_tem)")
    from drgan.configs import shipped_materials

    if str(name) in shipped_materials():
        raise ConfigError(
            f"pipeline: name={name}: the run's material takes its name, and a material drgan ships has it "
            f"({', '.join(shipped_materials())}); choose another name, e.g. name={name}_mine"
        )
    redo = own["redo"]
    if redo in ("null", "None", ""):
        redo = None
    if redo is not None and redo not in STAGES:
        raise ConfigError(f"pipeline: redo={redo!r}: expected a stage, one of {', '.join(STAGES)}")
    annotated = own["annotated"]
    annotated = None if annotated in (None, "null", "None", "") else Path(str(annotated)).expanduser()
    out = own["out"]
    out = Path("runs/pipeline") / str(name) if out in (None, "null", "None", "") else Path(str(out)).expanduser()
    mlflow = own["mlflow"]
    mlflow = mlflow if isinstance(mlflow, bool) else str(mlflow).lower() in ("true", "1", "yes")
    for stage, keys in stages.items():
        fixed = sorted(set(k.lstrip("+~") for k in keys) & set(PIPELINE_KEYS[stage]))
        if fixed:
            raise ConfigError(
                f"pipeline: {stage}.{fixed[0]} is set by the pipeline (it wires the stages' folders together); "
                f"set out= for another folder, or run python -m drgan.{stage} by hand"
            )
    return Settings(
        data_dir=Path(str(own["data.dir"])).expanduser().resolve(),
        name=str(name),
        annotated=annotated.resolve() if annotated else None,
        out=out.resolve(),
        redo=redo,
        mlflow=mlflow,
        stages=stages,
    )


# The keys the pipeline sets itself (each stage's folders and links); a user's STAGE.KEY for one of them is refused.
PIPELINE_KEYS = {
    "profile": ("data.dir", "name", "out", "conf_dir", "overwrite"),
    "train": ("material", "run_name", "hydra.run.dir", "hydra.searchpath", "parent_run", RESUME_KEY),
    "generate": ("ckpt", "out"),
    "segment": ("data", "real", "out", "name", "run_name", "parent_run", RESUME_KEY),
    "analyze": ("model", "images", "out"),
    "evaluate": ("model", "models", "data", "out"),
}


# --- the stages ---------------------------------------------------------------------------------------------


@dataclass
class Stage:
    """One stage: its command's module, its folder, the arguments the pipeline gives it, and the file whose
    presence (with a clean exit) says it is done."""

    name: str
    folder: Path
    wired: list[str]  # the pipeline's own arguments (folders, links)
    settings: list[str]  # defaults of the pipeline's config and the user's STAGE.KEY=VALUE
    done_file: Path
    resume: Callable[[], list[str]] = field(default=lambda: [])  # extra arguments of a resumed run

    @property
    def module(self) -> str:
        return f"drgan.{self.name}"

    def command(self) -> list[str]:
        return [sys.executable, "-m", self.module, *self.wired, *self.settings, *self.resume()]

    def recorded(self) -> list[str]:
        """What decides the stage's result: its arguments without the resume flag."""
        return [*self.wired, *self.settings]


def _last_checkpoint(folder: Path) -> Callable[[], list[str]]:
    return lambda: [f"{RESUME_KEY}=last"] if (folder / "checkpoints" / "last.ckpt").is_file() else []


def build_stages(s: Settings, parent_run: str | None, nm_per_px: float | None = None) -> list[Stage]:
    """The stages of a pipeline run, in order (evaluate only with ``annotated``)."""
    out, name = s.out, s.name
    conf = out / "drgan_conf"
    experiment = f"pipeline_{name}"
    links = [f"parent_run={parent_run}"] if parent_run else []
    logged = [f"logger.mlflow.experiment_name={experiment}", *links] if s.mlflow else ["logger=none"]

    def settings(stage: str) -> list[str]:
        return [key if value is None else f"{key}={value}" for key, value in s.stages[stage].items()]

    folders = {stage: out / stage for stage in STAGES}
    model = folders["segment"] / "checkpoints" / "last.ckpt"
    stages = [
        Stage(
            "profile",
            folders["profile"],
            [f"data.dir={s.data_dir}", f"name={name}", f"out={folders['profile']}", f"conf_dir={conf}",
             "overwrite=true"],
            settings("profile"),
            conf / "material" / f"{name}.yaml",
        ),
        Stage(
            "train",
            folders["train"],
            [f"material={name}", f"run_name={name}", f"hydra.run.dir={folders['train']}",
             f"hydra.searchpath=[file://{conf}]", *logged],
            settings("train"),
            folders["train"] / "metrics.json",
            _last_checkpoint(folders["train"]),
        ),
        Stage(
            "generate",
            folders["generate"],
            [f"ckpt={folders['train']}", f"out={folders['generate']}"],
            settings("generate"),
            folders["generate"] / "manifest.json",
        ),
        Stage(
            "segment",
            folders["segment"],
            [f"data={folders['generate']}", f"out={folders['segment']}", f"name={name}", f"run_name={name}", *logged],
            settings("segment"),
            folders["segment"] / "metrics.json",
            _last_checkpoint(folders["segment"]),
        ),
        Stage(
            "analyze",
            folders["analyze"],
            [f"model={model}", f"images={s.data_dir}", f"out={folders['analyze']}",
             *([f"nm_per_px={nm_per_px}"] if nm_per_px and "nm_per_px" not in s.stages["analyze"] else [])],
            settings("analyze"),
            folders["analyze"] / "particles.csv",
        ),
    ]  # fmt: skip
    if s.annotated is not None:
        subset = [] if (s.annotated / "split.json").is_file() else ["subset=all"]
        stages.append(
            Stage(
                "evaluate",
                folders["evaluate"],
                [f"model={model}", f"data={s.annotated}", f"out={folders['evaluate']}", *subset],
                settings("evaluate"),
                folders["evaluate"] / "results.md",
            )
        )
    return stages


CONFIG_NAMES = {"profile": "profile", "train": "train", "generate": "generate", "segment": "segment",
                "analyze": "analyze", "evaluate": "evaluate"}  # fmt: skip


def check_stage_settings(s: Settings) -> None:
    """Compose each stage's config with the user's keys for it: an unknown key or a wrong type fails now."""
    from drgan.configs import compose

    for stage, keys in s.stages.items():
        if not keys:
            continue
        overrides = [key if value is None else f"{key}={value}" for key, value in keys.items()]
        try:
            compose(overrides, config_name=CONFIG_NAMES[stage])
        except Exception as error:  # noqa: BLE001  (Hydra's errors come in several types; all mean a bad key)
            first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
            raise ConfigError(f"pipeline: the {stage} settings {overrides} do not fit drgan.{stage}: {first}") from None


# --- inputs -----------------------------------------------------------------------------------------------


def _digest(path: Path) -> str:
    return hashlib.sha1(path.read_bytes()).hexdigest()


def training_images(data_dir: Path) -> list[Path]:
    """The images training reads: the split's train ids (split.json beside or above the folder), else all."""
    from drgan.data.images import default_split, list_images, read_split

    split = default_split(data_dir)
    return list_images(data_dir, read_split(split)["train"]) if split else list_images(data_dir)


def check_inputs(s: Settings) -> dict:
    """Everything about the inputs that can fail, before any stage runs; returns a summary for the report."""
    from drgan.data.images import list_images, read_split

    if not s.data_dir.is_dir():
        raise DataError(f"pipeline: data.dir={s.data_dir}: no such folder (expected a folder of images)")
    images = list_images(s.data_dir)  # a folder without images is named here
    train = training_images(s.data_dir)
    summary = {"images": len(images), "training_images": len(train)}
    if s.annotated is not None:
        if not (s.annotated / "images").is_dir() or not (s.annotated / "masks").is_dir():
            raise DataError(
                f"pipeline: annotated={s.annotated}: expected an annotated dataset folder with images/ and masks/ "
                "(and split.json: its test ids are scored; without it, every image)"
            )
        split = s.annotated / "split.json"
        ids = read_split(split)["test"] if split.is_file() else None
        scored = list_images(s.annotated / "images", ids)
        if not scored:
            raise DataError(f"pipeline: annotated={s.annotated}: no image to score (its split's test list is empty)")
        seen = {_digest(p): p for p in train}
        shared = [(p, seen[d]) for p in scored if (d := _digest(p)) in seen]
        if shared:
            raise DataError(
                f"pipeline: annotated={s.annotated}: {len(shared)} of its scored image(s) are training images too "
                f"(e.g. {shared[0][0]} = {shared[0][1]}); images scored at the end must never train anything: give "
                "data.dir a split.json whose test ids they are, or other images"
            )
        summary["annotated_images"] = len(scored)
    return summary


# --- state, lock, MLflow ----------------------------------------------------------------------------------


class State:
    """pipeline.json: per stage its recorded arguments, state (running / done / failed), times."""

    def __init__(self, path: Path):
        self.path = path
        self.data = json.loads(path.read_text()) if path.is_file() else {"stages": {}}

    def stage(self, name: str) -> dict:
        return self.data["stages"].get(name, {})

    def update(self, name: str, **values) -> None:
        self.data["stages"].setdefault(name, {}).update(values)
        write_json(self.path, self.data)

    def forget(self, name: str) -> None:
        self.data["stages"].pop(name, None)
        write_json(self.path, self.data)


@contextlib.contextmanager
def folder_lock(out: Path):
    out.mkdir(parents=True, exist_ok=True)
    with open(out / LOCK_FILE, "w") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ConfigError(
                f"pipeline: another drgan.pipeline is running on {out} (its lock {out / LOCK_FILE} is held); "
                "wait for it, or give this one another name="
            ) from None
        yield


class Tracker:
    """The MLflow parent run of a pipeline (its id kept in out/mlflow_parent_run_id.txt, so a resumed pipeline
    continues it) and the child runs of the stages that log nothing themselves. Any store error only warns."""

    ID_FILE = "mlflow_parent_run_id.txt"

    def __init__(self, s: Settings):
        self.client = self.parent = None
        if not s.mlflow:
            return
        try:
            import mlflow

            from drgan.loggers import store_lock, tracking_store

            uri, _ = tracking_store([f"hydra.searchpath=[file://{s.out / 'drgan_conf'}]"])
            self.client = mlflow.MlflowClient(tracking_uri=uri)
            with store_lock(uri):
                experiment = self.client.get_experiment_by_name(f"pipeline_{s.name}")
                experiment_id = (
                    experiment.experiment_id if experiment else self.client.create_experiment(f"pipeline_{s.name}")
                )
            id_file = s.out / self.ID_FILE
            previous = id_file.read_text().strip() if id_file.is_file() else None
            if previous:
                self.client.update_run(previous, status="RUNNING")
                self.parent = previous
            else:
                run = self.client.create_run(
                    experiment_id, run_name=s.name, tags={"data_dir": str(s.data_dir), "output_dir": str(s.out)}
                )
                self.parent = run.info.run_id
                write_bytes(id_file, self.parent.encode())
            self.experiment_id = experiment_id
        except Exception as error:  # noqa: BLE001  (a tracking store must never stop the pipeline)
            log.warning("MLflow: no parent run (%s); the stages run without it", str(error).splitlines()[0])
            self.client = self.parent = None

    def child(self, stage: Stage, seconds: float, metrics: Mapping[str, float], artifacts: Sequence[Path]) -> None:
        """A finished child run for a stage that has no MLflow run of its own."""
        if self.client is None:
            return
        try:
            run = self.client.create_run(
                self.experiment_id,
                run_name=stage.name,
                tags={"mlflow.parentRunId": self.parent, "stage": stage.name, "output_dir": str(stage.folder)},
            )
            rid = run.info.run_id
            self.client.log_param(rid, "command", " ".join(stage.recorded())[:6000])
            self.client.log_metric(rid, "time/wall_s", seconds)
            for key, value in metrics.items():
                self.client.log_metric(rid, key, float(value))
            for path in artifacts:
                if path.is_file():
                    self.client.log_artifact(rid, str(path))
            self.client.set_terminated(rid, "FINISHED")
        except Exception as error:  # noqa: BLE001
            log.warning("MLflow: stage %s not logged (%s)", stage.name, str(error).splitlines()[0])

    def finish(self, status: str, metrics: Mapping[str, float] = {}) -> None:
        if self.client is None:
            return
        try:
            for key, value in metrics.items():
                self.client.log_metric(self.parent, key, float(value))
            self.client.set_terminated(self.parent, status)
        except Exception as error:  # noqa: BLE001
            log.warning("MLflow: parent run not closed (%s)", str(error).splitlines()[0])


# --- running ---------------------------------------------------------------------------------------------


def _die_with_parent() -> None:
    """In the child, before exec: a SIGKILL of the pipeline kills the stage too (Linux), so that a rerun never
    finds the old stage still writing into its folder."""
    with contextlib.suppress(Exception):
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


def run_stage(stage: Stage, env: Mapping[str, str] | None = None) -> int:
    """Run one stage's command, its output on this console; the exit code."""
    process = subprocess.Popen(stage.command(), env=dict(env or os.environ), preexec_fn=_die_with_parent)
    try:
        return process.wait()
    except KeyboardInterrupt:  # the stage got the same Ctrl-C (one process group): let it stop cleanly
        try:
            process.wait(timeout=60)
        except subprocess.TimeoutExpired:
            process.kill()
        raise


def stale_difference(recorded: Sequence[str], current: Sequence[str]) -> str:
    old, new = set(recorded), set(current)
    parts = [f"now {a}" for a in current if a not in old] + [f"was {a}" for a in recorded if a not in new]
    return "; ".join(parts)


def run(s: Settings, echo: Callable[[str], None] = print) -> dict:
    """Run (or resume) the pipeline of ``s``; returns pipeline.json's content."""
    from drgan.pipeline_report import stage_summary, write_report

    inputs = check_inputs(s)
    check_stage_settings(s)
    with folder_lock(s.out):
        state = State(s.out / STATE_FILE)
        state.data.update({"data_dir": str(s.data_dir), "name": s.name, "inputs": inputs,
                           "annotated": str(s.annotated) if s.annotated else None})  # fmt: skip
        tracker = Tracker(s)
        stages = build_stages(s, tracker.parent)
        if s.redo is not None:
            for stage in stages[[st.name for st in stages].index(s.redo) :]:
                if stage.folder.exists():
                    shutil.rmtree(stage.folder)
                if stage.name == "profile":
                    stage.done_file.unlink(missing_ok=True)
                state.forget(stage.name)
        total, started = len(stages), time.perf_counter()
        status = "FAILED"
        try:
            for number, stage in enumerate(stages, 1):
                if stage.name == "analyze":  # the pixel size the profile read from the images' metadata
                    stage = build_stages(s, tracker.parent, _profiled_pixel_size(s.out))[number - 1]
                record = state.stage(stage.name)
                if record.get("state") == "done" and stage.done_file.is_file():
                    if record.get("args") != stage.recorded():
                        raise ConfigError(
                            f"pipeline: stage {stage.name} is done with other settings "
                            f"({stale_difference(record.get('args') or [], stage.recorded())}); run it and the "
                            f"stages after it again with redo={stage.name}, or keep it and drop the new settings"
                        )
                    echo(f"[{number}/{total}] {stage.name}: done ({_minutes(record.get('seconds'))}), skipped")
                    continue
                resumed = bool(record) or bool(stage.resume())
                echo(f"[{number}/{total}] {stage.name}: {'resuming' if resumed else 'starting'} "
                     f"(folder {stage.folder})")  # fmt: skip
                state.update(stage.name, state="running", args=stage.recorded(), started=time.time())
                begin = time.perf_counter()
                code = run_stage(stage)
                seconds = time.perf_counter() - begin + float(record.get("seconds_before") or 0.0)
                if code != 0:
                    state.update(stage.name, state="failed", exit_code=code, seconds_before=seconds)
                    raise DrganError(
                        f"pipeline: stage {stage.name} failed (exit code {code}; its message is above, its log in "
                        f"{stage.folder}); fix what it says and run the same command again to resume"
                    )
                if not stage.done_file.is_file():
                    state.update(stage.name, state="failed", exit_code=code, seconds_before=seconds)
                    raise DrganError(f"pipeline: stage {stage.name} exited 0 but wrote no {stage.done_file}")
                summary = stage_summary(stage.name, stage.folder, s)
                state.update(stage.name, state="done", seconds=seconds, seconds_before=None, finished=time.time(),
                             summary=summary)  # fmt: skip
                if stage.name not in ("train", "segment"):  # those two log MLflow runs of their own
                    tracker.child(stage, seconds, _numbers(summary), _artifacts(stage))
                echo(f"[{number}/{total}] {stage.name}: done in {_minutes(seconds)}"
                     + (f": {summary['line']}" if summary.get("line") else ""))  # fmt: skip
                write_report(s, state.data, stages)
            status = "FINISHED"
        except KeyboardInterrupt:
            status = "KILLED"
            echo("pipeline: interrupted; run the same command again to resume")
            raise
        finally:
            write_report(s, state.data, stages)
            tracker.finish(status, {"time/wall_s": time.perf_counter() - started})
        echo(f"pipeline {s.name}: done; the report: {s.out / REPORT_FILE}")
        return state.data


def _profiled_pixel_size(out: Path) -> float | None:
    path = out / "profile" / "profile.json"
    if not path.is_file():
        return None
    size = (json.loads(path.read_text()).get("pixel_size") or {}).get("nm_per_px")
    return float(size) if size else None


def _numbers(summary: dict) -> dict[str, float]:
    return {k: v for k, v in (summary.get("metrics") or {}).items() if isinstance(v, (int, float))}


def _artifacts(stage: Stage) -> list[Path]:
    names = {"profile": ["report.md", "profile.json"], "generate": ["manifest.json"],
             "analyze": ["particles.csv", "histograms.png"], "evaluate": ["results.md", "statistics.md"]}  # fmt: skip
    return [stage.folder / n for n in names.get(stage.name, [])]


def _minutes(seconds) -> str:
    if not isinstance(seconds, (int, float)):
        return "time unknown"
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.1f} min"


# --- command line ---------------------------------------------------------------------------------------------


def help_text() -> str:
    return (
        f"{__doc__.strip()}\n\nSettings (conf/pipeline/pipeline.yaml):\n\n{CONFIG.read_text()}\n"
        "Each stage's own keys: python -m drgan.STAGE --help (e.g. python -m drgan.train --help)."
    )


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if any(a in ("-h", "--help") for a in argv):
        print(help_text())
        return 0
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s] %(message)s", datefmt="%H:%M:%S")
    try:
        run(parse_settings(argv))
    except DrganError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
