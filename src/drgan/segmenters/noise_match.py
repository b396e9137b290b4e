"""Noise matching at inference: a real image cleaner than the segmenter's training images gets white noise up to
their level before the network sees it (`inference.noise_match`).

Generated pairs can be noisier than the images they imitate (the GAN's learned noise, Monte Carlo sampling at a
low spp: `drgan.synthetic.noise_check`), and a U-Net trained on them may then read a clean real particle as something
it never saw: with generated pairs a few times as noisy as the real images, a seed can find almost none of the real
particles, and the same network finds them once the real images carry the pairs' noise level
(experiments/pipeline/README.md). Noise is only ever added, never removed: an image as
noisy as the training images or more is left as it is.

The level is one number per image, the same estimator on both sides: the robust standard deviation (1.4826 x the
median absolute deviation) of the image minus its 1 px Gaussian blur (`drgan.synthetic.noise_check.fine_detail`, the
detail generate's noise check reads too), which flat regions (background and particle cores, most of a micrograph)
dominate and edges barely move. drgan.segment stores the median level of its
generated training images in the checkpoint (`NOISE_KEY`); a real-trained segmenter stores none (its images are the
real ones). The noise added is seeded by the image's size, so a prediction is repeatable.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from functools import lru_cache

import numpy as np

from drgan.core.checkpoint_io import positive_entry

MAD_TO_SIGMA = 1.4826  # a Gaussian's standard deviation per median absolute deviation
SAMPLE = 64  # training images whose level is measured (the first ones)
NOISE_KEY = "drgan_train_noise"  # the checkpoint entry: the training images' level (absent: no matching)


def noise_level(image: np.ndarray) -> float:
    """The image's fine-noise level: 1.4826 x the median absolute deviation of its `fine_detail` (the image minus its
    Gaussian blur), in the image's grey units."""
    from drgan.synthetic.noise_check import fine_detail

    detail = fine_detail(image)
    return float(MAD_TO_SIGMA * np.median(np.abs(detail - np.median(detail))))


@lru_cache(maxsize=1)
def white_gain() -> float:
    """`noise_level` of unit white noise: what the estimator reads per unit of the noise `match_noise` adds
    (below 1: the blur subtracted takes part of the noise with it). Measured once on 512 x 512 px."""
    return noise_level(np.random.default_rng(0).standard_normal((512, 512)))


def training_level(images: Iterable[np.ndarray]) -> float | None:
    """The median `noise_level` of up to SAMPLE training images (None for none)."""
    levels = [noise_level(image) for _, image in zip(range(SAMPLE), images)]
    return float(np.median(levels)) if levels else None


def added_sigma(image_level: float, train_level: float) -> float:
    """The standard deviation of the white noise that brings an image at ``image_level`` to ``train_level``
    (`noise_level`s; levels add in quadrature): 0 when the image is as noisy already."""
    missing = train_level**2 - image_level**2
    return math.sqrt(missing) / white_gain() if missing > 0 else 0.0


def match_noise(image: np.ndarray, train_level: float | None) -> np.ndarray:
    """``image`` (float grey in [0, 1]) with white noise up to ``train_level`` (`added_sigma`), clipped to [0, 1];
    unchanged for None or 0, or when the image is as noisy already. The noise is seeded by the image's shape."""
    if not train_level:
        return image
    sigma = added_sigma(noise_level(image), float(train_level))
    if sigma == 0.0:
        return image
    rng = np.random.default_rng(list(np.shape(image)))
    noisy = np.asarray(image, dtype=np.float32) + rng.normal(0.0, sigma, np.shape(image)).astype(np.float32)
    return np.clip(noisy, 0.0, 1.0)


def stored_level(checkpoint: Mapping) -> float | None:
    """The training images' level a checkpoint holds (`NOISE_KEY`), or None (real-trained, from before it was
    stored, or malformed)."""
    return positive_entry(checkpoint, NOISE_KEY)
