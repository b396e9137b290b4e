"""Each generated image draws its own grey levels from the real images' spread (`generate grey_spread=true`).

The generator learns one value per scene parameter, so every image of a generated set shows about the same
background grey and particle contrast, while real micrographs vary from image to image (illumination, detector
settings, film thickness): on tio2_tsem the real 256-px windows' background grey spans 0.69-0.87 (5th-95th
percentile) and the generated set's 0.78-0.92 (experiments/realism/README.md). A segmenter trained on the narrow set
calls the darkest real images all particle and the brightest all background (issue 29).

With grey_spread, image i takes the (background, particle) mean grey of one real *train* patch, drawn with the
image's own seed, and its grey levels are mapped by the affine function that sends its own background mean and
particle mean (known exactly from its labels) there: x -> b' + (x - b) (p' - b') / (p - b), clipped to [0, 1].
Labels do not change; noise and texture scale with the contrast, as they do in a real image. The real patches'
means come from drgan's classical segmentation with the patch set's own settings (no annotation is read), so they
are what drgan's profile would measure.
"""

from __future__ import annotations

import numpy as np

from drgan.errors import DataError

MIN_SHARE = 0.02  # a patch counts only when particles and background each cover at least this share of it


def patch_grey_levels(patches: np.ndarray, segment: dict, polarity: str) -> np.ndarray:
    """(N, 2) mean (background, particle) grey of each patch in which both are shown (others left out)."""
    from drgan.data.particles import SegmentParams, particle_foreground

    params = SegmentParams.from_config(segment)
    levels = []
    for patch in np.asarray(patches, dtype=np.float32):
        particle = particle_foreground(patch, params, polarity)
        share = particle.mean()
        if MIN_SHARE <= share <= 1 - MIN_SHARE:
            levels.append((float(patch[~particle].mean()), float(patch[particle].mean())))
    if not levels:
        raise DataError(
            f"grey_spread: none of the {len(patches)} real patches shows both particles and background (classical "
            "segmentation with the patch set's settings); set grey_spread=false"
        )
    return np.asarray(levels, dtype=np.float64)


def match_grey(image: np.ndarray, labels: np.ndarray, target: tuple[float, float]) -> np.ndarray:
    """``image`` with its background mean and particle mean (``labels`` > 0) moved to ``target`` (background,
    particle) by one affine grey map, clipped to [0, 1]. Unchanged when either is missing or they are equal."""
    image = np.asarray(image, dtype=np.float32)
    particle = np.asarray(labels) > 0
    if not particle.any() or particle.all():
        return image
    background_mean, particle_mean = float(image[~particle].mean()), float(image[particle].mean())
    if abs(particle_mean - background_mean) < 1e-6:
        return image
    new_background, new_particle = target
    gain = (new_particle - new_background) / (particle_mean - background_mean)
    return np.clip(new_background + (image - background_mean) * gain, 0.0, 1.0).astype(np.float32)


def draw(levels: np.ndarray, seed: int) -> tuple[float, float]:
    """One real patch's (background, particle) grey, drawn with ``seed`` (the image's own)."""
    return tuple(levels[np.random.default_rng(seed).integers(len(levels))])
