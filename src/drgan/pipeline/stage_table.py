"""The pipeline's stages, each declared once and in order (``PIPELINE``): its name, the arguments that wire it to
the stages before it, the keys it leaves to the pipeline, its done file, and how the report reads back and shows what
it wrote. Everything else that names stages is derived from this table: ``STAGES`` and ``PIPELINE_KEYS`` (read here,
computed at each read, so a stage added to ``PIPELINE`` is in them at once), the routing of ``STAGE.KEY=VALUE``
(settings.py), the commands (stages.py ``build_stages``), the summaries (each entry's ``summary``) and report.md."""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

from drgan.pipeline import report

RESUME_KEY = "ckpt_path"  # the resume flag a stage gets when it has a checkpoint; not a setting


@dataclass(frozen=True)
class Context:
    """What a stage's arguments are made of: the run's inputs, its folders, and what the stages before found."""

    out: Path
    name: str
    data_dir: Path
    annotated: Path | None
    settings: Mapping[str, Mapping[str, str | None]]  # stage -> its STAGE.KEY=VALUE (config defaults, command line)
    nm_per_px: float | None = None  # the pixel size the profile read from the images' metadata (None before it ran)
    corrected: Path | None = None  # the user's corrected outlines: the finetune stage runs, analyze uses its segmenter

    def folder(self, stage: str) -> Path:
        return self.out / stage

    @property
    def conf(self) -> Path:
        """The pipeline's config folder (on the stages' Hydra search path): the profile writes the material there."""
        return self.out / "drgan_conf"


@dataclass(frozen=True)
class StageSpec:
    """One stage of the pipeline. Its command is ``python -m MODULE *wire(context) *STAGE.KEY=VALUE`` run into
    ``OUT/NAME``; it is done when it exited 0 and ``done(context)`` exists."""

    name: str
    wire: Callable[[Context], list[str] | None]  # the pipeline's own arguments (folders, links); None: not in this run
    keys: tuple[str, ...]  # the keys ``wire`` sets (or that would contradict it): a user's STAGE.KEY for one is refused
    done: Callable[[Context], Path]  # the file whose presence (with a clean exit) says the stage is done
    summary: Callable[[Path], dict]  # its folder read back: {"line": ..., "metrics": {...}, ...} ({} when empty)
    what: str  # what it does, for report.md
    links: tuple[tuple[str, str], ...] = ()  # (label, path in its folder): the report links those that exist
    details: Callable[[dict, object], list[str]] = lambda summary, settings: []  # report lines below its result
    artifacts: tuple[str, ...] = ()  # files of its folder logged to its MLflow child run
    resumes: bool = False  # resumes from FOLDER/checkpoints/last.ckpt (RESUME_KEY=last) after a kill
    mlflow_run: bool = False  # logs an MLflow run of its own (given the pipeline's experiment and parent run)
    module: str = ""  # its command's module; "" for drgan.NAME
    config: str = ""  # its config's name (the user's keys are composed with it before any stage runs); "" for NAME
    typical_minutes: float = 1.0  # its wall time with the defaults on 2 quiet CPU cores for 32 + 8 TSEM images of
    # 1024 x 768 px (benchmarks/pipeline.py, experiments/benchmarks/pipeline.md): the prior of the whole run's estimated
    # end, scaled by how the stages done so far compared with theirs (progress_line.py)
    paced: bool = True  # its time follows the machine's pace, not the folder's size (profile, analyze and evaluate read
    # every image: a folder of 4 small images would make the GAN look 3 x quicker); those neither set nor take the pace

    @property
    def command_module(self) -> str:
        return self.module or f"drgan.{self.name}"

    @property
    def config_name(self) -> str:
        return self.config or self.name

    @property
    def pipeline_keys(self) -> tuple[str, ...]:
        """The keys the pipeline sets itself, a user's STAGE.KEY for one of them refused."""
        return (*self.keys, *(("parent_run",) if self.mlflow_run else ()), *((RESUME_KEY,) if self.resumes else ()))


def _segmenter(c: Context) -> Path:
    """The segmenter analyze and evaluate use: the fine-tuned one when the user corrected outlines, else segment's."""
    return c.folder("finetune" if c.corrected else "segment") / "checkpoints" / "last.ckpt"


# --- the table: one entry per stage, in the order they run ------------------------------------------------------

PIPELINE: list[StageSpec] = [
    StageSpec(
        "profile",
        typical_minutes=3.5,
        paced=False,
        wire=lambda c: [f"data.dir={c.data_dir}", f"name={c.name}", f"out={c.folder('profile')}",
                        f"conf_dir={c.conf}", "overwrite=true"],
        keys=("data.dir", "name", "out", "conf_dir", "overwrite"),
        done=lambda c: c.conf / "material" / f"{c.name}.yaml",
        summary=report.profile_summary,
        details=report.profile_details,
        what="reads the images (train ids only), detects the polarity, segments the particles classically and "
        "writes the material: sizes, particles per patch, placement, noise, the edge",
        links=(("report", "report.md"), ("outlines found", "particles.png"), ("sizes", "sizes.png"),
               ("scale search", "scale_search.png"), ("edge profile", "edge_profile.png")),
        artifacts=("report.md", "profile.json"),
    ),
    StageSpec(
        "train",
        typical_minutes=8.0,
        wire=lambda c: [f"material={c.name}", f"run_name={c.name}", f"hydra.run.dir={c.folder('train')}",
                        f"hydra.searchpath=[file://{c.conf}]"],
        keys=("material", "run_name", "hydra.run.dir", "hydra.searchpath"),
        done=lambda c: c.folder("train") / "metrics.json",
        summary=report.train_summary,
        details=report.train_details,
        what="trains the GAN with that material; an evaluation (FID, grey levels) every 67 steps; the best epoch is "
        "the broadest among the lowest FIDs whose grey matches the real patches'",
        links=(("real patches", "patches/contact_sheet.png"), ("FID per evaluation", "plots/fid.png"),
               ("best epoch and why", "checkpoints/best_epoch.json"), ("grey start", "grey_start.json")),
        resumes=True,
        mlflow_run=True,
    ),
    StageSpec(
        "generate",
        typical_minutes=3.0,
        wire=lambda c: [f"ckpt={c.folder('train')}", f"out={c.folder('generate')}"],
        keys=("ckpt", "out"),
        done=lambda c: c.folder("generate") / "manifest.json",
        summary=report.generate_summary,
        what="renders annotated pairs from the best epoch, each image's grey levels those of one real patch "
        "(grey_spread), and adds real background windows",
        links=(("manifest (kept, dropped, why)", "manifest.json"), ("images", "images"), ("masks", "masks")),
        artifacts=("manifest.json",),
    ),
    StageSpec(
        "segment",
        typical_minutes=7.0,
        wire=lambda c: [f"data={c.folder('generate')}", f"out={c.folder('segment')}", f"name={c.name}",
                        f"run_name={c.name}", f"agreement.images={c.data_dir}",
                        f"agreement.reference={c.folder('profile') / 'labels'}"],
        keys=("data", "real", "out", "name", "run_name", "agreement.images", "agreement.reference"),
        done=lambda c: c.folder("segment") / "metrics.json",
        summary=report.segment_summary,
        what="trains the segmenter on the pairs, chooses its touching-particle split on held-out pairs and checks it "
        "against the profile's classical outlines of your images (another seed when it covers too little of them)",
        links=(("metrics and split calibration", "metrics.json"), ("its closed-loop check", "closed_loop.png"),
               ("log", "segment.log")),
        resumes=True,
        mlflow_run=True,
    ),
    StageSpec(
        "finetune",  # only with corrected=DIR: the correction loop (drgan.segmenters.corrections)
        typical_minutes=4.0,
        module="drgan.segment",
        config="segment",
        wire=lambda c: None if c.corrected is None else
        [f"finetune={c.folder('segment')}", f"data={c.folder('generate')}", f"corrected={c.corrected}",
         f"correction.images={c.data_dir}", f"out={c.folder('finetune')}", f"name={c.name}",
         f"run_name={c.name}_finetune"],
        keys=("finetune", "data", "real", "corrected", "correction.images", "out", "name", "run_name"),
        done=lambda c: c.folder("finetune") / "metrics.json",
        summary=report.segment_summary,
        what="fine-tunes the segmenter on your corrected outlines beside its generated pairs, and chooses its split "
        "on them",
        links=(("metrics and split calibration", "metrics.json"), ("its closed-loop check", "closed_loop.png"),
               ("log", "segment.log")),
        resumes=True,
        mlflow_run=True,
    ),
    StageSpec(
        "analyze",
        typical_minutes=1.5,
        paced=False,
        wire=lambda c: [f"model={_segmenter(c)}", f"images={c.data_dir}", f"out={c.folder('analyze')}",
                        f"profile={c.folder('profile')}",
                        *([f"nm_per_px={c.nm_per_px}"] if c.nm_per_px and "nm_per_px" not in c.settings["analyze"]
                          else [])],
        keys=("model", "images", "out", "profile"),
        done=lambda c: c.folder("analyze") / "particles.csv",
        summary=report.analyze_summary,
        details=report.analyze_details,
        what="segments every image of the folder and measures each particle",
        links=(("statistics", "statistics.md"), ("size distribution", "sizes.png"), ("particles", "particles.csv"),
               ("overlays", "overlays")),
        artifacts=("particles.csv", "histograms.png"),
    ),
    StageSpec(
        "evaluate",  # only with annotated=DATASET: its test ids (every image without a split.json) are scored
        typical_minutes=0.5,
        paced=False,
        wire=lambda c: None if c.annotated is None else
        [f"model={_segmenter(c)}", f"data={c.annotated}", f"out={c.folder('evaluate')}",
         f"reported={c.folder('analyze')}",
         *([] if (c.annotated / "split.json").is_file() else ["subset=all"])],
        keys=("model", "models", "data", "out", "reported"),
        done=lambda c: c.folder("evaluate") / "results.md",
        summary=report.evaluate_summary,
        what="scores the segmenter on the annotated images (never used for anything else), and the sizes the analyze "
        "stage reported for them",
        links=(("scores", "results.md"), ("statistics", "statistics.md"), ("sizes", "sizes.png"),
               ("overlays", "overlays")),
        artifacts=("results.md", "statistics.md"),
    ),
]  # fmt: skip


# --- derived ------------------------------------------------------------------------------------------------


def __getattr__(name: str):
    """``STAGES`` (the stages' names, in order) and ``PIPELINE_KEYS`` (stage -> the keys the pipeline sets itself),
    both derived from ``PIPELINE`` at each read."""
    if name == "STAGES":
        return tuple(spec.name for spec in PIPELINE)
    if name == "PIPELINE_KEYS":
        return {spec.name: spec.pipeline_keys for spec in PIPELINE}
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def stage_spec(stage: str) -> StageSpec:
    for entry in PIPELINE:
        if entry.name == stage:
            return entry
    raise KeyError(stage)


def profiled_pixel_size(out: Path) -> float | None:
    """The pixel size (nm/px) the profile read from the images' metadata, once it has run (analyze measures in nm)."""
    path = out / "profile" / "profile.json"
    if not path.is_file():
        return None
    size = (json.loads(path.read_text()).get("pixel_size") or {}).get("nm_per_px")
    return float(size) if size else None
