"""`python -m drgan.segment data=DIR name=NAME`: train the U-Net segmenter (3 classes, Dice + CE, Adam).

`data=DIR`: pairs written by `python -m drgan.generate` (images/ID.png, masks/ID.png classes 0/1/2, and 255 on
the particles of partial backgrounds, which the loss and val/dsc leave out: drgan.segmenters.module).
`real=DATASET`: the real-data baseline, trained on the `train` ids of DATASET/split.json only; targets are
class_mask(4-connected components of the binary mask, contour_px). A seeded `val_fraction` of the pairs is
held out for validation. Run folder `out`: checkpoints/last.ckpt (and the latest epoch), segment.log,
metrics.json; MLflow experiment `segment_<name>` gets the params, metrics and the final checkpoint.
Resume: same `out` and `ckpt_path=last` (no checkpoint yet: a fresh start).
`finetune=RUN corrected=DIR`: the correction loop, RUN's segmenter (a pipeline run, a segment run folder or a
checkpoint) fine-tuned on a user's corrected outlines (drgan.segmenters.corrections) beside RUN's generated pairs,
split and held out as RUN did (`prepare_finetune`); the split is then chosen on the corrected images and the
validation pairs.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf, open_dict

from drgan.errors import ConfigError, DataError, check_keys, setting_float, setting_int
from drgan.io import write_json
from drgan.runtime import stage_main, start
from drgan.segmenters.contacts import resolve_contact_weight

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainingPairs:
    """Where segment's training pairs come from: ``data`` (pairs of drgan.generate) or ``real`` (the train ids of
    an annotated dataset, with its split, crop_rows, masks, mask_suffix and contour_px); exactly one of the two.
    Field defaults = segment.yaml's (tests/test_segment.py compares)."""

    data: str | None = None
    real: str | None = None
    split: str | None = None
    contour_px: int = 1
    crop_rows: Any = "auto"
    masks: str = "masks"
    mask_suffix: str = "auto"

    @classmethod
    def from_config(cls, cfg: DictConfig) -> TrainingPairs:
        if bool(cfg.get("data")) == bool(cfg.get("real")):
            raise ConfigError("segment: give exactly one of data=DIR (generated pairs) or real=DATASET (real baseline)")
        if cfg.get("data"):
            return cls(data=cfg.data)
        return cls(
            real=cfg.real,
            split=cfg.get("split"),
            contour_px=setting_int("contour_px", cfg.contour_px, 0),
            crop_rows=cfg.get("crop_rows"),
            masks=cfg.get("masks", "masks"),
            mask_suffix=cfg.get("mask_suffix", "auto"),
        )

    def manifest(self) -> dict | None:
        """The generated set's manifest.json (drgan.synthetic.manifest), None for real images and hand-made pairs."""
        if not self.data:
            return None
        from drgan.synthetic.folder import MANIFEST
        from drgan.synthetic.manifest import read_manifest

        return read_manifest(self.data, "data") if (Path(self.data) / MANIFEST).is_file() else None

    def pixel_scale(self, manifest: dict | None = None) -> float:
        """Image px per real px of the pairs: a generated set's (its manifest; 1.0 for hand-made pairs), 1.0 for real
        images. The segmenter keeps it in its checkpoints; inference resamples real images by it."""
        from drgan.synthetic.manifest import manifest_pixel_scale

        manifest = self.manifest() if manifest is None else manifest
        return 1.0 if manifest is None else manifest_pixel_scale(manifest, "data")

    def contour_width(self, manifest: dict | None = None) -> int:
        """The contour class's width (px) in the pairs' masks: a generated set's (its manifest's generate config;
        1 for hand-made pairs), ``contour_px`` for real images."""
        if not self.data:
            return self.contour_px
        value = ((manifest or {}).get("config") or {}).get("contour_px", 1)
        return int(value) if isinstance(value, int) and value >= 0 else 1

    def noise_level(self, pairs, manifest: dict | None = None) -> float | None:
        """The fine-noise level of a generated set's synthetic images (drgan.segmenters.noise_match: the median over
        its first ones, from ``pairs``, the set as `load` gives it), which inference brings cleaner real images up
        to; None for real images and hand-made pairs (nothing to match)."""
        from drgan.segmenters.noise_match import SAMPLE, training_level

        manifest = self.manifest() if manifest is None else manifest
        if manifest is None:
            return None
        images = {p.id: p.image for p in pairs}
        items = [e for e in manifest.get("entries", []) if e.get("kind") == "synthetic"][:SAMPLE]
        return training_level(images[e["id"]] for e in items)

    def polarity(self, manifest: dict | None = None) -> str | None:
        """The particles' polarity (bright / dark) of a generated set (its manifest: the checkpoint material's);
        None for real images and hand-made pairs without a manifest."""
        manifest = self.manifest() if manifest is None else manifest
        polarity = ((manifest or {}).get("config") or {}).get("polarity")
        return polarity if polarity in ("bright", "dark") else None

    def clark_evans(self, manifest: dict | None = None) -> float | None:
        """The real particles' Clark-Evans ratio a generated set's material carries (manifest "material", from
        drgan.profile); None when not measured, for real images and for sets written before manifests had it."""
        manifest = self.manifest() if manifest is None else manifest
        value = ((manifest or {}).get("material") or {}).get("clark_evans")
        return float(value) if isinstance(value, (int, float)) else None

    def load(self):
        """The pairs (drgan.segmenters.pairs): generated, or the real dataset's train ids (never its test ids)."""
        from drgan.segmenters.pairs import load_generated_pairs, load_real_pairs, real_ids

        if self.data:
            return load_generated_pairs(self.data, setting="data")
        real = Path(self.real)
        ids = real_ids(real, self.split, "train", setting="real")
        return load_real_pairs(real, ids, self.contour_px, self.crop_rows, self.mask_suffix, self.masks)


@dataclass(frozen=True)
class LoaderSettings:
    """The ``loader`` group (and seed, val_fraction) of segment.yaml, checked (`from_config`: a ConfigError names
    the key of a bad value). Field defaults = segment.yaml's (tests/test_segment.py compares)."""

    crop: int = 128  # random crops per sample, px
    samples_per_pair: int | str = "auto"  # crops of each pair per epoch; auto: real images by area, generated once
    batch_size: int = 8
    num_workers: int = 0
    brightness: float = 0.05  # jitter, in units of the [0, 1] grey range
    contrast: float = 0.1  # relative contrast jitter
    texture: float = 0.1  # std of the surface texture added to each crop (pairs.surface_texture); 0: none
    contact_shade: float = 0.0  # largest depth of the dip drawn at the contacts of touching particles; 0: none
    working_px: float | str | None = "auto"  # the median particle's diameter in the crops (pairs.working_scale)
    contour_px: int | None = None  # rendered pairs' contour class redrawn from their labels this wide; None: theirs
    seed: int = 0
    val_fraction: float = 0.1

    @classmethod
    def from_config(cls, cfg: DictConfig) -> LoaderSettings:
        ld = cfg.loader
        per_pair = ld.samples_per_pair
        return cls(
            crop=setting_int("loader.crop", ld.crop, 1),
            samples_per_pair="auto" if per_pair == "auto" else setting_int("loader.samples_per_pair", per_pair, 1),
            batch_size=setting_int("loader.batch_size", ld.batch_size, 1),
            num_workers=setting_int("loader.num_workers", ld.num_workers, 0),
            brightness=setting_float("loader.brightness", ld.brightness, 0.0),
            contrast=setting_float("loader.contrast", ld.contrast, 0.0),
            texture=setting_float("loader.texture", ld.texture, 0.0),
            contact_shade=_fraction("loader.contact_shade", ld.contact_shade),
            working_px=_working_px(ld.get("working_px", "auto")),
            contour_px=None if ld.get("contour_px") is None else setting_int("loader.contour_px", ld.contour_px, 0),
            seed=setting_int("seed", cfg.seed),
            val_fraction=setting_float("val_fraction", cfg.val_fraction),
        )


def _working_px(value) -> float | str | None:
    """``loader.working_px``: "auto", null (off) or a diameter in px (> 1), else a ConfigError naming the key."""
    if value is None or value == "auto":
        return value
    number = setting_float("loader.working_px", value, 0.0)
    if not number > 1.0:
        raise ConfigError(f"loader.working_px={value}: expected a particle diameter in px (> 1), auto or null (off)")
    return number


def working_px_of(setting: float | str | None, model) -> float | None:
    """The working diameter a segmenter learns at: ``setting`` as given; "auto": ``CENTRE_WORKING_PX`` for a
    segmenter with a centre map (``needs_centres``: it needs whole particles in a crop), None (the pairs as they
    are) for the U-Net, whose classes are local."""
    from drgan.segmenters.pairs import CENTRE_WORKING_PX

    if setting == "auto":
        return CENTRE_WORKING_PX if getattr(model, "needs_centres", False) else None
    return setting


def at_working_scale(cfg: DictConfig, model, pairs, pixel_scale: float, contour_px: int):
    """(pairs, pixel_scale, scale, diameter): the pairs shrunk to the model's working diameter (`working_px_of`,
    drgan.segmenters.pairs.working_scale), their pixel scale multiplied alike (inference shrinks real images by it),
    and their particles' area-weighted median diameter after it (px, drgan.metrics.statistics.area_median; None
    without particles: inference's per-image scale aims at it); unchanged when no shrinking is needed."""
    from drgan.metrics.statistics import area_median
    from drgan.segmenters.pairs import sample_diameters, shrink_pair, working_scale

    ld = LoaderSettings.from_config(cfg)
    diameters = sample_diameters(pairs)
    scale, median = working_scale(pairs, working_px_of(ld.working_px, model), ld.crop, diameters)
    by_area = area_median(diameters)
    diameter = round(by_area * scale, 3) if by_area > 0 else None  # nan (no particle) fails the test too
    if scale >= 1.0:
        return pairs, pixel_scale, 1.0, diameter
    contour = max(1, int(round(contour_px * scale))) if contour_px > 0 else 0
    log.info(
        "loader.working_px=%s: the pairs' median particle spans %.0f px; the pairs are shrunk by %.3g (to %.0f px "
        "particles, contour %d px), and inference shrinks images alike (pixel scale %.3g, stored in the "
        "checkpoints)", ld.working_px, median, scale, median * scale, contour, pixel_scale * scale,
    )  # fmt: skip
    return [shrink_pair(p, scale, contour) for p in pairs], round(pixel_scale * scale, 6), scale, diameter


def redrawn_contours(pairs, contour_px: int | None):
    """``pairs`` with the contour class of those that carry exact instance labels (rendered pairs) drawn anew
    ``contour_px`` wide (drgan.scene.labels.class_mask; IGNORE pixels kept); unchanged for None."""
    from drgan.scene.labels import IGNORE, class_mask
    from drgan.segmenters.pairs import Pair

    if contour_px is None:
        return pairs
    out = []
    for pair in pairs:
        if pair.labels is None:
            out.append(pair)
            continue
        mask = class_mask(pair.labels, contour_px).astype(np.uint8)
        mask[pair.mask == IGNORE] = IGNORE
        out.append(Pair(pair.id, pair.image, mask, pair.labels))
    log.info("loader.contour_px=%d: the rendered pairs' contour class redrawn from their exact labels", contour_px)
    return out


def _fraction(key: str, value) -> float:
    """A setting in [0, 1], or a ConfigError naming ``key``."""
    number = setting_float(key, value, 0.0)
    if number > 1.0:
        raise ConfigError(f"{key}={value}: expected a number in [0, 1]")
    return number


def checked_source(cfg: DictConfig) -> TrainingPairs:
    """The training pairs' source of a segment config, its loader.* settings checked too: a bad value fails before
    any image is read."""
    source = TrainingPairs.from_config(cfg)
    LoaderSettings.from_config(cfg)
    check_fraction(cfg)
    return source


def load_training_pairs(cfg: DictConfig):
    """The training pairs of a segment config, every setting checked first (`checked_source`)."""
    return checked_source(cfg).load()


def dataloaders(
    cfg: DictConfig,
    pairs,
    normalize: str = "none",
    centres: bool = False,
    scale: float = 1.0,
    rays=(0, 64),
    corrected=(),
    split_seed: int | None = None,
):
    """Train and validation loaders of the pairs; ``normalize``: the segmenter's input normalisation, which its
    training crops get as its inference will (``input_normalization``); ``centres``: the crops carry centre-map
    targets too (an instance-aware segmenter, ``needs_centres``); ``scale``: the working scale the pairs were shrunk
    by (`at_working_scale`), so that real images keep the crops per epoch of their original area; ``rays``: (number,
    longest px) of the ray distances the crops carry (the star-convex segmenter, drgan.segmenters.star; 0: none);
    ``corrected``: a user's corrected images (drgan.segmenters.corrections), all trained on, ``correction.share`` of
    each epoch's crops; ``split_seed``: the validation split's seed (None: ``seed``; a fine-tuning run keeps its
    base run's, so that the base's validation pairs stay unseen)."""
    from torch.utils.data import DataLoader

    from drgan.segmenters.corrections import crops_for_share
    from drgan.segmenters.pairs import CropDataset, crops_by_area, split_pairs

    ld = LoaderSettings.from_config(cfg)
    train_pairs, val_pairs = split_pairs(pairs, ld.val_fraction, ld.seed if split_seed is None else split_seed)
    per_pair = ld.samples_per_pair
    if per_pair == "auto":
        # Real images are sampled by their area (an epoch of 20 large tiles is not 20 crops); generated pairs are
        # windows the GAN rendered, sampled once each, as their number (1,000 and more) already sets the epoch.
        per_pair = crops_by_area(train_pairs, ld.crop * scale) if cfg.get("real") else 1
    if corrected:
        counts = [per_pair] * len(train_pairs) if isinstance(per_pair, int) else list(per_pair)
        share = setting_float("correction.share", cfg.correction.share, 0.0)
        per_pair = counts + crops_for_share(list(corrected), sum(counts), share)
        train_pairs = [*train_pairs, *corrected]
    kw = dict(
        crop=ld.crop,
        brightness=ld.brightness,
        contrast=ld.contrast,
        texture=ld.texture,
        contact_shade=ld.contact_shade,
        seed=ld.seed,
        normalize=normalize,
        centres=centres,
        rays=rays[0],
        ray_px=rays[1],
    )
    crops = CropDataset(train_pairs, augment=True, samples_per_pair=per_pair, **kw)
    train = DataLoader(
        crops,
        batch_size=ld.batch_size,
        shuffle=True,
        drop_last=len(crops) > ld.batch_size,
        num_workers=ld.num_workers,
        persistent_workers=ld.num_workers > 0,
    )
    val = None
    if val_pairs:
        val = DataLoader(CropDataset(val_pairs, augment=False, **kw), batch_size=ld.batch_size, num_workers=0)
    return train, val, len(train_pairs), len(val_pairs)


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
    its validation split and why its contact weight is what it is."""

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
    finetuned: dict | None = None  # fine-tuning: the base checkpoint and the corrected images (metrics.json)

    def entries(self) -> dict:
        """The checkpoint entries inference reads back (drgan.segmenters.registry.load_segmenter)."""
        from drgan.segmenters.calibrate import PIXEL_SCALE_KEY, WORKING_DIAMETER_KEY
        from drgan.segmenters.noise_match import NOISE_KEY

        return {PIXEL_SCALE_KEY: self.pixel_scale, NOISE_KEY: self.noise, WORKING_DIAMETER_KEY: self.diameter}


def segment(cfg: DictConfig) -> dict:
    """Train one segmenter (or fine-tune one on a user's corrected images: ``finetune=`` with ``corrected=``);
    return final metrics. Writes everything under cfg.out."""
    import lightning.pytorch as L

    from drgan.segmenters.calibrate import check_grid

    wall_start = time.perf_counter()
    with open_dict(cfg):
        cfg.paths.root_dir = str(Path(cfg.paths.root_dir).expanduser().resolve())
    L.seed_everything(int(cfg.seed), workers=True)

    # Settings first (early stopping; the model: an allow-listed class, or a ConfigError naming model._target_),
    # then data: bad folders, sizes or mask values fail here, before the run folder gets anything.
    stopper = early_stopping(cfg.get("early_stopping"))
    calibration_grid = check_grid(cfg.get("split_calibration"))
    prepared = prepare_finetune(cfg) if cfg.get("finetune") or cfg.get("corrected") else prepare(cfg)
    return fit_and_record(cfg, prepared, stopper, calibration_grid, wall_start)


def scaled_pairs(cfg: DictConfig, source: TrainingPairs, manifest: dict | None, model):
    """(pairs, pixel_scale, working scale, working diameter, contour width): the source's pairs read, their contour
    class redrawn where ``loader.contour_px`` asks (`redrawn_contours`) and brought to the model's working scale
    (`at_working_scale`)."""
    redraw = LoaderSettings.from_config(cfg).contour_px
    pairs = redrawn_contours(source.load(), redraw)
    contour_width = source.contour_width(manifest) if redraw is None else redraw
    scaled = at_working_scale(cfg, model, pairs, source.pixel_scale(manifest), contour_width)
    return (*scaled, contour_width)


def prepare(cfg: DictConfig) -> Prepared:
    """A fresh segmenter and its pairs (generated or real), checked; see `Prepared`."""
    from drgan.segmenters.registry import build_segmenter

    source = checked_source(cfg)
    manifest = source.manifest()
    contact_why = None
    if "contact_weight" in cfg.model:
        with open_dict(cfg):
            cfg.model.contact_weight, contact_why = resolve_contact_weight(
                cfg.model.contact_weight, source.polarity(manifest), source.clark_evans(manifest)
            )
        log.info("model.contact_weight=%s (%s)", cfg.model.contact_weight, contact_why)
    model = build_segmenter(cfg.model, "model")
    pairs, pixel_scale, working, diameter, _ = scaled_pairs(cfg, source, manifest, model)
    if pixel_scale != 1.0:
        log.info(
            "the pairs hold %.3g px per real image px: inference will resample images by %.3g (stored in the "
            "checkpoints)", pixel_scale, pixel_scale,
        )  # fmt: skip
    noise = source.noise_level(pairs, manifest)
    if noise is not None:
        log.info(
            "the generated images' fine-noise level is %.4f: inference adds white noise to cleaner images up to it "
            "(inference.noise_match; stored in the checkpoints)", noise,
        )  # fmt: skip
    pairs, check_pairs = held_out_check(cfg, source, pairs)
    return Prepared(model, pairs, check_pairs, pixel_scale, noise, diameter, working, contact_why=contact_why)


FINETUNE_KEPT = ("val_fraction", "check_fraction", "loader.working_px", "loader.contour_px")  # the base run's


def finetune_base(cfg: DictConfig) -> tuple[Path, DictConfig | None, str]:
    """(segmenter checkpoint, the base run's config or None, its generated pairs' folder) of ``finetune=RUN``: a
    pipeline run folder (its segment/), a segment run folder or a checkpoint file; ``data=`` names the pairs where
    the base run does not record them. A ConfigError or DataError names what is missing."""
    if not cfg.get("finetune") or not cfg.get("corrected"):
        raise ConfigError(
            "segment: fine-tuning needs both finetune=RUN (a pipeline run, a segment run folder or a segmenter "
            "checkpoint) and corrected=DIR (the corrected outlines: drgan.segmenters.corrections)"
        )
    if cfg.get("real"):
        raise ConfigError("segment: finetune= fine-tunes on generated pairs and corrected images; real= is not used")
    run = Path(cfg.finetune).expanduser()
    folder = run / "segment" if (run / "segment" / "checkpoints").is_dir() else run
    ckpt = run if run.is_file() else folder / "checkpoints" / "last.ckpt"
    if not ckpt.is_file():
        raise DataError(
            f"finetune={run}: no segmenter checkpoint there (expected a pipeline run with segment/checkpoints/"
            "last.ckpt, a segment run folder with checkpoints/last.ckpt, or a .ckpt file)"
        )
    config_file = (ckpt.parent.parent if run.is_file() else folder) / ".hydra" / "config.yaml"
    base = OmegaConf.load(config_file) if config_file.is_file() else None  # YAML: nothing in it runs
    data = cfg.get("data") or (base.get("data") if base is not None else None)
    if not data:
        raise ConfigError(
            f"finetune={run}: its run does not record the generated pairs it was trained on; give data=DIR too"
        )
    return ckpt, base, str(data)


def prepare_finetune(cfg: DictConfig) -> Prepared:
    """The segmenter of ``finetune=RUN`` with its generated pairs (split and held out as its own run did: the base's
    seed, val_fraction, check_fraction and loader scale settings) and the corrected images of ``corrected=DIR``
    resampled to its scale (drgan.segmenters.corrections); trained ``correction.epochs`` epochs at
    ``correction.lr``. The checkpoints keep the base's pixel scale, noise level and working diameter."""
    from drgan.segmenters.corrections import correction_pairs, load_corrections
    from drgan.segmenters.registry import load_segmenter

    ckpt, base, data = finetune_base(cfg)
    setting = cfg.correction
    lr = setting_float("correction.lr", setting.lr, 0.0)
    epochs = setting_int("correction.epochs", setting.epochs, 1)
    setting_float("correction.share", setting.share, 0.0)
    model = load_segmenter(ckpt, "finetune").train()  # (loaded for inference, in eval mode)
    model.hparams.lr = lr
    split_seed = int(base.seed) if base is not None and base.get("seed") is not None else int(cfg.seed)
    with open_dict(cfg):
        cfg.data = data
        if base is not None:
            for key in FINETUNE_KEPT:
                OmegaConf.update(cfg, key, OmegaConf.select(base, key), merge=False)
        cfg.trainer.max_epochs = epochs
        # the model is the base's (its class and keywords, as its checkpoint records them; lr the fine-tuning's)
        cfg.model = OmegaConf.create(dict(model.hparams))
    source = checked_source(cfg)
    items = load_corrections(cfg.corrected, setting.get("images"), cfg.get("crop_rows", "auto"))
    pairs, pixel_scale, working, _, contour_width = scaled_pairs(cfg, source, source.manifest(), model)
    corrected = correction_pairs(items, model.pixel_scale, contour_width, model.train_noise)
    pairs, check_pairs = held_out_check(cfg, source, pairs, split_seed)
    n = sum(int(lab.max()) for _, lab in items)
    log.info(
        "fine-tuning %s on %d corrected image(s) (%d particles, resampled by %.3g) beside %s's pairs: %d epochs at "
        "lr %g%s", ckpt, len(items), n, model.pixel_scale, data, epochs, lr,
        "" if base is not None else " (no config of the base run found: this run's seed and loader settings)",
    )  # fmt: skip
    return Prepared(
        model,
        pairs,
        check_pairs,
        model.pixel_scale,
        model.train_noise,
        model.working_diameter,
        working,
        corrected,
        split_seed=split_seed,
        contact_why="the base segmenter's",
        finetuned={"base": str(ckpt), "corrected": str(cfg.corrected), "images": [item.id for item, _ in items],
                   "particles": n, "pixel_scale": pixel_scale},
    )  # fmt: skip


def fit_and_record(cfg: DictConfig, prepared: Prepared, stopper, calibration_grid, wall_start: float) -> dict:
    """Train ``prepared.model`` into cfg.out, then calibrate its split, run its closed-loop check, log and write
    metrics.json; the final metrics."""
    from hydra.utils import instantiate
    from lightning.pytorch.callbacks import ModelCheckpoint

    from drgan.callbacks.progress_bar import StepProgress
    from drgan.callbacks.resume import ResumeCheckpoint
    from drgan.runtime import flat_config, instantiate_loggers, resolve_checkpoint, start_loggers
    from drgan.segmenters.module import CheckpointEntries, ScoreHistory, settled

    model, out = prepared.model, Path(cfg.out)
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

    ckpt_path = resolve_checkpoint(cfg.get("ckpt_path"), out)
    tags = {"name": str(cfg.name), "output_dir": str(out), **{str(t): "1" for t in cfg.get("tags") or []}}
    loggers = instantiate_loggers(
        cfg.get("logger"), out, resume=ckpt_path is not None, tags=tags, parent_run=cfg.get("parent_run")
    )
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
        "segmenter %s: %d train / %d val pairs%s, run folder %s", cfg.name, n_train, n_val,
        f" and {len(prepared.corrected)} corrected images" if prepared.corrected else "", out,
    )  # fmt: skip
    trainer.fit(
        model, train_dataloaders=train_loader, val_dataloaders=val_loader, ckpt_path=ckpt_path, weights_only=True
    )

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
    calibration = calibrate(model, calibration_pairs, calibration_grid, last, progress)
    if calibration is not None:
        metrics["split/ap50"] = calibration["ap50"]
    check = closed_loop_check(model, prepared.check_pairs, calibration, last, progress)
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
            **({"finetuned": prepared.finetuned} if prepared.finetuned else {}),
            **metrics,
        },
    )
    log.info("done in %.1f s: %s", metrics["time/wall_s"], {k: round(v, 4) for k, v in sorted(metrics.items())})
    return metrics


def calibrate(model, pairs, grid: dict | None, last: Path, progress: bool) -> dict | None:
    """Choose the touching-particle split on ``pairs`` (the validation pairs; drgan.segmenters.calibrate) and store it
    in ``last`` for evaluate/analyze's ``split_core: auto``; None when calibration is off or impossible."""
    from drgan.checkpoint_io import add_entry
    from drgan.segmenters.calibrate import CHECKPOINT_KEY, SEEDED, as_array_free, calibrate_split, markdown_table

    if grid is None:
        return None
    if not pairs or not last.is_file():
        log.warning("split calibration skipped: %s", "no validation pairs" if not pairs else f"no {last}")
        return None
    try:
        calibration = as_array_free(calibrate_split(model.eval(), pairs, grid, progress=progress))
    except ValueError as error:
        log.warning("split calibration skipped: %s", error)
        return None
    add_entry(last, CHECKPOINT_KEY, calibration, "ckpt_path")
    chosen = (
        f"seed_level {calibration['seed_level']}"
        if calibration.get("split") in SEEDED
        else f"split_seeds {calibration.get('split_seeds')}, split_depth {calibration['split_depth']}, split_core "
        f"{calibration['split_core']}"
    )
    log.info(
        "split chosen on %d pairs (particles %.0f px across, median): %s (AP50 %.3f); stored in %s\n%s",
        calibration["n_pairs"],
        calibration.get("particle_px", float("nan")),
        chosen,
        calibration["ap50"],
        last,
        markdown_table(calibration),
    )
    return calibration


def held_out_check(cfg: DictConfig, source: TrainingPairs, pairs, seed: int | None = None) -> tuple[list, list]:
    """(pairs to train and validate on, pairs of the closed-loop check): ``check_fraction`` of a generated set's
    rendered pairs set aside (drgan.segmenters.closed_loop.hold_out; ``seed``: its seed, None: cfg.seed); real images
    keep every pair (their truth is an annotator's, which drgan.evaluate scores on the test ids)."""
    from drgan.segmenters.closed_loop import hold_out

    fraction = check_fraction(cfg)
    if not source.data:
        return pairs, []
    rest, check = hold_out(pairs, fraction, int(cfg.seed) if seed is None else seed)
    if fraction > 0 and not check:
        log.warning(
            "check_fraction=%g: too few rendered pairs with exact labels (%d) to hold out a closed-loop check; "
            "every pair trains", fraction, len(pairs),
        )  # fmt: skip
    elif check:
        log.info("closed-loop check: %d rendered pairs held out (never trained on, never used to choose)", len(check))
    return rest, check


def check_fraction(cfg: DictConfig) -> float:
    """``check_fraction`` as a number in [0, 0.5), or a ConfigError naming it (closed_loop.checked_fraction)."""
    from drgan.segmenters.closed_loop import checked_fraction

    return checked_fraction(setting_float("check_fraction", cfg.get("check_fraction", 0.0), 0.0))


def closed_loop_check(model, pairs, calibration: dict | None, last: Path, progress: bool) -> dict | None:
    """The segmenter scored on its held-out generated pairs (drgan.segmenters.closed_loop), with the split just
    calibrated; stored in ``last`` (evaluate/analyze and the pipeline's report quote it). None without pairs."""
    from drgan.checkpoint_io import add_entry
    from drgan.segmenters.closed_loop import CLOSED_LOOP_KEY, closed_loop, log_summary

    if not pairs:
        return None
    if not last.is_file():
        log.warning("closed-loop check skipped: no %s", last)
        return None
    check = closed_loop(model.eval(), pairs, calibration, progress=progress)
    add_entry(last, CLOSED_LOOP_KEY, check, "ckpt_path")
    log_summary(check)
    return check


def check_metrics(check: dict) -> dict[str, float]:
    """The closed-loop check as flat metrics (MLflow, metrics.json's top level): check/median_error ..."""
    flat = {f"check/{k}": check[k]["value"] for k in ("median_error", "mean_error", "count_error")}
    flat.update({f"check/{k}": check[k] for k in ("edge_offset_px", "merged", "split", "missed", "ap50", "dsc")})
    return {k: float(v) for k, v in flat.items() if v is not None}


@stage_main("conf/segmentation", "segment")
def main(cfg: DictConfig):
    return segment(cfg)


if __name__ == "__main__":
    start(main)
