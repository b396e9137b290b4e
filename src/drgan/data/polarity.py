"""Polarity: are the particles brighter than the background (SEM, HIM) or darker (TEM, STEM bright field, TSEM)?

Every step that looks at pixels (patch mining, background extraction, the generate contrast filter, the
best-epoch brightness guard) needs to know which side of the grey scale the particles are on. drgan works on
"particle-bright" images internally: a dark-particle image is segmented as its negative, ``1 - image``.

Detection, without masks (`detect_polarity`): in each image, Otsu's threshold of the smoothed image splits
it into two classes. The background is the class that holds the histogram's mode: the substrate is the
single most frequent grey level of a particle image, even where agglomerates cover much of it. The particles
are then the other class: brighter than the threshold when the mode lies below it. Each image votes; the
majority decides, and the share of agreeing images is reported as the confidence. Measured on the shared
sets: all 32 TiO2 SEM train images vote "bright" (mode 0.11-0.19 below thresholds 0.27-0.35) and all 32 TSEM
ones "dark" (mode 0.68-0.92 above thresholds 0.39-0.50).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from skimage.filters import gaussian, threshold_otsu

from drgan.errors import ConfigError, DataError

POLARITIES = ("bright", "dark")
SETTINGS = ("auto",) + POLARITIES


def check_polarity(value, setting: str = "data.polarity", allow_auto: bool = False) -> str:
    """``value`` as one of bright / dark (and auto when allowed), or a ConfigError naming ``setting``."""
    allowed = SETTINGS if allow_auto else POLARITIES
    if not isinstance(value, str) or value not in allowed:
        raise ConfigError(
            f"{setting}={value!r}: expected one of {', '.join(allowed)} (particles brighter or darker than "
            "the background)"
        )
    return value


def to_bright(image: np.ndarray, polarity: str) -> np.ndarray:
    """The image with particles bright: unchanged for "bright", its negative (1 - image) for "dark"."""
    check_polarity(polarity, "polarity")
    image = np.asarray(image, dtype=np.float32)
    return image if polarity == "bright" else (1.0 - image).astype(np.float32)


@dataclass(frozen=True)
class ImageVote:
    polarity: str | None  # None: no usable contrast (a flat image)
    mode: float  # grey level of the histogram's mode (the background)
    threshold: float  # Otsu threshold
    minority_fraction: float  # area fraction of the class not holding the mode (the particles)


@dataclass(frozen=True)
class PolarityEstimate:
    polarity: str
    confidence: float  # share of voting images that agree with the majority
    votes: tuple[ImageVote, ...]

    def as_dict(self) -> dict:
        return {
            "polarity": self.polarity,
            "confidence": round(self.confidence, 4),
            "images": len(self.votes),
            "bright_votes": sum(v.polarity == "bright" for v in self.votes),
            "dark_votes": sum(v.polarity == "dark" for v in self.votes),
            "background_grey_median": float(np.median([v.mode for v in self.votes])) if self.votes else None,
        }


def image_vote(image: np.ndarray, sigma: float = 2.0, bins: int = 256) -> ImageVote:
    """One image's vote: on which side of Otsu's threshold does its most frequent grey level lie?"""
    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 2:
        raise DataError(f"polarity: expected a grey image (H, W), got shape {image.shape}")
    smooth = gaussian(image, sigma=sigma, preserve_range=True) if sigma > 0 else image
    low, high = float(smooth.min()), float(smooth.max())
    if high - low < 1e-6:
        return ImageVote(None, low, low, 0.0)
    threshold = float(threshold_otsu(smooth))
    hist, edges = np.histogram(smooth, bins=bins, range=(low, high))
    k = int(hist.argmax())
    mode = float(0.5 * (edges[k] + edges[k + 1]))
    if mode < threshold:
        return ImageVote("bright", mode, threshold, float((smooth > threshold).mean()))
    return ImageVote("dark", mode, threshold, float((smooth <= threshold).mean()))


def detect_polarity(images: Iterable[np.ndarray], sigma: float = 2.0) -> PolarityEstimate:
    """Majority vote of `image_vote` over ``images``; a DataError when no image has contrast, or on a tie."""
    votes = tuple(image_vote(image, sigma) for image in images)
    cast = [v.polarity for v in votes if v.polarity is not None]
    if not cast:
        raise DataError(
            f"polarity: none of the {len(votes)} image(s) has any contrast; cannot tell particles from "
            "background (set data.polarity=bright or dark)"
        )
    bright = cast.count("bright")
    dark = len(cast) - bright
    if bright == dark:
        raise DataError(
            f"polarity: {bright} image(s) look like bright particles and {dark} like dark ones; set "
            "data.polarity=bright or data.polarity=dark"
        )
    polarity = "bright" if bright > dark else "dark"
    return PolarityEstimate(polarity, max(bright, dark) / len(cast), votes)


def resolve_polarity(setting: str, images: Iterable[np.ndarray]) -> tuple[str, PolarityEstimate | None]:
    """``setting`` (auto / bright / dark) -> (polarity, the estimate when it was detected)."""
    check_polarity(setting, allow_auto=True)
    if setting != "auto":
        return setting, None
    estimate = detect_polarity(images)
    return estimate.polarity, estimate
