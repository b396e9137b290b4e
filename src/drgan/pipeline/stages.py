"""The stages of a pipeline run (each its command, folder and done file), and the checks of the inputs and of each
stage's settings that run before any stage."""

from __future__ import annotations

import hashlib
import shutil
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from drgan.core.errors import ConfigError, DataError
from drgan.pipeline import stage_table
from drgan.pipeline.settings import Settings
from drgan.pipeline.stage_table import RESUME_KEY, Context, StageSpec

# --- the stages ---------------------------------------------------------------------------------------------


@dataclass
class Stage:
    """One stage of this run: its entry in stage_table.PIPELINE, its folder, the arguments the pipeline gives it, and
    the file whose presence (with a clean exit) says it is done."""

    spec: StageSpec
    folder: Path
    wired: list[str]  # the pipeline's own arguments (folders, links)
    settings: list[str]  # defaults of the pipeline's config and the user's STAGE.KEY=VALUE
    done_file: Path
    resume: Callable[[], list[str]] = field(default=lambda: [])  # extra arguments of a resumed run

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def module(self) -> str:
        return self.spec.command_module

    def command(self) -> list[str]:
        return [sys.executable, "-m", self.module, *self.wired, *self.settings, *self.resume()]

    def recorded(self) -> list[str]:
        """What decides the stage's result: its arguments without the resume flag."""
        return [*self.wired, *self.settings]


def _last_checkpoint(folder: Path) -> Callable[[], list[str]]:
    return lambda: [f"{RESUME_KEY}=last"] if (folder / "checkpoints" / "last.ckpt").is_file() else []


def build_stages(s: Settings, parent_run: str | None, nm_per_px: float | None = None) -> list[Stage]:
    """The stages of a pipeline run, in stage_table.PIPELINE's order (those whose ``wire`` gives None left out: evaluate
    without ``annotated``); ``nm_per_px``: the pixel size the profile found."""
    context = Context(s.out, s.name, s.data_dir, s.annotated, s.stages, nm_per_px, s.corrected)
    links = [f"parent_run={parent_run}"] if parent_run else []
    stages = []
    for spec in stage_table.PIPELINE:
        wired = spec.wire(context)
        if wired is None:
            continue
        folder = context.folder(spec.name)
        # a stage that logs its own MLflow run names it after the stage (the sample's name is its parent run's)
        logged = (
            [f"logger.mlflow.experiment_name={s.experiment_name}", f"logger.mlflow.run_name={spec.name}", *links]
            if s.mlflow
            else ["logger=none"]
        )
        stages.append(
            Stage(
                spec,
                folder,
                [*wired, *(logged if spec.mlflow_run else [])],
                [key if value is None else f"{key}={value}" for key, value in s.stages.get(spec.name, {}).items()],
                spec.done(context),
                _last_checkpoint(folder) if spec.resumes else (lambda: []),
            )
        )
    return stages


def is_done(stage: Stage, record: dict) -> bool:
    """A stage is done when its record says so and its done file exists (a deleted output is not done)."""
    return record.get("state") == "done" and stage.done_file.is_file()


def stale_difference(recorded: Sequence[str], current: Sequence[str]) -> str:
    old, new = set(recorded), set(current)
    parts = [f"now {a}" for a in current if a not in old] + [f"was {a}" for a in recorded if a not in new]
    return "; ".join(parts)


def _key(arg: str) -> str:
    return arg.split("=", 1)[0]


def stale_check(stage: Stage, record: dict) -> None:
    """A done stage whose settings changed since is not rerun silently: the difference, and what to do. Keys the
    pipeline wires itself that the record lacks altogether (a stage done by an older drgan, before it wired them)
    leave the stage done, with a note on stderr."""
    recorded, current = record.get("args") or [], stage.recorded()
    if recorded == current:
        return
    had = {_key(a) for a in recorded}
    added = [a for a in current if a not in recorded]
    if set(recorded) <= set(current) and all(_key(a) in stage.spec.keys and _key(a) not in had for a in added):
        print(
            f"pipeline: {stage.name} was done by an older drgan without {', '.join(added)}; kept (redo={stage.name} "
            "runs it with them)",
            file=sys.stderr,
        )
        return
    raise ConfigError(
        f"pipeline: stage {stage.name} is done with other settings ({stale_difference(recorded, current)}); run it "
        f"and the stages after it again with redo={stage.name}, or keep it and drop the new settings"
    )


def prepare_redo(s: Settings, state, stages: Sequence[Stage]) -> None:
    """``redo=STAGE``: that stage's folder and every later one's removed, their records in ``state`` forgotten."""
    if s.redo is None:
        return
    names = [st.name for st in stages]
    if s.redo not in names:
        raise ConfigError(
            f"pipeline: redo={s.redo}: this run has no such stage (its stages: {', '.join(names)}; evaluate "
            "runs only with annotated=DIR, finetune only with corrected=DIR)"
        )
    for stage in stages[names.index(s.redo) :]:
        forget(stage, state)


def forget(stage: Stage, state) -> None:
    """A stage's folder removed and its record in ``state`` forgotten: it runs again from scratch."""
    if stage.folder.exists():
        shutil.rmtree(stage.folder)
    stage.done_file.unlink(missing_ok=True)  # the profile's (the material) lies outside its folder
    state.forget(stage.name)


def done_after_pending(stages: Sequence[Stage], state) -> list[Stage]:
    """The done stages after the first stage that is not: their inputs will change when it runs (a stage added to a
    finished run, e.g. finetune with corrected=DIR; an output deleted), so they run again after it."""
    pending = next((k for k, st in enumerate(stages) if not is_done(st, state.stage(st.name))), None)
    if pending is None:
        return []
    return [st for st in stages[pending + 1 :] if is_done(st, state.stage(st.name))]


def check_stage_settings(s: Settings) -> None:
    """Compose each stage's config with the user's keys for it: an unknown key or a wrong type fails now."""
    from drgan.launch.configs import compose

    for stage, keys in s.stages.items():
        if not keys:
            continue
        overrides = [key if value is None else f"{key}={value}" for key, value in keys.items()]
        try:
            compose(overrides, config_name=stage_table.stage_spec(stage).config_name)
        except Exception as error:  # noqa: BLE001  (Hydra's errors come in several types; all mean a bad key)
            first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
            module = stage_table.stage_spec(stage).command_module
            raise ConfigError(f"pipeline: the {stage} settings {overrides} do not fit {module}: {first}") from None


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
        shared = same_images(scored, train)
        if shared:
            raise DataError(
                f"pipeline: annotated={s.annotated}: {len(shared)} of its scored image(s) are training images too "
                f"(e.g. {shared[0][0]} = {shared[0][1]}); images scored at the end must never train anything: give "
                "data.dir a split.json whose test ids they are, or other images"
            )
        summary["annotated_images"] = len(scored)
    if s.corrected is not None:
        summary["corrected_images"] = check_corrected(s, scored if s.annotated is not None else [])
    return summary


def same_images(these: Sequence[Path], those: Sequence[Path]) -> list[tuple[Path, Path]]:
    """(a, b) for every image of ``these`` whose content is that of an image ``b`` of ``those`` (compared by digest)."""
    seen = {_digest(p): p for p in those}
    return [(p, seen[d]) for p in these if (d := _digest(p)) in seen]


def check_corrected(s: Settings, scored: Sequence[Path]) -> int:
    """``corrected=DIR``: outlines of images of data.dir (drgan.segmenters.corrections), none of them an image the
    run scores at the end; the number of corrected images."""
    from drgan.data.images import list_images
    from drgan.segmenters.corrections import find_corrections

    outlines = find_corrections(s.corrected, "pipeline: corrected")
    own = s.corrected / "images"
    images = list_images(own if own.is_dir() else s.data_dir, list(outlines))
    shared = same_images(images, scored)
    if shared:
        raise DataError(
            f"pipeline: corrected={s.corrected}: {len(shared)} corrected image(s) are scored at the end too (e.g. "
            f"{shared[0][0]} = {shared[0][1]}); a corrected image trains the segmenter, so it must not be scored: "
            "correct other images, or score others"
        )
    return len(images)
