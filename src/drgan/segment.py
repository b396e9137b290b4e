"""`python -m drgan.segment data=DIR name=NAME`: train the U-Net segmenter (3 classes, Dice + CE, Adam).

`data=DIR`: pairs written by `python -m drgan.generate` (images/ID.png, masks/ID.png classes 0/1/2, and 255 on
the particles of partial backgrounds, which the loss and val/dsc leave out: drgan.segmenters.module).
`real=DATASET`: the real-data baseline, trained on the `train` ids of DATASET/split.json only; targets are
class_mask(4-connected components of the binary mask, contour_px). A seeded `val_fraction` of the pairs is
held out for validation. Run folder `out`: checkpoints/last.ckpt (and the latest epoch), segment.log,
metrics.json, closed_loop.png (the closed-loop check's held-out generated pairs, drgan.segmenters.closed_loop: found
particles matched to a true one green, false ones red, true ones nothing found yellow); MLflow experiment
`segment_<name>` gets the params, metrics and the final checkpoint.
Resume: same `out` and `ckpt_path=last` (no checkpoint yet: a fresh start).
`finetune=RUN corrected=DIR`: the correction loop, RUN's segmenter (a pipeline run, a segment run folder or a
checkpoint) fine-tuned on a user's corrected outlines (drgan.segmenters.corrections) beside RUN's generated pairs,
split and held out as RUN did (`prepare_finetune`); the split is then chosen on the corrected images and the
validation pairs.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict

from drgan.core.errors import ConfigError, DataError, check_keys, setting_float, setting_int
from drgan.core.io import write_json
from drgan.core.typed_settings import read_settings, setting, typed
from drgan.launch.runtime import stage_main, start
from drgan.segmenters.agreement import agreement_settings
from drgan.segmenters.contacts import resolve_contact_weight
from drgan.segmenters.training import (  # segment's data (the names it exports as its own too: __all__)
    LoaderSettings,
    TrainingPairs,
    at_working_scale,
    check_fraction,
    checked_source,
    dataloaders,
    load_training_pairs,
    redrawn_contours,
    scaled_pairs,
    working_px_of,
)

__all__ = [
    "LoaderSettings", "TrainingPairs", "at_working_scale", "check_fraction", "checked_source", "dataloaders",
    "load_training_pairs", "main", "redrawn_contours", "segment", "working_px_of",
]  # fmt: skip
log = logging.getLogger(__name__)

SHEET = "closed_loop.png"  # the closed-loop check's picture in the run folder


def early_stopping(cfg):
    """Lightning's EarlyStopping from ``early_stopping`` {monitor, patience, min_delta} (None: no early stop)."""
    if cfg is None:
        return None
    from lightning.pytorch.callbacks import EarlyStopping

    settings = dict(OmegaConf.to_container(cfg, resolve=True)) if isinstance(cfg, DictConfig) else dict(cfg)
    check_keys("early_stopping", settings, ("monitor", "patience", "min_delta"))
    monitor = str(settings.get("monitor", "val/loss"))
    if monitor not in ("val/loss", "val/dsc"):
        raise ConfigError(f"early_stopping.monitor={monitor!r}: expected val/loss or val/dsc")
    return EarlyStopping(
        monitor=monitor,
        mode="min" if monitor == "val/loss" else "max",
        patience=setting_int("early_stopping.patience", settings.get("patience", 3), 1),
        min_delta=setting_float("early_stopping.min_delta", settings.get("min_delta", 0.0), 0.0),
        check_on_train_epoch_end=False,  # after validation, on its value
    )


def stop_reason(trainer, stopper) -> str:
    """Why the fit ended: early stop ("patience: val/loss ...") or "max_epochs" / "max_steps" / "interrupted"."""
    if stopper is not None and stopper.stopped_epoch > 0:
        return (
            f"patience: {stopper.monitor} not better than {float(stopper.best_score):.4g} for {stopper.patience} epochs"
        )
    if trainer.interrupted:
        return "interrupted"
    if trainer.max_steps not in (-1, None) and trainer.global_step >= trainer.max_steps:
        return "max_steps"
    return "max_epochs"


@dataclass
class Prepared:
    """What a segment run trains, its data read and checked: the model, its training pairs (validation pairs among
    them) and the closed-loop check's held-out pairs, a user's corrected pairs (fine-tuning), the values its
    checkpoints carry for inference (pixel scale, noise level, working diameter), the working scale, the seed of
    its validation split and why its contact weight and depth are what they are."""

    model: Any
    pairs: list
    check_pairs: list
    pixel_scale: float = 1.0
    noise: float | None = None
    diameter: float | None = None
    working: float = 1.0
    corrected: list = field(default_factory=list)
    split_seed: int | None = None
    contact_why: str | None = None
    depth_why: str | None = None  # model.depth: auto (drgan.segmenters.unet.auto_depth)
    finetuned: dict | None = None  # fine-tuning: the base checkpoint and the corrected images (metrics.json)

    def entries(self) -> dict:
        """The checkpoint entries inference reads back (drgan.segmenters.registry.load_segmenter)."""
        from drgan.segmenters.calibrate import PIXEL_SCALE_KEY, WORKING_DIAMETER_KEY
        from drgan.segmenters.noise_match import NOISE_KEY

        return {PIXEL_SCALE_KEY: self.pixel_scale, NOISE_KEY: self.noise, WORKING_DIAMETER_KEY: self.diameter}


@typed
@dataclass(frozen=True)
class SegmentRun:
    """The keys of conf/segmentation/segment.yaml that say how a run starts, what it fine-tunes and how it is
    recorded, typed (`read_settings`); the pairs' source and loader are `TrainingPairs` and `LoaderSettings`, the
    model and trainer groups are built by the segmenter registry and Hydra."""

    out: Path = setting()
    name: str = "synthetic"
    seed: int = 0
    ckpt_path: str | None = None  # null: fresh; "last": resume the run folder's last.ckpt; or a checkpoint path
    tags: tuple[str, ...] = ()
    parent_run: str | None = None
    data: str | None = None
    real: str | None = None
    crop_rows: Any = "auto"
    finetune: Path | None = None
    corrected: Path | None = None
    early_stopping: dict | None = None  # `early_stopping` builds it, once per attempt
    split_calibration: dict | None = setting(None, check=lambda stage, grid: _check_grid(grid))
    agreement: Any = setting(None, check=lambda stage, node: agreement_settings(node))

    @classmethod
    def from_config(cls, cfg: DictConfig) -> SegmentRun:
        return read_settings(cls, cfg, "segment")

    @property
    def finetuning(self) -> bool:
        return self.finetune is not None or self.corrected is not None


def _check_grid(grid):
    from drgan.segmenters.calibrate import check_grid

    return check_grid(grid)


def segment(cfg: DictConfig) -> dict:
    """Train one segmenter (or fine-tune one on a user's corrected images: ``finetune=`` with ``corrected=``);
    return final metrics. Writes everything under cfg.out."""
    import lightning.pytorch as L

    wall_start = time.perf_counter()
    with open_dict(cfg):
        cfg.paths.root_dir = str(Path(cfg.paths.root_dir).expanduser().resolve())
    run = SegmentRun.from_config(cfg)
    L.seed_everything(run.seed, workers=True)

    # Settings first (early stopping; the model: an allow-listed class, or a ConfigError naming model._target_),
    # then data: bad folders, sizes or mask values fail here, before the run folder gets anything.
    stopper = early_stopping(run.early_stopping)
    calibration_grid = run.split_calibration
    guard = None if run.finetuning else run.agreement
    if guard is not None:
        return guarded(cfg, run, guard, calibration_grid)
    prepared = prepare_finetune(cfg, run) if run.finetuning else prepare(cfg)
    return fit_and_record(cfg, run, prepared, stopper, calibration_grid, wall_start)


def guarded(cfg: DictConfig, run: SegmentRun, guard, calibration_grid) -> dict:
    """Train, check the segmenter against the classical foreground of the user's images, and train the next seed
    while it covers too little of it (drgan.segmenters.agreement); the best-agreeing attempt is kept in cfg.out. Each
    attempt has an early stopping of its own (one shared would carry the last attempt's best loss and patience into
    the next, and stop it after its first epoch)."""
    import lightning.pytorch as L

    from drgan.segmenters.agreement import Attempts, check_agreement, read_reference

    out = run.out
    attempts = Attempts(out, guard)
    if attempts.finished() and (out / "metrics.json").is_file():  # done before (an attempt's own is stashed)
        return _floats(json.loads((out / "metrics.json").read_text()))
    items = read_reference(guard)  # every reference file read and checked before any training
    progress = bool(cfg.trainer.get("enable_progress_bar", True))
    mlflow = (cfg.logger or {}).get("mlflow")
    first_name = None if mlflow is None else mlflow.get("run_name")
    while not attempts.finished():
        seed = run.seed + len(attempts.records)  # the torch seed; the pairs' split stays cfg.seed's
        L.seed_everything(seed, workers=True)
        if attempts.records and mlflow is not None:  # a retry is its own MLflow run, named by its seed
            with open_dict(cfg):
                cfg.logger.mlflow.run_name = f"{first_name}/seed={seed}"
        stopper = early_stopping(run.early_stopping)
        fit_and_record(cfg, run, prepare(cfg), stopper, calibration_grid, time.perf_counter(), items)
        check = check_agreement(out / "checkpoints" / "last.ckpt", items, progress)
        log.info(
            "seed %d: its foreground covers %.1f %% of the classical one on %d of the images (Dice %.3f; at least "
            "%.0f %% expected)", seed, 100 * check["covered"], len(check["ids"]), check["dice"], 100 * guard.min_covered,
        )  # fmt: skip
        attempts.stash(seed, check)
        with open_dict(cfg):
            cfg.ckpt_path = None  # the next attempt starts fresh (its logged params say so too)
        run = replace(run, ckpt_path=None)
    metrics = attempts.keep_best()
    log.info("agreement: %s", metrics["agreement"]["why"])
    return _floats(metrics)


def _floats(metrics: dict) -> dict:
    return {k: v for k, v in metrics.items() if isinstance(v, float)}


def prepare(cfg: DictConfig) -> Prepared:
    """A fresh segmenter and its pairs (generated or real), checked; see `Prepared`."""
    source = checked_source(cfg)
    manifest = source.manifest()
    contact_why = None
    if "contact_weight" in cfg.model:
        with open_dict(cfg):
            cfg.model.contact_weight, contact_why = resolve_contact_weight(
                cfg.model.contact_weight, source.polarity(manifest), source.clark_evans(manifest)
            )
        log.info("model.contact_weight=%s (%s)", cfg.model.contact_weight, contact_why)
    model, scaled, depth_why = _model_and_pairs(cfg, source, manifest)
    pixel_scale, noise = scaled.pixel_scale, scaled.noise
    if pixel_scale != 1.0:
        log.info(
            "the pairs hold %.3g px per real image px: inference will resample images by %.3g (stored in the "
            "checkpoints)", pixel_scale, pixel_scale,
        )  # fmt: skip
    if noise is not None:
        log.info(
            "the generated images' fine-noise level is %.4f: inference adds white noise to cleaner images up to it "
            "(inference.noise_match; stored in the checkpoints)", noise,
        )  # fmt: skip
    return Prepared(
        model, scaled.pairs, scaled.check, pixel_scale, noise, scaled.diameter, scaled.working, contact_why=contact_why,
        depth_why=depth_why,
    )  # fmt: skip


def _model_and_pairs(cfg: DictConfig, source, manifest):
    """(segmenter, its pairs at their working scale (`scaled_pairs`), why its depth; None unless auto): a fresh
    segmenter; ``model.depth: auto`` resolved from those pairs' particles (drgan.segmenters.unet.auto_depth) and written
    into ``cfg.model``, the segmenter built at that depth from the torch RNG state a direct build would have had."""
    import torch

    from drgan.segmenters.registry import build_segmenter
    from drgan.segmenters.unet import AUTO_DEPTHS, auto_depth

    auto = "depth" in cfg.model and cfg.model.depth == "auto"
    if auto:
        with open_dict(cfg):
            cfg.model.depth = AUTO_DEPTHS[0]
    rng = torch.random.get_rng_state() if auto else None
    model = build_segmenter(cfg.model, "model")
    scaled = scaled_pairs(cfg, source, manifest, model)
    if not auto:
        return model, scaled, None
    depth, why = auto_depth(scaled.diameter)
    log.info("model.depth=%d (%s)", depth, why)
    if depth != cfg.model.depth:
        with open_dict(cfg):
            cfg.model.depth = depth
        torch.random.set_rng_state(rng)
        model = build_segmenter(cfg.model, "model")
    return model, scaled, why


FINETUNE_KEPT = ("val_fraction", "check_fraction", "loader.working_px", "loader.contour_px")  # the base run's


def finetune_base(keys: SegmentRun) -> tuple[Path, DictConfig | None, str]:
    """(segmenter checkpoint, the base run's config or None, its generated pairs' folder) of ``finetune=RUN``: a
    pipeline run folder (its segment/), a segment run folder or a checkpoint file; ``data=`` names the pairs where
    the base run does not record them. A ConfigError or DataError names what is missing."""
    if keys.finetune is None or keys.corrected is None:
        raise ConfigError(
            "segment: fine-tuning needs both finetune=RUN (a pipeline run, a segment run folder or a segmenter "
            "checkpoint) and corrected=DIR (the corrected outlines: drgan.segmenters.corrections)"
        )
    if keys.real:
        raise ConfigError("segment: finetune= fine-tunes on generated pairs and corrected images; real= is not used")
    run = keys.finetune.expanduser()
    folder = run / "segment" if (run / "segment" / "checkpoints").is_dir() else run
    ckpt = run if run.is_file() else folder / "checkpoints" / "last.ckpt"
    if not ckpt.is_file():
        raise DataError(
            f"finetune={run}: no segmenter checkpoint there (expected a pipeline run with segment/checkpoints/"
            "last.ckpt, a segment run folder with checkpoints/last.ckpt, or a .ckpt file)"
        )
    config_file = (ckpt.parent.parent if run.is_file() else folder) / ".hydra" / "config.yaml"
    base = OmegaConf.load(config_file) if config_file.is_file() else None  # YAML: nothing in it runs
    data = keys.data or (base.get("data") if base is not None else None)
    if not data:
        raise ConfigError(
            f"finetune={run}: its run does not record the generated pairs it was trained on; give data=DIR too"
        )
    return ckpt, base, str(data)


def prepare_finetune(cfg: DictConfig, keys: SegmentRun) -> Prepared:
    """The segmenter of ``finetune=RUN`` with its generated pairs (split and held out as its own run did: the base's
    seed, val_fraction, check_fraction and loader scale settings) and the corrected images of ``corrected=DIR``
    resampled to its scale (drgan.segmenters.corrections); trained ``correction.epochs`` epochs at
    ``correction.lr``. The checkpoints keep the base's pixel scale, noise level and working diameter."""
    from drgan.segmenters.corrections import correction_pairs, load_corrections
    from drgan.segmenters.registry import load_segmenter

    ckpt, base, data = finetune_base(keys)
    setting = cfg.correction
    lr = setting_float("correction.lr", setting.lr, 0.0)
    epochs = setting_int("correction.epochs", setting.epochs, 1)
    setting_float("correction.share", setting.share, 0.0)
    model = load_segmenter(ckpt, "finetune").train()  # (loaded for inference, in eval mode)
    model.hparams.lr = lr
    model.hparams.lr_schedule = "constant"  # the fine-tuning's few epochs at correction.lr, as measured
    split_seed = int(base.seed) if base is not None and base.get("seed") is not None else keys.seed
    with open_dict(cfg):
        cfg.data = data
        if base is not None:
            for key in FINETUNE_KEPT:
                OmegaConf.update(cfg, key, OmegaConf.select(base, key), merge=False)
        cfg.trainer.max_epochs = epochs
        # the model is the base's (its class and keywords, as its checkpoint records them; lr the fine-tuning's)
        cfg.model = OmegaConf.create(dict(model.hparams))
    source = checked_source(cfg)
    items = load_corrections(keys.corrected, setting.get("images"), keys.crop_rows)
    scaled = scaled_pairs(cfg, source, source.manifest(), model, split_seed)
    corrected = correction_pairs(items, model.pixel_scale, scaled.contour_width, model.train_noise)
    n = sum(int(lab.max()) for _, lab in items)
    log.info(
        "fine-tuning %s on %d corrected image(s) (%d particles, resampled by %.3g) beside %s's pairs: %d epochs at "
        "lr %g%s", ckpt, len(items), n, model.pixel_scale, data, epochs, lr,
        "" if base is not None else " (no config of the base run found: this run's seed and loader settings)",
    )  # fmt: skip
    return Prepared(
        model,
        scaled.pairs,
        scaled.check,
        model.pixel_scale,
        model.train_noise,
        model.working_diameter,
        scaled.working,
        corrected,
        split_seed=split_seed,
        contact_why="the base segmenter's",
        finetuned={"base": str(ckpt), "corrected": str(keys.corrected), "images": [item.id for item, _ in items],
                   "particles": n, "pixel_scale": scaled.pixel_scale},
    )  # fmt: skip


def fit_and_record(
    cfg: DictConfig, run: SegmentRun, prepared: Prepared, stopper, calibration_grid, wall_start: float, real_items=None
) -> dict:
    """Train ``prepared.model`` into cfg.out, then calibrate its split (checked on ``real_items``, the user's images
    with their classical labels, when given), run its closed-loop check, log and write metrics.json; the final
    metrics."""
    from drgan.segmenters.module import settled

    model, out = prepared.model, run.out
    train_loader, val_loader, n_train, n_val = dataloaders(
        cfg,
        prepared.pairs,
        str(getattr(model, "input_normalization", "none")),
        bool(getattr(model, "needs_centres", False)),
        prepared.working,
        (int(getattr(model, "rays", 0)), int(getattr(model, "hparams", {}).get("ray_px", 64))),
        prepared.corrected,
        prepared.split_seed,
    )
    out.mkdir(parents=True, exist_ok=True)
    trainer, loggers, scores = _fit(cfg, run, prepared, stopper, (train_loader, val_loader), (n_train, n_val))

    metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if getattr(v, "numel", lambda: 1)() == 1}
    if "val/dsc" not in metrics and scores.history:  # a resumed run whose training had finished validates nothing
        metrics["val/dsc"] = scores.history[-1]
    metrics["time/wall_s"] = time.perf_counter() - wall_start
    stop = stop_reason(trainer, stopper)
    log.info("stopped after epoch %d: %s", trainer.current_epoch - 1, stop)
    is_settled, why = settled(scores.history) if val_loader is not None else (True, "no validation pairs")
    if not is_settled and not prepared.corrected:
        log.warning(
            "the segmenter stopped before its validation score settled (%s): it is likely undertrained; raise "
            "early_stopping.patience or trainer.max_epochs (or set loader.samples_per_pair for longer epochs)",
            why,
        )
    last = out / "checkpoints" / "last.ckpt"
    progress = bool(cfg.trainer.get("enable_progress_bar", True))
    # the split is chosen on the validation pairs and, when fine-tuning, on the user's corrected images first
    calibration_pairs = [*prepared.corrected, *(val_loader.dataset.pairs if val_loader is not None else [])]
    calibration = calibrate(model, calibration_pairs, calibration_grid, last, progress, real_items)
    if calibration is not None:
        metrics["split/ap50"] = calibration["ap50"]
    check = closed_loop_check(model, prepared.check_pairs, calibration, last, progress, prepared.working)
    if check is not None:
        metrics.update(check_metrics(check))
    for logger in loggers:
        logger.log_metrics(
            {k: v for k, v in metrics.items() if k == "time/wall_s" or k.startswith("check/")}, step=trainer.global_step
        )
        if hasattr(logger, "experiment") and getattr(logger, "run_id", None) and last.is_file():
            logger.experiment.log_artifact(logger.run_id, str(last), artifact_path="checkpoints")
    write_json(
        out / "metrics.json",
        {
            "epoch": trainer.current_epoch,
            "global_step": trainer.global_step,
            "stop_reason": stop,
            "settled": is_settled,
            "settled_why": why,
            "val_dsc_history": scores.history,
            "split_calibration": calibration,
            "closed_loop": check,
            "pixel_scale": prepared.pixel_scale,
            "working_diameter": prepared.diameter,
            "noise_level": prepared.noise,
            "contact_weight": {"value": cfg.model.get("contact_weight"), "why": prepared.contact_why},
            **({"depth": {"value": cfg.model.depth, "why": prepared.depth_why}} if prepared.depth_why else {}),
            **({"finetuned": prepared.finetuned} if prepared.finetuned else {}),
            **metrics,
        },
    )
    log.info("done in %.1f s: %s", metrics["time/wall_s"], {k: round(v, 4) for k, v in sorted(metrics.items())})
    return metrics


def _fit(cfg: DictConfig, run: SegmentRun, prepared: Prepared, stopper, loaders: tuple, sizes: tuple[int, int]):
    """Fit ``prepared.model`` on ``loaders`` (train, validation) into ``run.out``, resumed from its last.ckpt when
    ``run.ckpt_path`` says so, its params logged; (trainer, loggers, the validation score history)."""
    from hydra.utils import instantiate
    from lightning.pytorch.callbacks import ModelCheckpoint

    from drgan.callbacks.progress_bar import StepProgress
    from drgan.callbacks.resume import ResumeCheckpoint
    from drgan.launch.runtime import flat_config, instantiate_loggers, resolve_checkpoint, start_loggers
    from drgan.segmenters.module import CheckpointEntries, ScoreHistory

    model, out = prepared.model, run.out
    (train_loader, val_loader), (n_train, n_val) = loaders, sizes
    ckpt_path = resolve_checkpoint(run.ckpt_path, out)
    tags = {"name": run.name, "output_dir": str(out), **{t: "1" for t in run.tags}}
    loggers = instantiate_loggers(cfg.logger, out, resume=ckpt_path is not None, tags=tags, parent_run=run.parent_run)
    # last.ckpt at every epoch end (ResumeCheckpoint), before validation-free epoch-end work; ModelCheckpoint keeps
    # the latest epoch's file.
    checkpoint = ModelCheckpoint(
        dirpath=out / "checkpoints",
        filename="epoch_{epoch:03d}",
        auto_insert_metric_name=False,
        save_last=False,
        save_top_k=1,
    )
    scores = ScoreHistory()
    callbacks = [
        CheckpointEntries(prepared.entries()),
        ResumeCheckpoint(),
        checkpoint,
        scores,
        *([stopper] if stopper is not None else []),
        StepProgress("fine-tuning the segmenter" if prepared.corrected else "training the segmenter"),
    ]
    trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False)
    start_loggers(loggers)

    params = flat_config(cfg)
    params.update(
        {
            "data/n_train_pairs": n_train,
            "data/n_val_pairs": n_val,
            "data/n_corrected": len(prepared.corrected),
            "model/n_parameters": sum(p.numel() for p in model.parameters()),
        }
    )
    for logger in loggers:
        try:
            logger.log_hyperparams(params)
        except Exception as error:  # noqa: BLE001  (a logger refusing a param must not stop training)
            log.warning("%s: params not (all) logged: %s", type(logger).__name__, str(error).splitlines()[0])

    log.info(
        "segmenter %s: %d train / %d val pairs%s, run folder %s", run.name, n_train, n_val,
        f" and {len(prepared.corrected)} corrected images" if prepared.corrected else "", out,
    )  # fmt: skip
    trainer.fit(
        model, train_dataloaders=train_loader, val_dataloaders=val_loader, ckpt_path=ckpt_path, weights_only=True
    )
    return trainer, loggers, scores


def calibrate(model, pairs, grid: dict | None, last: Path, progress: bool, real_items=None, store=True) -> dict | None:
    """Choose the touching-particle split on ``pairs`` (the validation pairs; drgan.segmenters.calibrate), check its
    particle count on ``real_items`` (the user's images and their classical labels: `real_count_guard`) and store it
    in ``last`` for evaluate/analyze's ``split_core: auto`` (unless not ``store``: recalibrate.py's dry run); None
    when calibration is off or impossible."""
    from drgan.core.checkpoint_io import add_entry
    from drgan.segmenters import calibrate as calib

    if grid is None:
        return None
    if not pairs or not last.is_file():
        log.warning("split calibration skipped: %s", "no validation pairs" if not pairs else f"no {last}")
        return None
    try:
        calibration = calib.as_array_free(calib.calibrate_split(model.eval(), pairs, grid, progress=progress))
    except ValueError as error:
        log.warning("split calibration skipped: %s", error)
        return None
    if real_items:  # the segmenter as analyze loads it (its pixel scale and noise level are checkpoint entries)
        from drgan.segmenters.registry import load_segmenter

        calibration = calib.as_array_free(calib.real_count_guard(load_segmenter(last), calibration, real_items))
        _log_real_count(calibration.get("real_count"))
    if store:
        add_entry(last, calib.CHECKPOINT_KEY, calibration, "ckpt_path")
    chosen = (
        f"seed_level {calibration['seed_level']}"
        if calibration.get("split") in calib.SEEDED
        else f"split_seeds {calibration.get('split_seeds')}, split_depth {calibration['split_depth']}, split_core "
        f"{calibration['split_core']}"
    )
    log.info(
        "split chosen on %d pairs (particles %.0f px across, median): %s (AP50 %.3f); %s\n%s",
        calibration["n_pairs"],
        calibration.get("particle_px", float("nan")),
        chosen,
        calibration["ap50"],
        f"stored in {last}" if store else "not stored",
        calib.markdown_table(calibration),
    )
    return calibration


def _log_real_count(guard: dict | None) -> None:
    if not guard:
        return
    said = (
        f"the split's count on {guard['images']} of your images: {guard['chosen_count']} particles against the "
        f"classical segmentation's {guard['classical']} ({100 * (guard['chosen_count'] / guard['classical'] - 1):+.1f} %)"
    )
    if guard["moved"]:
        why, instead = (
            ("cuts particles of your images into pieces", f"counting the most up to {guard.get('ceiling'):g}")
            if guard.get("side") == "above"
            else ("merges particles of your images that even the classical segmentation separates",
                  "nearest the classical count")
        )  # fmt: skip
        log.warning("%s: the generated pairs' choice %s; the setting within the AP50 margin %s taken instead (%d "
                    "particles)", said, why, instead, guard["count"])  # fmt: skip
    else:
        log.info("%s: the choice kept", said)


def closed_loop_check(
    model, pairs, calibration: dict | None, last: Path, progress: bool, working: float = 1.0
) -> dict | None:
    """The segmenter scored on its held-out generated pairs (drgan.segmenters.closed_loop), with the split just
    calibrated, each pair resampled by the ``working`` scale as inference resamples a real image; stored in
    ``last`` (evaluate/analyze and the pipeline's report quote it) and drawn in the run folder (``SHEET``). None without
    pairs."""
    from drgan.core.checkpoint_io import add_entry
    from drgan.segmenters.closed_loop import CLOSED_LOOP_KEY, closed_loop, log_summary

    if not pairs:
        return None
    if not last.is_file():
        log.warning("closed-loop check skipped: no %s", last)
        return None
    check = closed_loop(
        model.eval(), pairs, calibration, progress=progress, pixel_scale=working, sheet=last.parent.parent / SHEET
    )
    add_entry(last, CLOSED_LOOP_KEY, check, "ckpt_path")
    log_summary(check)
    return check


def check_metrics(check: dict) -> dict[str, float]:
    """The closed-loop check as flat metrics (MLflow, metrics.json's top level): check/median_error ..."""
    flat = {f"check/{k}": check[k]["value"] for k in ("median_error", "mean_error", "count_error")}
    flat.update({f"check/{k}": check[k] for k in ("edge_offset_px", "merged", "split", "missed", "ap50", "dsc")})
    contacts = check.get("contacts") or {}
    flat.update({f"check/contacts_{k}": contacts.get(k) for k in ("hidden", "hidden_merged", "shown_merged")})
    return {k: float(v) for k, v in flat.items() if v is not None}


@stage_main("conf/segmentation", "segment")
def main(cfg: DictConfig):
    return segment(cfg)


if __name__ == "__main__":
    start(main)
