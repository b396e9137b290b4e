"""Polarity: are the particles brighter than the background (SEM, HIM) or darker (TEM, STEM bright field, TSEM)?

Every step that looks at pixels (patch mining, background extraction, the generate contrast filter, the
best-epoch brightness guard) needs to know which side of the grey scale the particles are on. drgan works on
"particle-bright" images internally: a dark-particle image is segmented as its negative, ``1 - image``.

Detection, without masks (`detect_polarity`): each image votes (`image_vote`) from two cues, and the majority
of the images decides; the share of agreeing images is reported as the confidence.

1. **Convexity** (`isophote_convexity`, the main cue): particles are convex blobs, so along their outlines the
   bright side (bright particles) or the dark side (dark particles) bulges out. At smoothings of 1, 2, 4 and 8 px
   (on a copy of about 512 x 512 pixels), the curvature of the isophotes is measured at the strongest edges (top
   10 % of the gradient, scale bars and text left out: `drgan.data.annotations.annotation_mask`); each resolved
   edge pixel (radius of curvature above 2 sigma) votes its sign, weighted by its gradient. It holds in densely
   packed fields: the outlines of touching particles stay convex arcs, and the background's gaps between them
   are concave with sharp cusps, which take few pixels.
2. **Histogram mode** (the vote before): Otsu's threshold of the image smoothed at 2 px splits it in two; the
   background is the class holding the most frequent grey level. Right in sparse fields, backwards where the
   particles cover more of the image than the background. It enters with a weight of 0.1 on its margin
   (|mode - threshold| over the grey range), so it only breaks near-ties of the convexity.

Measured (experiments/profile/polarity_check.py; settings chosen on the EMPS ids 0-7 only): each EMPS image alone
(one image = one user's folder), scored on the 240 with >= 5 instances against the instance maps: 97.5 % right on
the dev half (116/119) and on the held-out half (118/121), 95.8 % on the 96 dense ones (instances on > 40 % of
the image; 94.5 % of the 55 held-out ones); the mode vote alone: 83.8 % (63.5 % dense). What it still misses:
close-packed monolayers of spheres (the gaps turn into dark dots), crossing rods (the background between them
forms convex cells), particles whose texture or hollow outline has more edges than their outline, faint
straight-edged cubes. All 32 TiO2 SEM train images vote "bright" (convexity +0.39 to +0.70) and all 32 TSEM
ones "dark" (-0.66 to -0.34). About 0.2-0.3 s per image on a loaded 2-core machine.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi
from skimage.filters import gaussian, threshold_otsu

from drgan.core.errors import ConfigError, DataError

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


# The convexity cue: isophote curvature at the strongest edges, on a copy of about WORKING_SIDE^2 pixels (larger
# images block-averaged by an integer factor), at CURVATURE_SIGMAS px of smoothing (octaves: particles of ~5 to
# ~200 px on such a copy).
WORKING_SIDE = 512
CURVATURE_SIGMAS = (1.0, 2.0, 4.0, 8.0)
EDGE_QUANTILE = 0.9  # the edges: pixels whose gradient is in the top 10 % of the image's
MAX_CURVATURE = 0.5  # |curvature x sigma| below this: isophotes resolved at this smoothing (radius > 2 sigma)
# Gaussian derivative orders (rows, columns): x, y, xx, yy, xy
_DERIVATIVES = ((0, 1), (1, 0), (0, 2), (2, 0), (1, 1))
MODE_WEIGHT = 0.1  # the mode vote's margin counts this much against the convexity (a tie-break)


@dataclass(frozen=True)
class ImageVote:
    polarity: str | None  # None: no usable contrast (a flat image)
    mode: float  # grey level of the histogram's mode (the background in a sparse field)
    threshold: float  # Otsu threshold
    minority_fraction: float  # area fraction of the class not holding the mode
    mode_vote: str | None = None  # the histogram-mode vote alone
    mode_margin: float = 0.0  # |mode - threshold| / the grey range (1st-99th percentile), in [0, 1]
    convexity: float = 0.0  # isophote convexity in [-1, 1]: > 0 bright blobs, < 0 dark blobs, 0 no edges
    margin: float = 0.0  # |convexity + MODE_WEIGHT x signed mode margin|: how clearly this image voted
    background: float = 0.0  # median grey of the background side of Otsu's threshold, in the voted polarity


@dataclass(frozen=True)
class PolarityEstimate:
    polarity: str
    confidence: float  # share of voting images that agree with the majority
    votes: tuple[ImageVote, ...]

    def as_dict(self) -> dict:
        cast = [v for v in self.votes if v.polarity is not None]
        return {
            "polarity": self.polarity,
            "confidence": round(self.confidence, 4),
            "images": len(self.votes),
            "bright_votes": sum(v.polarity == "bright" for v in self.votes),
            "dark_votes": sum(v.polarity == "dark" for v in self.votes),
            "mode_vote_disagrees": sum(v.mode_vote not in (None, v.polarity) for v in cast),
            "convexity_median": round(float(np.median([v.convexity for v in cast])), 4) if cast else None,
            "background_grey_median": round(float(np.median([v.background for v in cast])), 4) if cast else None,
        }


def _working_copy(image: np.ndarray) -> tuple[np.ndarray, int]:
    """``image`` block-averaged by an integer factor to about WORKING_SIDE^2 pixels; the factor."""
    factor = max(1, int(round(math.sqrt(image.size) / WORKING_SIDE)))
    if factor == 1:
        return image, 1
    h, w = (image.shape[0] // factor) * factor, (image.shape[1] // factor) * factor
    return image[:h, :w].reshape(h // factor, factor, w // factor, factor).mean(axis=(1, 3)), factor


def _annotations(image: np.ndarray) -> np.ndarray:
    """Scale bars, their text and panel letters (`drgan.data.annotations.annotation_mask`), on a [0, 1] copy."""
    from drgan.data.annotations import annotation_mask

    low, high = float(image.min()), float(image.max())
    if low < 0 or high > 1:
        image = (image - low) / (high - low)
    return annotation_mask(image)


def isophote_convexity(
    image: np.ndarray, sigmas: Iterable[float] = CURVATURE_SIGMAS, exclude: np.ndarray | None = None
) -> float:
    """Which side of the image's edges is convex, in [-1, 1]: > 0 when the bright side is (bright particles).

    At each smoothing sigma, the curvature of the isophotes (the lines of equal grey) is measured where the
    gradient is strongest (the top 10 % of edge pixels, off the border and off ``exclude``). It is positive where
    the bright side bulges out, as it does around a bright blob. Each such pixel votes its sign, weighted by its
    gradient; only isophotes resolved at that sigma vote (radius of curvature above 2 sigma): a gap smaller than
    the smoothing turns into a round dark dot whatever its shape, and noise into dots of both signs. The result
    is the mean over the sigmas that had edges (0 when none had).

    Particles are convex, and their outlines are convex arcs all along, even where they touch: the background
    between touching particles forms concave gaps with sharp cusps, where the curvature concentrates on a few
    pixels. Counting pixels (not summing curvature, which would only count components and holes) therefore
    follows the particles in sparse and in densely packed fields alike.
    """
    image = np.asarray(image, np.float64)
    image = image - image.mean()  # the truncated kernels' sums are not exactly 0: no offset to leak
    h, w = image.shape
    away = None if exclude is None or not exclude.any() else ndi.distance_transform_edt(~exclude)
    scores = []
    for sigma in sigmas:
        margin = int(3 * sigma) + 1
        if min(h, w) <= 2 * margin + 2:
            continue
        gx, gy, gxx, gyy, gxy = (ndi.gaussian_filter(image, sigma, order=o) for o in _DERIVATIVES)
        g2 = gx**2 + gy**2
        valid = np.zeros((h, w), bool)
        valid[margin:-margin, margin:-margin] = True
        if away is not None:
            valid &= away > 2 * sigma + 2
        if valid.sum() < 100:
            continue
        grad = np.sqrt(g2)
        cut = float(np.quantile(grad[valid], EDGE_QUANTILE))
        if cut <= 1e-9:
            continue
        edge = valid & (grad >= cut)
        ex, ey, exx, eyy, exy = gx[edge], gy[edge], gxx[edge], gyy[edge], gxy[edge]
        curvature = -(exx * ey**2 - 2 * exy * ex * ey + eyy * ex**2) / g2[edge] ** 1.5 * sigma
        resolved = np.abs(curvature) < MAX_CURVATURE
        weight = grad[edge][resolved]
        if weight.sum() > 0:
            scores.append(float(np.average(np.sign(curvature[resolved]), weights=weight)))
    return float(np.mean(scores)) if scores else 0.0


def image_vote(image: np.ndarray, sigma: float = 2.0, bins: int = 256) -> ImageVote:
    """One image's vote, from two cues.

    - The histogram mode (the vote before): Otsu's threshold of the image smoothed at ``sigma`` splits it in two;
      the background is the class holding the most frequent grey level. Right in sparse fields, backwards where
      particles cover more of the image than the background.
    - The convexity of the particle side (`isophote_convexity`, scale bars and text left out): particles are
      convex blobs, in sparse and in dense fields.

    The score is the convexity plus MODE_WEIGHT times the mode vote's signed margin (|mode - threshold| over the
    grey range, in [0, 1]): where the two disagree, the mode vote wins only when the convexity's margin is under
    0.1 times its own (edges with no clear convex side); its sign is the vote. On EMPS (dev half) any weight from
    0 to 0.1 scores the same, and weights from 0.15 up lose dense fields.
    """
    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 2:
        raise DataError(f"polarity: expected a grey image (H, W), got shape {image.shape}")
    smooth = gaussian(image, sigma=sigma, preserve_range=True) if sigma > 0 else image
    low, high = float(smooth.min()), float(smooth.max())
    if high - low < 1e-6:
        return ImageVote(None, low, low, 0.0, background=low)
    threshold = float(threshold_otsu(smooth))
    hist, edges = np.histogram(smooth, bins=bins, range=(low, high))
    k = int(hist.argmax())
    mode = float(0.5 * (edges[k] + edges[k + 1]))
    above = smooth > threshold
    mode_vote = "bright" if mode < threshold else "dark"
    minority = float(above.mean()) if mode_vote == "bright" else float(1.0 - above.mean())
    p1, p99 = (float(v) for v in np.percentile(smooth, [1, 99]))
    mode_margin = min(1.0, abs(mode - threshold) / max(p99 - p1, 1e-6))

    work, factor = _working_copy(image)
    annotations = _annotations(image)
    if factor > 1:
        h, w = work.shape
        annotations = annotations[: h * factor, : w * factor].reshape(h, factor, w, factor).any(axis=(1, 3))
    convexity = isophote_convexity(work, exclude=annotations)

    score = convexity + MODE_WEIGHT * (mode_margin if mode_vote == "bright" else -mode_margin)
    polarity = mode_vote if score == 0 else ("bright" if score > 0 else "dark")
    side = smooth[~above] if polarity == "bright" else smooth[above]
    background = float(np.median(side)) if side.size else mode
    return ImageVote(polarity, mode, threshold, minority, mode_vote, mode_margin, convexity, abs(score), background)


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
