"""What drgan.segment trains on: the pairs' source (generated or real, `TrainingPairs`), the loader settings, the pairs
brought to the segmenter's working scale, the closed-loop hold-out, and the train and validation loaders."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig

from drgan.core.errors import ConfigError, setting_float, setting_int
from drgan.core.typed_settings import read_settings, setting, typed

log = logging.getLogger(__name__)


@typed
@dataclass(frozen=True)
class _Source:
    data: str | None = None
    real: str | None = None


@typed
@dataclass(frozen=True)
class TrainingPairs:
    """Where segment's training pairs come from: ``data`` (pairs of drgan.generate) or ``real`` (the train ids of
    an annotated dataset, with its split, crop_rows, masks, mask_suffix and contour_px); exactly one of the two.
    Field defaults = segment.yaml's (tests/test_segment.py compares)."""

    data: str | None = None
    real: str | None = None
    split: str | None = None
    contour_px: int = setting(1, ge=0)
    crop_rows: Any = "auto"
    masks: str = "masks"
    mask_suffix: str = "auto"

    @classmethod
    def from_config(cls, cfg: DictConfig) -> TrainingPairs:
        source = read_settings(_Source, cfg, "segment")
        if bool(source.data) == bool(source.real):
            raise ConfigError("segment: give exactly one of data=DIR (generated pairs) or real=DATASET (real baseline)")
        return read_settings(cls, cfg, "segment") if source.real else cls(data=source.data)  # real-only keys: real

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
    min_working_px: float | None = None  # smaller median particles are enlarged to this diameter; None: never
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
            min_working_px=_working_px(ld.get("min_working_px"), "loader.min_working_px", auto=False),
            contour_px=None if ld.get("contour_px") is None else setting_int("loader.contour_px", ld.contour_px, 0),
            seed=setting_int("seed", cfg.seed),
            val_fraction=setting_float("val_fraction", cfg.val_fraction),
        )


def _working_px(value, key: str = "loader.working_px", auto: bool = True) -> float | str | None:
    """The diameter setting ``key``: null (off), "auto" where ``auto`` allows it, or a diameter in px (> 1), else a
    ConfigError naming the key."""
    if value is None or (auto and value == "auto"):
        return value
    number = setting_float(key, value, 0.0)
    if not number > 1.0:
        raise ConfigError(
            f"{key}={value}: expected a particle diameter in px (> 1), {'auto or ' if auto else ''}null (off)"
        )
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
    """(pairs, pixel_scale, scale, diameter): the pairs resampled to the model's working diameter (`working_px_of`
    and ``loader.min_working_px``, drgan.segmenters.pairs.working_scale), their pixel scale multiplied alike
    (inference resamples real images by it), and their particles' area-weighted median diameter after it (px,
    drgan.metrics.statistics.area_median; None without particles: inference's per-image scale aims at it);
    unchanged when no resampling is needed."""
    from drgan.metrics.statistics import area_median
    from drgan.segmenters.pairs import rescale_pair, sample_diameters, working_scale

    ld = LoaderSettings.from_config(cfg)
    diameters = sample_diameters(pairs)
    scale, median = working_scale(pairs, working_px_of(ld.working_px, model), ld.crop, diameters, ld.min_working_px)
    by_area = area_median(diameters)
    diameter = round(by_area * scale, 3) if by_area > 0 else None  # nan (no particle) fails the test too
    if scale == 1.0:
        return pairs, pixel_scale, 1.0, diameter
    contour = max(1, int(round(contour_px * scale))) if contour_px > 0 else 0
    log.info(
        "loader.working_px=%s, min_working_px=%s: the pairs' median particle spans %.0f px; the pairs are %s by %.3g "
        "(to %.0f px particles, contour %d px), and inference resamples images alike (pixel scale %.3g, stored in the "
        "checkpoints)", ld.working_px, ld.min_working_px, median, "shrunk" if scale < 1 else "enlarged", scale,
        median * scale, contour, pixel_scale * scale,
    )  # fmt: skip
    return [rescale_pair(p, scale, contour) for p in pairs], round(pixel_scale * scale, 6), scale, diameter


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
        per_pair = crops_by_area(train_pairs, ld.crop * scale) if TrainingPairs.from_config(cfg).real else 1
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


@dataclass
class ScaledPairs:
    """`scaled_pairs`: the pairs to train and validate on (at the working scale), the closed-loop check's pairs (as
    rendered), the pixel scale and working scale and diameter the checkpoints store, the contour width, and the
    generated images' fine-noise level at the working scale (`TrainingPairs.noise_level`; None for real images)."""

    pairs: list
    check: list
    pixel_scale: float
    working: float
    diameter: float | None
    contour_width: int
    noise: float | None


def scaled_pairs(cfg: DictConfig, source: TrainingPairs, manifest: dict | None, model, split_seed: int | None = None):
    """The source's pairs read, their contour class redrawn where ``loader.contour_px`` asks (`redrawn_contours`),
    brought to the model's working scale (`at_working_scale`), and the closed-loop check's pairs held out
    (`held_out_check`, seed ``split_seed``) as rendered: real images come to inference at their own scale too.
    A `ScaledPairs`."""
    redraw = LoaderSettings.from_config(cfg).contour_px
    pairs = redrawn_contours(source.load(), redraw)
    contour_width = source.contour_width(manifest) if redraw is None else redraw
    scaled, pixel_scale, working, diameter = at_working_scale(
        cfg, model, pairs, source.pixel_scale(manifest), contour_width
    )
    noise = source.noise_level(scaled, manifest)
    _, check = held_out_check(cfg, source, pairs, split_seed)
    held = {p.id for p in check}
    rest = [p for p in scaled if p.id not in held]
    return ScaledPairs(rest, check, pixel_scale, working, diameter, contour_width, noise)


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
    return read_settings(_HeldOut, cfg, "segment").check_fraction


def _check_fraction(stage: str, value) -> float:
    from drgan.segmenters.closed_loop import checked_fraction

    return checked_fraction(setting_float("check_fraction", value, 0.0))


@typed
@dataclass(frozen=True)
class _HeldOut:
    check_fraction: float = setting(0.0, check=_check_fraction)  # absent (a run from before the check): no check
