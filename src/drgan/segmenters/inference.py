"""Sliding-window inference: a full image (e.g. 1024 x 712) -> class probabilities -> class map.

The image is covered by `tile` x `tile` windows at stride tile * (1 - overlap) (the last row/column of
windows is shifted to end at the image border); windows go through the network in batches, and their
softmax probabilities are blended with a Gaussian weight (sigma = tile / 8, peak at the tile centre,
floored at 1e-3 so borders still count) that down-weights tile borders, where the network sees least
context. Images smaller than a tile are reflect-padded to one tile. One tile covering the whole image
gives exactly the network's direct output (the weights cancel).

Touching particles: a network trained with a thin contour class (1 px for TiO2 SEM) rarely draws the
whole line between two touching particles, so the particle class alone merges agglomerates into blobs.
``split_touching`` (default in ``predict``) cuts them apart with a seeded watershed: foreground = particle
or contour class (probabilities summed > 0.5), seeds = the h-maxima (depth ``split_depth`` px) of the
smoothed distance transform of the predicted particle class, so the contour pixels the network does draw
deepen the valleys between particles. Neighbouring watershed regions are then separated by a 1-px line of
the contour class, so that 4-connected labelling of the particle class (drgan.metrics.instance_scores,
drgan.analyze) returns one instance per region. Defaults (depth 2 px, smoothing 1 px) were chosen on annotated
real *train* images (experiments/tio2_sem/RESULTS.md), never on test images; drgan.segment calibrates the split per
segmenter on its validation pairs (drgan.segmenters.calibrate).
"""

from __future__ import annotations

import inspect
import logging

import numpy as np
import torch

from drgan.core.errors import ConfigError, DataError, check_keys
from drgan.data.images import resample
from drgan.metrics.statistics import SPECK_PX
from drgan.segmenters.noise_match import match_noise
from drgan.segmenters.pairs import normalization

log = logging.getLogger(__name__)
SPLITS = ("auto", "watershed", "centres", "star", "none")  # auto: the segmenter's own (`split_of`)


def gaussian_weight(tile: int, sigma_fraction: float = 0.125) -> torch.Tensor:
    r = torch.arange(tile, dtype=torch.float32) - (tile - 1) / 2
    g = torch.exp(-0.5 * (r / (tile * sigma_fraction)) ** 2)
    w = g[:, None] * g[None, :]
    return (w / w.max()).clamp_min(1e-3)


def _starts(size: int, tile: int, stride: int) -> list[int]:
    starts = list(range(0, size - tile + 1, stride))
    if starts[-1] != size - tile:
        starts.append(size - tile)
    return starts


MIRRORS = ((), (-1,), (-2,), (-2, -1))  # identity, left-right, up-down, both: the test-time mirrorings


@torch.no_grad()
def predict_probs(
    model: torch.nn.Module,
    image: np.ndarray,
    tile: int = 384,
    overlap: float = 0.125,
    batch_size: int = 8,
    mirror: bool = False,
) -> np.ndarray:
    """(H, W) float image in [0, 1] -> (C, H, W) float32 class probabilities.

    The whole image is normalised first as the model was trained (its ``input_normalization``, e.g. "zscore";
    "none" for plain modules), then cut into overlapping tiles whose probabilities are blended with a
    Gaussian weight. ``mirror``: each tile's probabilities are the mean over its four mirror images (``MIRRORS``,
    each prediction flipped back; test-time augmentation as nnU-Net's mirroring), 4 x the network's work."""
    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 2:
        raise DataError(f"predict: expected a 2-D grey image, got shape {image.shape}")
    shift, scale = normalization(image, getattr(model, "input_normalization", "none"))
    image = (image - shift) / scale
    if not 0.0 <= overlap < 1.0 or tile < 1:
        raise ConfigError(f"predict: need tile >= 1 and overlap in [0, 1), got tile={tile}, overlap={overlap}")
    model.eval()
    h, w = image.shape
    padded = image
    if h < tile or w < tile:
        pad = ((0, max(tile - h, 0)), (0, max(tile - w, 0)))
        padded = np.pad(image, pad, mode="reflect" if h > 1 and w > 1 and tile < 2 * min(h, w) else "edge")
    ph, pw = padded.shape
    stride = max(1, int(round(tile * (1 - overlap))))
    corners = [(y, x) for y in _starts(ph, tile, stride) for x in _starts(pw, tile, stride)]
    weight = gaussian_weight(tile)
    src = torch.from_numpy(padded)
    acc, norm = None, torch.zeros(ph, pw)
    for k in range(0, len(corners), batch_size):
        chunk = corners[k : k + batch_size]
        batch = torch.stack([src[y : y + tile, x : x + tile] for y, x in chunk])[:, None]
        if mirror:
            probs = sum(_probabilities(model, batch.flip(d)).flip(d) for d in MIRRORS) / len(MIRRORS)
        else:
            probs = _probabilities(model, batch)
        if acc is None:
            acc = torch.zeros(probs.shape[1], ph, pw)
        for (y, x), p in zip(chunk, probs):
            acc[:, y : y + tile, x : x + tile] += p * weight
            norm[y : y + tile, x : x + tile] += weight
    return (acc / norm)[:, :h, :w].numpy()


def _probabilities(model: torch.nn.Module, batch: torch.Tensor) -> torch.Tensor:
    output = model(batch)
    return model.probabilities(output) if hasattr(model, "probabilities") else output.softmax(dim=1)


def split_of(model, split: str = "auto") -> str:
    """The split a segmenter's class maps get: ``split`` as given, or for "auto" the model's own
    (``instance_split``: "centres" for the instance-aware segmenter, drgan.segmenters.instances), else the
    distance-transform watershed."""
    if split != "auto":
        return split
    return getattr(model, "instance_split", "watershed")


SEED_RULES = ("hmaxima", "components")  # the watershed split's seeds: h-maxima only, or every core piece kept too


def check_split(
    split: str, split_depth: float, split_smooth: float, split_core: float | None = None, split_seeds: str = "hmaxima"
) -> None:
    if split not in SPLITS:
        raise ConfigError(f"inference.split={split!r}: expected one of {SPLITS}")
    if split_seeds not in SEED_RULES:
        raise ConfigError(f"inference.split_seeds={split_seeds!r}: expected one of {SEED_RULES} (or auto)")
    if split_core is not None and not 0.0 < split_core < 1.0:
        raise ConfigError(
            f"inference.split_core={split_core}: expected a particle probability in (0, 1), or null (the argmax)"
        )
    if not split_depth > 0:
        raise ConfigError(f"inference.split_depth={split_depth}: expected > 0 (px)")
    if not split_smooth >= 0:
        raise ConfigError(f"inference.split_smooth={split_smooth}: expected >= 0 (px)")


def separate_regions(labels: np.ndarray) -> np.ndarray:
    """Class map of a label image: 1 inside regions, 2 on a 1-px line between 4-adjacent different regions
    (the pixel of the larger label of each such pair), 0 elsewhere. Its particle class has exactly one
    4-connected component per region, unless a region is itself cut by the line (thin necks)."""
    labels = np.asarray(labels)
    line = np.zeros(labels.shape, bool)
    # vertical neighbours (rows r, r + 1), then horizontal ones (columns c, c + 1)
    for first, second in (
        ((slice(None, -1), slice(None)), (slice(1, None), slice(None))),
        ((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
    ):
        a, b = labels[first], labels[second]
        cut = (a > 0) & (b > 0) & (a != b)
        line[first] |= cut & (a > b)  # the larger label's pixel of each pair becomes line
        line[second] |= cut & (b > a)
    out = (labels > 0).astype(np.uint8)
    out[line] = 2
    return out


def split_touching(
    probs: np.ndarray,
    split_depth: float = 2.0,
    split_smooth: float = 1.0,
    split_core: float | None = None,
    split_seeds: str = "hmaxima",
    min_px: float = SPECK_PX,
) -> np.ndarray:
    """(C, H, W) class probabilities -> (H, W) uint8 class map whose particle class separates touching
    particles (module docstring). ``split_core``: the particle core whose distance transform seeds the split is
    where the particle probability exceeds it (a stricter core opens the necks between touching particles);
    None: where the particle class wins the argmax. ``split_seeds``: "hmaxima", the h-maxima of the smoothed
    distance transform; "components", those and at least one seed in every 4-connected piece of the core
    (drgan.data.classical.watershed.component_seeds: a piece the contour class cut off is a particle of its own).
    A region the watershed floods smaller than ``min_px`` px (a speck, as the statistics define it) goes to the
    neighbour it shares the most border with, or is dropped where it touches none (`merge_specks`): a seed in a
    sliver of core between two particles, which `components` keeps, would otherwise be a false particle to AP50
    (experiments/statistics/closed_loop.md, "Specks the split made")."""
    from drgan.data.classical.watershed import component_seeds, distance_watershed, flood, merge_specks

    check_split("watershed", split_depth, split_smooth, split_core, split_seeds)
    probs = np.asarray(probs)
    if probs.ndim != 3 or probs.shape[0] < 3:
        raise DataError(f"split_touching: expected (3, H, W) class probabilities, got shape {probs.shape}")
    foreground = probs[1] + probs[2] > 0.5
    core = probs.argmax(axis=0) == 1 if split_core is None else probs[1] > split_core
    if not core.any():
        return np.zeros(core.shape, np.uint8)
    # the classical segmentation's watershed, seeded at the h-maxima of the core's smoothed distance transform;
    # foreground pieces without a seed (no particle-class core) stay 0: they are stray contour pixels, not particles
    if split_seeds == "components":
        labels = flood(*component_seeds(core, smooth=split_smooth, depth=split_depth), foreground)
    else:
        labels = distance_watershed(core, foreground, smooth=split_smooth, depth=split_depth)
    return separate_regions(merge_specks(labels, min_px))


def split_by_centres(probs: np.ndarray, seed_level: float = 0.5, min_seed_px: int = 2) -> np.ndarray:
    """(4, H, W) probabilities (3 classes, then the instance-aware segmenter's centre map) -> (H, W) uint8 class map
    whose particle class holds one 4-connected region per particle: the foreground (particle + contour > 0.5) flooded
    over the negative centre map from its pieces above ``seed_level`` (drgan.segmenters.instances). Seeds smaller
    than ``min_seed_px`` pixels are noise."""
    from scipy import ndimage
    from skimage.segmentation import watershed

    probs = np.asarray(probs)
    if probs.ndim != 3 or probs.shape[0] != 4:
        raise DataError(f"split_by_centres: expected (4, H, W) class and centre probabilities, got {probs.shape}")
    check_seed_level(seed_level)
    foreground = probs[1] + probs[2] > 0.5
    centre = probs[3]
    seeds, n = ndimage.label((centre > seed_level) & foreground)
    if n == 0:
        return np.zeros(foreground.shape, np.uint8)
    sizes = np.bincount(seeds.ravel())
    small = sizes < min_seed_px
    small[0] = False
    if small.any():
        seeds[small[seeds]] = 0
    labels = watershed(-centre, seeds, mask=foreground)
    return separate_regions(labels)


def split_by_stars(probs: np.ndarray, seed_level: float = 0.5) -> np.ndarray:
    """(3 + 1 + n_rays, H, W) outputs of the star-convex segmenter (class probabilities, object probability, ray
    distances in px; drgan.segmenters.star) -> (H, W) uint8 class map with one 4-connected particle region per polygon
    kept (drgan.segmenters.polygons.star_labels)."""
    from drgan.segmenters.polygons import star_labels

    probs = np.asarray(probs)
    if probs.ndim != 3 or probs.shape[0] < 6:
        raise DataError(f"split_by_stars: expected (3 + 1 + rays, H, W) outputs, got shape {probs.shape}")
    check_seed_level(seed_level)
    return separate_regions(star_labels(probs, seed_level))


def check_seed_level(seed_level) -> float:
    if isinstance(seed_level, bool) or not isinstance(seed_level, (int, float)) or not 0.0 < seed_level < 1.0:
        raise ConfigError(f"inference.seed_level={seed_level!r}: expected a centre-map level in (0, 1)")
    return float(seed_level)


def probs_at_scale(model: torch.nn.Module, image: np.ndarray, scale: float, level: float | None, **kw) -> np.ndarray:
    """The network's class probabilities of ``image`` seen resampled by ``scale`` (with white noise up to the
    fine-noise ``level`` when it is cleaner: drgan.segmenters.noise_match), brought back to the image's size."""
    probs = predict_probs(model, match_noise(resample(image, scale), level), **kw)
    return resample_probs(probs, np.shape(image)) if scale != 1.0 else probs


def predict(
    model: torch.nn.Module,
    image: np.ndarray,
    split: str = "auto",
    split_depth: float = 2.0,
    split_smooth: float = 1.0,
    split_core: float | None = None,
    seed_level: float = 0.5,
    split_seeds: str = "hmaxima",
    pixel_scale: float | str | None = None,
    noise_match: float | bool | None = None,
    annotations: bool = True,
    fill_holes: bool = True,
    **kw,
) -> np.ndarray:
    """(H, W) image -> (H, W) uint8 class map (0 background, 1 particle, 2 contour).

    split="watershed": touching particles cut apart (``split_touching``); "centres": seeded by the instance-aware
    segmenter's centre map above ``seed_level`` (drgan.segmenters.instances.split_by_centres); "none": the
    network's argmax; "auto": the model's own (`split_of`).

    ``pixel_scale``: the network sees the image resampled by this factor (area-averaged when below 1) and its
    probabilities are brought back to the image's size; None: the model's own (``model.pixel_scale``, stored by
    drgan.segment from its generated pairs: their px per real px, times the working scale; 1.0 for real-trained
    U-Nets); "auto": `resolve_pixel_scale`. The split's lengths (``split_depth``, ``split_smooth``: px at the
    network's scale, as calibrated) are scaled with it. "per_image":
    a first pass at the model's own scale, then the image again at the scale its particles measure (`image_scale`:
    their area-weighted median diameter brought to the training pairs' own, ``model.working_diameter``).

    ``noise_match``: the network sees the (resampled) image with white noise up to this fine-noise level when it is
    cleaner (drgan.segmenters.noise_match); None: the model's own (``model.train_noise``, stored by drgan.segment from
    its generated pairs; none for real-trained models: off); false or 0: off.

    ``annotations``: particles lying mostly on a figure's scale bar, its text or a panel letter
    (drgan.data.annotations.annotation_mask, as the classical segmentation leaves them out) are dropped.

    ``fill_holes``: a particle's holes (pixels of no particle that it alone encloses, `filled_holes`) are its own: a
    particle is a solid, its area-equivalent diameter that of its outline (as ImageJ's traced ROIs and ISO 13322-1's
    projected area take it), and a ring the network draws around a bright centre is one particle."""
    check_split(split, split_depth, split_smooth, split_core, split_seeds)
    split = split_of(model, split)
    own = getattr(model, "pixel_scale", 1.0)
    pixel_scale = resolve_pixel_scale(model, pixel_scale)
    per_image = pixel_scale == PER_IMAGE
    if per_image:
        check_working_diameter(model)
    scale = check_pixel_scale(own if pixel_scale is None or per_image else pixel_scale)
    level = check_noise_match(getattr(model, "train_noise", None) if noise_match is None else noise_match)

    def classes_at(scale: float) -> tuple[np.ndarray, np.ndarray]:
        probs = probs_at_scale(model, image, scale, level, **kw)
        depth, smooth = split_depth / scale, split_smooth / scale
        if split == "star":
            if probs.shape[0] < 6:
                raise ConfigError(
                    "inference.split=star: this segmenter has no ray distances (only drgan.segmenters.star."
                    "StarSegmenterModule has); use split=watershed or auto"
                )
            if scale != 1.0:
                probs[4:] /= scale  # ray lengths in px of the network's scale -> of the image's
            return split_by_stars(probs, seed_level), probs
        if split == "centres":
            if probs.shape[0] != 4:
                raise ConfigError(
                    "inference.split=centres: this segmenter has no centre map (only drgan.segmenters.instances."
                    "CentreSegmenterModule has); use split=watershed or auto"
                )
            return split_by_centres(probs, seed_level), probs
        if split == "none":
            return probs[:3].argmax(axis=0).astype(np.uint8), probs
        return split_touching(probs[:3], depth, smooth, split_core, split_seeds), probs

    classes, probs = classes_at(scale)
    better = image_scale(classes, probs, model.working_diameter, scale) if per_image else None
    if better is not None:
        log.info("pixel_scale=%s: image resampled by %.3g (the segmenter's own: %.3g)", PER_IMAGE, better, scale)
        classes, _ = classes_at(better)
    if fill_holes:
        classes = filled_holes(classes)
    return without_annotations(classes, image) if annotations else classes


def filled_holes(classes: np.ndarray) -> np.ndarray:
    """``classes`` (uint8 class map) with every hole of a particle set to the particle class: a connected piece of
    non-particle pixels (background or contour) that one particle (4-connected component of the particle class)
    encloses and that holds no pixel of another particle. Touching particles' shared gaps, which no single particle
    encloses, stay as they are."""
    from scipy import ndimage

    classes = np.asarray(classes)
    labels, n = ndimage.label(classes == 1)
    if n == 0:
        return classes
    out = classes.copy()
    for i, box in enumerate(ndimage.find_objects(labels), start=1):
        if box is None:
            continue
        own = labels[box] == i
        holes = ndimage.binary_fill_holes(own) & ~own
        if not holes.any():
            continue
        pieces, k = ndimage.label(holes)
        others = np.bincount(pieces[labels[box] > 0].ravel(), minlength=k + 1)  # particle pixels in each piece
        keep = others == 0
        keep[0] = False
        region = out[box]
        region[keep[pieces]] = 1
    return out


PER_IMAGE = "per_image"  # inference.pixel_scale: each image's own scale (`image_scale`)
AUTO = "auto"  # inference.pixel_scale: per_image for the instance-aware segmenter, else the segmenter's own


def resolve_pixel_scale(model, value):
    """``inference.pixel_scale`` with "auto" resolved: ``PER_IMAGE`` for a segmenter that learnt whole particles at one
    working diameter (``needs_centres``: the instance-aware one, drgan.segmenters.pairs.working_scale) and stores it,
    else None (the segmenter's own scale: the U-Net's classes are local). Measured in experiments/statistics/segmenters.md,
    "A scale per image"."""
    if value != AUTO:
        return value
    return PER_IMAGE if getattr(model, "needs_centres", False) and getattr(model, "working_diameter", None) else None


RESCALE_TOLERANCE = 1.5  # per_image: a measured scale less than this factor above the segmenter's own is not used
RESCALE_RANGE = 4.0  # per_image: images are enlarged at most this factor beyond the segmenter's own scale
RESCALE_MIN_PARTICLES = 3  # per_image: fewer particles found measure nothing (the segmenter's own scale is kept)


def image_scale(classes: np.ndarray, probs: np.ndarray, working_diameter: float, scale: float) -> float | None:
    """The larger pixel scale at which the particles of a class map predicted at ``scale`` (the segmenter's own)
    would span ``working_diameter`` px (the area-weighted median particle of its training pairs, at the network's
    scale), or None to keep ``scale``: fewer than RESCALE_MIN_PARTICLES particles, or a scale less than
    RESCALE_TOLERANCE x ``scale``. At most RESCALE_RANGE x ``scale`` (and 16). Only enlarging: merged particles
    measure larger than they are, fragments smaller but the area weighting discounts them, so only a measurement
    of small particles is trusted (shrinking an image whose first pass merged its particles merges more). The
    particles are those of the split ``classes``,
    else (fewer than RESCALE_MIN_PARTICLES there: particles too small for the split's seeds at this scale) the
    4-connected regions of the plain argmax of its class probabilities ``probs``; their size is the area-weighted median
    (drgan.metrics.statistics.area_median), which the specks and fragments of a first pass at the wrong scale do not
    move (a plain median of one large particle and its fragments measures the fragments).

    Why: a segmenter learns one particle size from its pairs (the instance-aware one a 40-px working diameter:
    drgan.segmenters.pairs.working_scale); an image whose particles are far smaller (a set that mixes 350-px and
    65-px particles) is shrunk with the rest until they vanish. Cellpose estimates each image's diameter
    for the same reason; here the first pass's own particles measure it. One measurement, not an iteration: a
    segmenter shown particles larger than it learnt fragments them, which would measure them smaller still."""
    from drgan.metrics.instance_scores import binarize_and_label
    from drgan.metrics.statistics import area_median, particles

    diameters = particles(binarize_and_label(classes)).diameter
    if len(diameters) < RESCALE_MIN_PARTICLES:
        diameters = particles(binarize_and_label(probs[:3].argmax(axis=0))).diameter
    if len(diameters) < RESCALE_MIN_PARTICLES:
        return None
    better = float(min(16.0, scale * RESCALE_RANGE, working_diameter / area_median(diameters)))
    return better if better >= scale * RESCALE_TOLERANCE else None


def without_annotations(classes: np.ndarray, image: np.ndarray, share: float = 0.5) -> np.ndarray:
    """``classes`` with every particle (4-connected component of the particle class) that has at least ``share`` of
    its pixels on the image's annotations (scale bars, text, panel letters: annotation_mask) set to background, and
    contour pixels on them too."""
    from scipy import ndimage as ndi

    from drgan.data.annotations import annotation_mask, as_grey

    mask = annotation_mask(as_grey(image))
    if not mask.any():
        return classes
    labels, n = ndi.label(classes == 1)
    on = np.bincount(labels[mask], minlength=n + 1) / np.maximum(np.bincount(labels.ravel(), minlength=n + 1), 1)
    on[0] = 0.0  # the background is no particle
    kept = classes.copy()
    kept[(on >= share)[labels] | ((classes == 2) & mask)] = 0
    return kept


def check_noise_match(value) -> float | None:
    """``inference.noise_match`` as a level (None: off): false / 0 / None are off, a number in (0, 1] a level."""
    if value is None or value is False or value == 0:
        return None
    if value is True or not isinstance(value, (int, float)) or not 0 < value <= 1:
        raise ConfigError(
            f"inference.noise_match={value!r}: expected a fine-noise level in (0, 1], false (off) or null (the "
            "model's own)"
        )
    return float(value)


def check_working_diameter(model) -> float:
    """The training pairs' area-weighted median diameter ``inference.pixel_scale=per_image`` aims at, or a
    ConfigError."""
    diameter = getattr(model, "working_diameter", None)
    if not diameter:
        raise ConfigError(
            f"inference.pixel_scale={PER_IMAGE}: this segmenter's checkpoint stores no working diameter (segmenters "
            "trained by drgan.segment from 2026-11-29 on do); use null (its own scale) or a factor"
        )
    return float(diameter)


def check_pixel_scale(value, per_image: bool = False) -> float | str:
    """``inference.pixel_scale`` as a factor (or ``PER_IMAGE`` where ``per_image`` allows it), else a ConfigError."""
    if per_image and value == PER_IMAGE:
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value <= 16:
        raise ConfigError(
            f"inference.pixel_scale={value!r}: expected a factor in (0, 16], {PER_IMAGE} (each image resampled so "
            "that its particles span the segmenter's training diameter) or null (the model's own)"
        )
    return float(value)


def resample_probs(probs: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(C, h, w) probabilities -> (C, H, W), bilinear (each channel; they still sum to 1)."""
    from skimage.transform import resize

    return np.stack([resize(p, shape, order=1, preserve_range=True) for p in probs]).astype(np.float32)


def make_predictor(model: torch.nn.Module, inference: dict):
    """f(image) -> class map with the settings of a config's `inference:` block, checked now (before any
    image is predicted). Known settings and their defaults are those of ``predict`` and ``predict_probs``."""
    inference = dict(inference)
    defaults = {
        name: p.default
        for fn in (predict_probs, predict)
        for name, p in inspect.signature(fn).parameters.items()
        if p.default is not inspect.Parameter.empty
    }
    check_keys("inference", inference, defaults, "setting")
    settings = {**defaults, **inference}
    check_split(settings["split"], settings["split_depth"], settings["split_smooth"], settings["split_core"])
    scale = resolve_pixel_scale(model, settings["pixel_scale"])
    if scale is not None and check_pixel_scale(scale, True) == PER_IMAGE:
        check_working_diameter(model)
    check_noise_match(settings["noise_match"])
    if not isinstance(settings["mirror"], bool):
        raise ConfigError(f"inference.mirror={settings['mirror']!r}: expected true or false")
    return lambda image: predict(model, image, **inference)
