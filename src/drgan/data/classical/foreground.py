"""Which pixels are particles: the image prepared, its threshold around the blobs, holes, outlines at the edges.

- **Prepared** (`prepare`): one grey channel, particles bright (``1 - grey`` for dark ones), annotations (scale bars,
  text, panel letters; drgan.data.annotations) filled from their surroundings so that they are neither particles
  nor background.
- **Foreground** (`cut_foreground`): Otsu's threshold of the smoothed, flattened image (the uneven illumination
  removed by a grey opening larger than any particle) over the pixels within one diameter of the blobs of the
  particles' size (`blob_centres`; on a grainy film with a few particles, taken again around the blobs that stand
  out of the film's noise), refused when it does not separate two classes (separability below
  ``min_separability``); pieces that reach no blob centre are grain or texture specks; marked and round holes filled
  (`_fill_holes`).
- **Outlines at the edges** (`grow_to_edges`): where the particles' strongest edges lie below Otsu's threshold (a
  sphere's contrast falls off towards its outline), each segment grows out to them, none merging.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy import ndimage as ndi
from skimage.filters import threshold_otsu
from skimage.segmentation import watershed

from drgan.data.annotations import annotation_mask, as_grey
from drgan.data.classical.calibration import CALIBRATION as CAL
from drgan.data.classical.params import SegmentParams
from drgan.data.classical.scale import blob_maxima, out_of_film_noise
from drgan.data.polarity import to_bright


@dataclass
class Prepared:
    """An image ready to threshold: particle-bright, annotations filled, illumination flattened."""

    bright: np.ndarray  # float32, particles bright, annotations filled
    annotations: np.ndarray  # bool: pixels drawn on the image (scale bar, text), never particles
    # What the scale search has segmented of this image, per setting (`_measure`): it refines and compares at scales
    # it has segmented, with both neck depths.
    measured: dict = field(default_factory=dict, repr=False, compare=False)


def prepare(image: np.ndarray, polarity: str, annotations: bool = True) -> Prepared:
    grey = as_grey(image)
    mask = annotation_mask(grey) if annotations else np.zeros(grey.shape, bool)
    bright = to_bright(grey, polarity)
    return Prepared(fill_masked(bright, mask) if mask.any() else bright, mask)


def fill_masked(image: np.ndarray, mask: np.ndarray, size: float = 8.0) -> np.ndarray:
    """``image`` with the ``mask`` pixels replaced by a smooth continuation of their surroundings (normalised
    convolution with a Gaussian of ``size`` px, grown until every masked pixel has a value)."""
    if not mask.any():
        return image
    keep = (~mask).astype(np.float64)
    if not keep.any():
        return image
    values = np.asarray(image, np.float64) * keep
    out = np.asarray(image, np.float64).copy()
    todo = mask.copy()
    while todo.any() and size < 4 * max(image.shape):
        num, den = ndi.gaussian_filter(values, size), ndi.gaussian_filter(keep, size)
        ok = todo & (den > 1e-3)
        out[ok] = num[ok] / den[ok]
        todo &= ~ok
        size *= 2
    out[todo] = float(np.median(image[~mask]))
    return out.astype(np.float32)


def flatten(bright: np.ndarray, size: float) -> np.ndarray:
    """``bright`` less its slowly varying illumination: a grey opening with a square of ``size`` px (it removes
    every bright structure narrower than that: the particles) smoothed by a Gaussian of size / 2, computed on an
    averaged-down copy. No change when size is 0 or above half the image."""
    h, w = bright.shape
    if not size or size >= 0.5 * min(h, w):
        return bright
    from skimage.transform import resize

    f = max(1, int(size // 16))
    small = resize(bright, (max(1, h // f), max(1, w // f)), order=1, anti_aliasing=f > 1) if f > 1 else bright
    k = max(3, int(round(size / f)) | 1)
    background = ndi.grey_opening(small, size=(k, k), mode="reflect")
    background = ndi.gaussian_filter(background, k / 2, mode="reflect")
    if f > 1:
        background = resize(background, (h, w), order=1)
    return (bright - background + float(np.median(background))).astype(np.float32)


def retry_separability(params: SegmentParams) -> float:
    """The separability below which `cut_foreground` thresholds again around the blobs standing out of the film's
    noise: the default CAL.min_separability, or ``params.min_separability`` where it is higher. A threshold below the
    default (the scale search's, lowered for a dense packing, or one set by hand) says which cuts to accept, not
    which to try again: the search measured its fixed points retrying below the default, so the final segmentation
    with the lowered threshold segments what the search measured."""
    return max(params.min_separability, CAL.min_separability)


class Cut(NamedTuple):
    """A threshold's foreground and how well it separates (`_threshold`)."""

    foreground: np.ndarray  # bool
    separability: float  # Otsu's between-class / total variance
    centres: np.ndarray  # bool: the blob centres whose surroundings were thresholded
    smooth: np.ndarray | None = None  # the smoothed image thresholded (None: nothing was)
    threshold: float = math.nan


def cut_foreground(prepared: Prepared, params: SegmentParams, retry_below: float | None = None) -> Cut:
    """The foreground of prepared, with resolved params, and how well its threshold separated (`Cut`).
    ``retry_below``: the separability below which the threshold is taken again around the significant blobs
    (default `retry_separability`; the scale search segments with min_separability 0 but retries as the final
    segmentation will).

    Otsu's threshold is taken over the pixels within one diameter of a blob of the particles' size (not the whole
    image): a few particles on a wide background give a lopsided histogram where Otsu cuts into the background's
    noise, while around the particles both classes are well represented. Where those blobs leave the separability
    below ``retry_below``, it is taken again around the blobs that stand out of the film's noise
    (`blob_centres`' ``significant``; the smoothing and the LoG response are reused): a grainy film whose own maxima
    surrounded the few particles. The retry is kept only where it separates better (on a dense packing no blob
    stands out of the "film", which is the particles' gaps and sides, and the retry has nothing to threshold).

    A connected piece of the foreground is kept when it is at least ``min_area`` and reaches within
    CAL.centre_reach diameters of a blob centre: grain, noise and texture specks past the threshold away from every
    blob of the particles' size are not particles (on a grainy film they outnumber a few particles and would set the
    median); a hollow particle's rim lies within half a diameter of its centre."""
    images = [prepared.bright]
    if params.background:  # the illumination flattened only where it separates particles better
        images.insert(0, flatten(prepared.bright, params.background))
    # "nearest", not "reflect": mirrored, a particle a few px from the border and its image blur across the gap,
    # and its segment reaches the border (and is not measured)
    smooths = [ndi.gaussian_filter(im, params.sigma, mode="nearest") if params.sigma > 0 else im for im in images]
    maxima = [blob_maxima(im, params.scale) for im in images]

    def best(centre_sets: list[np.ndarray]) -> Cut:
        return max(
            (_threshold(smooth, c & ~prepared.annotations, prepared.annotations, params.scale)
             for smooth, c in zip(smooths, centre_sets)),
            key=lambda cut: cut.separability,
        )  # fmt: skip

    cut = best([peak for _, peak in maxima])
    if cut.separability < (retry_separability(params) if retry_below is None else retry_below):
        retry = best([out_of_film_noise(im, r, peak) for im, (r, peak) in zip(images, maxima)])
        cut = retry if retry.separability >= cut.separability else cut
    if cut.separability < params.min_separability:
        return cut._replace(foreground=np.zeros(cut.foreground.shape, bool))
    components, n = ndi.label(cut.foreground)
    keep = np.bincount(components.ravel(), minlength=n + 1) >= params.min_area
    near = ndi.distance_transform_edt(~cut.centres) <= CAL.centre_reach * params.scale
    keep &= np.bincount(components[near], minlength=n + 1) > 0
    keep[0] = False
    return cut._replace(foreground=_fill_holes(keep[components], params, prepared.annotations))


def _threshold(smooth: np.ndarray, centres: np.ndarray, annotations: np.ndarray, scale: float) -> Cut:
    """Pixels of ``smooth`` past Otsu's threshold of the pixels within ``scale`` of the ``centres``, and how well
    that threshold separates them (`Cut`)."""
    empty = np.zeros(smooth.shape, bool)
    if smooth.max() - smooth.min() < 1e-6:
        return Cut(empty, 0.0, empty)
    if not centres.any():
        return Cut(empty, 0.0, centres)
    region = (ndi.distance_transform_edt(~centres) <= scale) & ~annotations
    values = smooth[region]
    threshold = threshold_otsu(values)
    above = values > threshold
    w1 = above.mean()
    if w1 in (0.0, 1.0):
        return Cut(empty, 0.0, centres)
    between = w1 * (1 - w1) * (values[above].mean() - values[~above].mean()) ** 2
    return Cut((smooth > threshold) & ~annotations, float(between / values.var()), centres, smooth, float(threshold))


def _fill_holes(foreground: np.ndarray, params: SegmentParams, marks: np.ndarray) -> np.ndarray:
    """``foreground`` with its marked and its round holes filled (the holes found once for both).

    A hole that lies wholly in ``marks`` (the annotation mask) is a mark enclosed by one piece of the foreground: it
    lies on a particle, and the particle goes on under it. Most are the particles' own texture read as marks
    (specks and strokes of character size and contrast on textured spheres: left as pinholes, the distance transform
    around them would cut each sphere into pieces); a label printed on a particle hides part of it. Marks on the
    film or reaching it stay out of the foreground.

    A round hole: a particle seen as a bright rim around a centre as grey as the background (SEM edge effect on
    spheres, hollow shells) thresholds into a ring, which the watershed would cut into arcs of a fraction of its
    size. A hole is the particle's own centre when it is round (solidity at least CAL.round_hole_solidity, area at least
    CAL.round_hole_fill of the disc of its major axis) and of plausible area; a gap among touching particles is bounded
    by several convex outlines, so it is concave (an equal-sphere packing's: solidity ~0.6) or, smoothed at a large
    scale, a rounded polygon far from a disc, and stays."""
    holes = ndi.binary_fill_holes(foreground) & ~foreground
    if not holes.any():
        return foreground
    from skimage.measure import regionprops

    labels, n = ndi.label(holes)
    marked = np.zeros(n + 1, bool)
    if marks.any():
        marked = np.bincount(labels[~marks], minlength=n + 1) == 0
        marked[0] = False
    filled = foreground | marked[labels]
    areas = np.bincount(labels.ravel(), minlength=n + 1)
    plausible = (areas >= params.min_area) & (areas <= params.max_area) & ~marked
    plausible[0] = False
    if not plausible.any():  # a noisy foreground has thousands of pinholes: their shapes are never asked for
        return filled
    labels = np.where(plausible[labels], labels, 0)
    for region in regionprops(labels):
        disc = math.pi / 4 * region.axis_major_length**2  # the disc of the hole's length: a round hole fills most
        if (
            region.area >= CAL.round_hole_fill * disc and region.solidity >= CAL.round_hole_solidity
        ):  # the hull last: dearest
            filled[region.slice] |= region.image
    return filled


def edge_level(cut: Cut, scale: float, outside: np.ndarray | None = None) -> float | None:
    """The grey level of the particles' strongest edges, where it lies below the threshold (None elsewhere).

    Otsu's threshold sits where the two classes' histograms part, about halfway up the particles' edge or above
    it (on EMPS images, a median 0.58 of the way from the film's grey to the particles'), and that is where
    a step edge blurred by the optics and the smoothing lies. A particle whose projected thickness or shading
    falls off towards its outline (a sphere in transmission: contrast sqrt(1 - r^2 / R^2)) has its steepest
    gradient, and its outline, further out (the EMPS instance maps' outlines: 0.38). Of the iso-grey
    contours in a band around the outlines (CAL.outline_band diameters either side), the level whose contour has the
    largest mean gradient magnitude is the particles' edge. ``outside``: the foreground's distance transform
    outside it, when the caller has it."""
    foreground, smooth = cut.foreground, cut.smooth
    if smooth is None or not foreground.any() or foreground.all():
        return None
    band = _outline_band(scale)
    outside = ndi.distance_transform_edt(~foreground) if outside is None else outside
    film = smooth[outside > band]
    if film.size == 0:
        return None
    low, high = float(np.median(film)), float(np.median(smooth[foreground]))
    if high <= low:
        return None
    near = (outside <= band) & (ndi.distance_transform_edt(foreground) <= band)
    gy, gx = np.gradient(smooth)
    gradient = np.hypot(gx, gy)
    strength = []
    for level in low + (high - low) * CAL.outline_levels:
        above = smooth >= level
        contour = above & ~ndi.binary_erosion(above) & near
        strength.append(gradient[contour].mean() if contour.sum() >= CAL.min_contour else 0.0)
    level = float(low + (high - low) * CAL.outline_levels[int(np.argmax(strength))])
    return level if level < cut.threshold else None


def _outline_band(scale: float) -> float:
    """px: CAL.outline_band diameters, at least 2 px."""
    return max(2.0, CAL.outline_band * scale)


def grow_to_edges(
    cut: Cut, labels: np.ndarray, scale: float, min_area: int, annotations: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(labels, foreground) with every segment grown out to the particles' edge level (`edge_level`) over the
    pixels connected to it, each pixel to the segment it is reached from first going down the grey (a watershed):
    segments of ``min_area`` or more grow, none merge and none appear, none into the ``annotations``. Unchanged
    where the edges lie at the threshold or above."""
    extent = grown_foreground(cut, scale, annotations)
    if extent is cut.foreground:
        return labels, extent
    grown = watershed(-cut.smooth, labels, mask=extent).astype(np.int32)
    # A watershed sliver or speck below min_area stays as it was: grown, hundreds of them on a textured film
    # would cross min_area and count as particles.
    small = np.bincount(labels.ravel(), minlength=grown.max() + 1) < min_area
    small[0] = False
    kept = ~small[grown] | (labels > 0)
    return np.where(kept, grown, 0).astype(np.int32), extent & kept


def grown_foreground(cut: Cut, scale: float, annotations: np.ndarray) -> np.ndarray:
    """The foreground grown out to the edge level (`edge_level`), over connected pixels at most CAL.outline_band
    diameters from it (where the level was measured: not into a film that happens to lie above it); the foreground
    itself where there is no lower edge."""
    if cut.smooth is None or not cut.foreground.any():
        return cut.foreground
    outside = ndi.distance_transform_edt(~cut.foreground)
    level = edge_level(cut, scale, outside)
    if level is None:
        return cut.foreground
    within = (outside <= _outline_band(scale)) & ~annotations
    return ndi.binary_propagation(cut.foreground, mask=((cut.smooth >= level) & within) | cut.foreground)
