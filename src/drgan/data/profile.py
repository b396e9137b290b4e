"""Profiling unannotated particle images: the numbers a material config needs, measured without masks.

Every estimator works on grey images in [0, 1] (drgan.data.images.read_grey) and the particles' polarity
(drgan.data.polarity). The pieces, in the order `python -m drgan.profile` runs them:

- `segment_image`: drgan.data.classical (the particle scale measured first, every length set from it), keeping the
  segments of plausible area;
- `particle_table`: equivalent diameter, centroid, axis ratio, border contact, contact with another segment;
- `background_noise`: background grey (median of background pixels), noise sigma (robust MAD of the
  high-pass residual on background pixels, corrected for what the high-pass removes) and grain (the stddev
  of the Gaussian whose blurred white noise, through the same high-pass, has the same lag-1 autocorrelation);
- `edge_samples` / `edge_profile`: the mean particle edge, grey against signed distance to the segmented edge
  (isolated particles only), in units of the particle contrast, and whether it shows a defocus fringe
  (`fit_fringe`: the transmission scene's fringe term fitted to it);
- `fit_sizes`: normal, lognormal and two-component lognormal mixture fitted to the diameters, chosen by BIC;
- `patch_counts`: particles whose centroid lies inside each 256 px window of a grid;
- `clark_evans`: nearest-neighbour ratio of the centroids (< 1 clustered, 1 random, > 1 regular);
- `pixel_size_nm`: TIFF resolution tags, or the Zeiss CZ_SEM tag's image pixel size.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from drgan.data.classical import Segmentation, SegmentParams, segment_with_report
from drgan.data.patches import window_starts
from drgan.errors import DataError

# The high-pass that isolates noise from the background's slow shading: image minus its Gaussian blur.
HIGHPASS_SIGMA = 3.0  # px
# Background pixels: outside the particle foreground grown by this many px (the high-pass spreads edges).
BACKGROUND_MARGIN = 6  # px

# --- segmentation -----------------------------------------------------------------------------------------


def segment_image(image: np.ndarray, params: SegmentParams, polarity: str) -> Segmentation:
    """drgan.data.classical's segmentation with resolved ``params`` (`Segmentation`), keeping only segments of
    plausible area."""
    found = segment_with_report(image, params, polarity)
    areas = np.bincount(found.labels.ravel())
    keep = (areas >= params.min_area) & (areas <= params.max_area)
    keep[0] = False
    return found._replace(labels=np.where(keep[found.labels], found.labels, 0).astype(np.int32))


PARTICLE_COLUMNS = ("area_px", "diameter_px", "row", "col", "axis_ratio", "touches_border", "touches_other")


def particle_table(labels: np.ndarray) -> dict[str, np.ndarray]:
    """Per segment: area, equivalent diameter 2 sqrt(area / pi), centroid, major/minor axis ratio, and whether
    it touches the image border or another segment (8-neighbourhood)."""
    from skimage.measure import regionprops

    h, w = labels.shape
    # A segment touches another when a pixel of it has an 8-neighbour of a different non-zero label.
    grown_max = ndi.grey_dilation(labels, size=3)
    grown_min = -ndi.grey_dilation(-np.where(labels > 0, labels, labels.max() + 1), size=3)
    contact = (labels > 0) & ((grown_max != labels) | (grown_min != labels))
    touching = set(np.unique(labels[contact]).tolist())
    rows = {c: [] for c in PARTICLE_COLUMNS}
    for region in regionprops(labels):
        r0, c0, r1, c1 = region.bbox
        minor = region.axis_minor_length
        rows["area_px"].append(region.area)
        rows["diameter_px"].append(2.0 * math.sqrt(region.area / math.pi))
        rows["row"].append(region.centroid[0])
        rows["col"].append(region.centroid[1])
        rows["axis_ratio"].append(region.axis_major_length / minor if minor > 0 else np.inf)
        rows["touches_border"].append(r0 == 0 or c0 == 0 or r1 == h or c1 == w)
        rows["touches_other"].append(region.label in touching)
    return {c: np.asarray(v, dtype=bool if c.startswith("touches") else np.float64) for c, v in rows.items()}


def component_table(mask: np.ndarray, min_area: int = 1, max_area: int | None = None) -> dict[str, np.ndarray]:
    """`particle_table` of a binary mask's 4-connected components of plausible area (the masks' side of the check)."""
    labels, _ = ndi.label(np.asarray(mask, bool))
    areas = np.bincount(labels.ravel())
    keep = (areas >= min_area) & (areas <= (max_area if max_area is not None else areas.max()))
    keep[0] = False
    return particle_table(np.where(keep[labels], labels, 0).astype(np.int32))


# --- particles per window ---------------------------------------------------------------------------------


def patch_counts(
    rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int], size: int = 256, stride: int | None = None
) -> np.ndarray:
    """Particles whose centroid lies inside each size x size window of the grid (stride size // 2): a flat array."""
    stride = stride or size // 2
    r0 = window_starts(shape[0], size, stride)[:, None]
    c0 = window_starts(shape[1], size, stride)[:, None]
    rows, cols = np.asarray(rows)[None, :], np.asarray(cols)[None, :]
    in_rows = ((rows >= r0) & (rows < r0 + size)).astype(np.int64)  # (R, K)
    in_cols = ((cols >= c0) & (cols < c0 + size)).astype(np.int64)  # (C, K)
    return (in_rows @ in_cols.T).ravel()


def clark_evans(rows: np.ndarray, cols: np.ndarray, area: float) -> float | None:
    """Clark-Evans ratio: mean nearest-neighbour distance over its value for a Poisson pattern, 0.5 / sqrt(density).

    < 1: clustered (agglomerates), ~1: random, > 1: regular. None with fewer than 3 points. No edge correction:
    edges lengthen nearest-neighbour distances slightly (the ratio reads a little high)."""
    points = np.column_stack([rows, cols])
    if len(points) < 3:
        return None
    distances, _ = cKDTree(points).query(points, k=2)
    return float(distances[:, 1].mean() / (0.5 / math.sqrt(len(points) / area)))


# --- background and noise ---------------------------------------------------------------------------------


def highpass(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image, np.float64)
    return image - ndi.gaussian_filter(image, HIGHPASS_SIGMA, mode="reflect")


def background_mask(foreground: np.ndarray, margin: int = BACKGROUND_MARGIN) -> np.ndarray:
    """Pixels farther than ``margin`` px from any foreground pixel, and from the image border."""
    far = ndi.distance_transform_edt(~np.asarray(foreground, bool)) > margin
    border = np.zeros_like(far)
    m = int(2 * HIGHPASS_SIGMA)
    border[m:-m, m:-m] = True
    return far & border


def lag1_autocorrelation(residual: np.ndarray, mask: np.ndarray) -> float:
    """Correlation of horizontally and vertically adjacent residual values, both pixels in mask, outliers clipped."""
    mad = _mad(residual[mask])
    r = np.clip(residual - np.median(residual[mask]), -5 * mad, 5 * mad) if mad > 0 else residual
    num, den = 0.0, 0.0
    for a, b, ma, mb in ((r[:, :-1], r[:, 1:], mask[:, :-1], mask[:, 1:]), (r[:-1], r[1:], mask[:-1], mask[1:])):
        both = ma & mb
        num += float((a[both] * b[both]).sum())
        den += 0.5 * float((a[both] ** 2).sum() + (b[both] ** 2).sum())
    return num / den if den > 0 else 0.0


def _mad(values: np.ndarray) -> float:
    values = np.asarray(values, np.float64)
    return float(1.4826 * np.median(np.abs(values - np.median(values)))) if values.size else 0.0


GRAIN_GRID = np.round(np.arange(0.0, 4.01, 0.1), 2)  # px


@lru_cache(maxsize=1)
def _grain_calibration() -> tuple[np.ndarray, np.ndarray]:
    """(lag-1 autocorrelation, residual std / noise std) of Gaussian-blurred white noise through `highpass`,
    per grain in GRAIN_GRID (fixed seed: the same table every run)."""
    rng = np.random.default_rng(0)
    white = rng.standard_normal((384, 384))
    mask = np.zeros(white.shape, bool)
    mask[16:-16, 16:-16] = True
    rho, ratio = [], []
    for grain in GRAIN_GRID:
        noise = ndi.gaussian_filter(white, grain, mode="wrap") if grain > 0 else white
        noise = noise / noise[mask].std()
        residual = highpass(noise)
        rho.append(lag1_autocorrelation(residual, mask))
        ratio.append(_mad(residual[mask]))
    # Below ~0.3 px a sampled Gaussian barely correlates neighbours; keep the table increasing for interpolation.
    return np.maximum.accumulate(np.asarray(rho)), np.asarray(ratio)


@dataclass(frozen=True)
class NoiseEstimate:
    background_grey: float  # median of background pixels, in the image's own polarity, [0, 1]
    noise_sigma: float  # std of the noise, grey levels in [0, 1]
    residual_sigma: float  # robust std (MAD) of the high-pass residual, before the correction
    lag1_autocorrelation: float  # of the residual on background pixels
    grain_px: float  # stddev of the Gaussian that correlates white noise the same way, px (0 = white)
    background_fraction: float  # share of the pixels used as background

    def as_dict(self) -> dict:
        return {k: round(float(v), 6) for k, v in self.__dict__.items()}


def background_noise(
    images: list[np.ndarray], foregrounds: list[np.ndarray], margin: int = BACKGROUND_MARGIN
) -> NoiseEstimate:
    """Background grey level, noise sigma and grain from the background pixels of all images (see module doc)."""
    grey, residual, used, total = [], [], 0, 0
    rhos, weights = [], []
    for image, foreground in zip(images, foregrounds):
        mask = background_mask(foreground, margin)
        total += mask.size
        if mask.sum() < 100:
            continue
        used += int(mask.sum())
        grey.append(np.asarray(image)[mask])
        r = highpass(image)
        residual.append(r[mask] - np.median(r[mask]))
        rhos.append(lag1_autocorrelation(r, mask))
        weights.append(float(mask.sum()))
    if not grey and margin > 1:  # particles cover nearly everything: take the background closer to them
        return background_noise(images, foregrounds, margin=1)
    if not grey:
        raise DataError(
            "profile: no image has background pixels (at least 100 farther than "
            f"{BACKGROUND_MARGIN} px from every particle): cannot measure the background and noise"
        )
    rho = float(np.average(rhos, weights=weights))
    table_rho, table_ratio = _grain_calibration()
    # The autocorrelation grows with the grain; interpolate the grain (clamped to the table's range).
    grain = float(np.interp(rho, table_rho, GRAIN_GRID))
    ratio = float(np.interp(grain, GRAIN_GRID, table_ratio))
    residual_sigma = _mad(np.concatenate(residual))
    return NoiseEstimate(
        float(np.median(np.concatenate(grey))), residual_sigma / ratio, residual_sigma, rho, grain, used / total
    )


# --- the mean particle edge -------------------------------------------------------------------------------
# Signed distance s to a particle's segmented edge (px; < 0 inside): the profile covers EDGE_INSIDE_PX inside to
# EDGE_OUTSIDE_PX outside in 1 px bins. Each particle's own background (mean grey EDGE_OUTSIDE_PX to
# EDGE_BACKGROUND_PX outside) is 0 and its interior (mean grey EDGE_INTERIOR_PX to EDGE_INSIDE_PX inside) sets
# the contrast: the profile is 1 inside a particle and 0 on its background, whatever the shading of the image.
EDGE_INSIDE_PX, EDGE_OUTSIDE_PX, EDGE_BACKGROUND_PX, EDGE_INTERIOR_PX = 6, 12, 16, 3
EDGE_BINS = np.arange(-EDGE_INSIDE_PX, EDGE_OUTSIDE_PX + 1, dtype=np.float64)  # bin edges, px
MIN_EDGE_PARTICLES = 10  # fewer isolated particles: no edge profile
MIN_BIN_PARTICLES = 3  # a bin with fewer particles is not used
# Grey within SATURATED of 0 or 1 is clipped (a saturated detector, or a fringe pushing black particles below 0):
# a bin with more than MAX_SATURATED of its pixels there is not used (the fit models unclipped grey).
SATURATED, MAX_SATURATED = 0.002, 0.02
# The fringe rule. A ring of the opposite grey to the particles (bright around dark ones: underfocus) is an
# overshoot: the profile's lowest bin within RING_RANGE_PX outside the edge lies below the background (0) by at
# least FRINGE_SIGNIFICANCE of its standard errors and MIN_FRINGE_CONTRAST of the particle contrast. A blurred
# edge never overshoots, however wide the blur. A ring like the particles (dark around dark ones: overfocus) is a
# bump: going outwards, the profile rises again, above the background and above its lowest value before, by as
# many standard errors (of the difference) and as much contrast; a ring like the particles but without a bump is
# a blurred edge as far as the profile can tell, and counts as none.
FRINGE_SIGNIFICANCE, MIN_FRINGE_CONTRAST, RING_RANGE_PX = 3.0, 0.03, 8.0
MIN_FRINGE_WIDTH_PX = 0.5  # the fitted width's lower limit: a ring narrower than that is a ring as wide as the blur


def signed_distance(mask: np.ndarray) -> np.ndarray:
    """Signed distance (px) of every pixel centre to the boundary of ``mask``: > 0 outside, < 0 inside, +-0.5 for
    the pixels on either side of the boundary."""
    mask = np.asarray(mask, bool)
    return np.where(mask, 0.5 - ndi.distance_transform_edt(mask), ndi.distance_transform_edt(~mask) - 0.5)


@dataclass(frozen=True)
class EdgeSamples:
    """The edges of one image's isolated particles: per particle (rows) and distance bin (columns, EDGE_BINS), the
    sum and count of grey minus the particle's background, the sum of distances and the saturated pixels; per
    particle its contrast (interior minus background grey) and equivalent radius."""

    sums: np.ndarray
    counts: np.ndarray
    distance_sums: np.ndarray
    saturated: np.ndarray  # pixels within SATURATED of 0 or 1
    contrast: np.ndarray
    radius: np.ndarray

    @staticmethod
    def empty() -> EdgeSamples:
        n = len(EDGE_BINS) - 1
        return EdgeSamples(*(np.zeros((0, n)) for _ in range(4)), np.zeros(0), np.zeros(0))


def edge_samples(
    image: np.ndarray, labels: np.ndarray, foreground: np.ndarray, exclude: np.ndarray | None = None
) -> EdgeSamples:
    """The edge profiles of the particles of ``labels`` (`segment_image`) that touch neither the image border nor
    another foreground or ``exclude`` pixel (annotations, which may hide particles; 8-neighbourhood), each over its
    own pixels and the pixels outside it that are farther than EDGE_OUTSIDE_PX from any other foreground or
    excluded pixel (there every other particle's edge has faded)."""
    image = np.asarray(image, np.float64)
    labels = np.asarray(labels)
    others = np.asarray(foreground, bool) | (np.asarray(exclude, bool) if exclude is not None else False)
    h, w = labels.shape
    margin = EDGE_BACKGROUND_PX + EDGE_OUTSIDE_PX + 2
    n_bins = len(EDGE_BINS) - 1
    rows = {key: [] for key in ("sums", "counts", "distance_sums", "saturated", "contrast", "radius")}
    for index, box in enumerate(ndi.find_objects(labels)):
        if box is None:
            continue
        (r0, r1), (c0, c1) = ((b.start, b.stop) for b in box)
        if r0 == 0 or c0 == 0 or r1 == h or c1 == w:
            continue
        crop = (slice(max(0, r0 - margin), min(h, r1 + margin)), slice(max(0, c0 - margin), min(w, c1 + margin)))
        mask = labels[crop] == index + 1
        other = others[crop] & ~mask
        if (ndi.binary_dilation(mask, np.ones((3, 3), bool)) & other).any():
            continue
        s = signed_distance(mask)
        clear = ndi.distance_transform_edt(~other) > EDGE_OUTSIDE_PX if other.any() else np.ones_like(mask)
        grey = image[crop]
        ring = clear & (s >= EDGE_OUTSIDE_PX) & (s < EDGE_BACKGROUND_PX)
        interior = mask & (s <= -EDGE_INTERIOR_PX) & (s >= -EDGE_INSIDE_PX)
        if ring.sum() < 20 or interior.sum() < 5:
            continue
        background = float(grey[ring].mean())
        used = (mask | clear) & (s >= EDGE_BINS[0]) & (s < EDGE_BINS[-1])
        bins = (np.floor(s[used]) - EDGE_BINS[0]).astype(np.int64)
        clipped = (grey[used] <= SATURATED) | (grey[used] >= 1.0 - SATURATED)
        rows["sums"].append(np.bincount(bins, grey[used] - background, n_bins))
        rows["counts"].append(np.bincount(bins, None, n_bins))
        rows["distance_sums"].append(np.bincount(bins, s[used], n_bins))
        rows["saturated"].append(np.bincount(bins, clipped, n_bins))
        rows["contrast"].append(float(grey[interior].mean()) - background)
        rows["radius"].append(math.sqrt(mask.sum() / math.pi))
    if not rows["contrast"]:
        return EdgeSamples.empty()
    return EdgeSamples(*(np.asarray(rows[k], np.float64) for k in rows))


@dataclass(frozen=True)
class Ring:
    """What the profile itself shows beyond the edge (`find_ring`): ``kind`` "opposite" (an overshoot beyond the
    background: a ring of the opposite grey to the particles), "like" (a bump: a ring like the particles) or
    "none"; its ``height`` (particle contrast; > 0 for opposite rings, < 0 for like ones: the sign of the scene's
    fringe amplitude), standard error and distance from the segmented edge (px)."""

    kind: str
    height: float
    height_se: float
    distance_px: float

    def as_dict(self) -> dict:
        return {k: (v if isinstance(v, str) else round(float(v), 5)) for k, v in self.__dict__.items()}


def _vertex(s: np.ndarray, p: np.ndarray, k: int) -> tuple[float, float]:
    """(distance, value) of the extremum at bin k, refined by the Gaussian through it and its neighbours (a
    parabola through the logarithms: the bins are 1 px wide and a ring's peak rarely sits on a bin's mean
    distance; the three bins centred on k, else on a neighbour when a bin beside k lies on the other side of 0, as
    beside the edge), its vertex within a bin of k's; bin k itself when none fits."""
    sign = np.sign(p[k])
    for centre in (k, k + 1, k - 1):
        if not 0 < centre < len(s) - 1:
            continue
        y = p[centre - 1 : centre + 2] * sign
        if not (y > 0).all():
            continue
        a, b, c = np.polyfit(s[centre - 1 : centre + 2], np.log(y), 2)
        x = -b / (2 * a) if a < 0 else np.nan
        if s[max(k - 1, 0)] <= x <= s[min(k + 1, len(s) - 1)]:
            return float(x), float(sign * np.exp(c - b * b / (4 * a)))
    return float(s[k]), float(p[k])


def find_ring(distance: np.ndarray, profile: np.ndarray, se: np.ndarray) -> Ring:
    """The rule at FRINGE_SIGNIFICANCE on the usable bins (``distance`` ascending): an overshoot first, else a bump.
    The height and distance are the parabola's through the extreme bin and its neighbours, the error the bin's."""
    outside = (distance > 0) & (distance <= RING_RANGE_PX)
    s, p, e = distance[outside], profile[outside], se[outside]
    if len(s) == 0:
        return Ring("none", 0.0, float("nan"), float("nan"))
    k = int(np.argmin(p))
    if -p[k] >= max(FRINGE_SIGNIFICANCE * e[k], MIN_FRINGE_CONTRAST):
        at, value = _vertex(s, p, k)
        return Ring("opposite", -value, float(e[k]), at)
    best = None
    for j in range(1, len(s)):
        i = int(np.argmin(p[:j]))
        rise, rise_se = p[j] - p[i], math.hypot(e[i], e[j])
        bump = rise >= max(FRINGE_SIGNIFICANCE * rise_se, MIN_FRINGE_CONTRAST)
        if bump and p[j] >= max(FRINGE_SIGNIFICANCE * e[j], MIN_FRINGE_CONTRAST) and (best is None or p[j] > p[best]):
            best = j
    if best is not None:
        at, value = _vertex(s, p, best)
        return Ring("like", -value, float(e[best]), at)
    return Ring("none", float(-p[k]), float(e[k]), float(s[k]))


@dataclass(frozen=True)
class FringeFit:
    """The transmission scene's edge and fringe (`edge_model`) fitted to the edge profile (`fit_fringe`): the
    scene's fringe amplitude (particle contrast at the edge; > 0 a ring of the opposite grey just outside) and
    width w (px, the rings' Gaussian stddev before the instrument's blur), the edge's blur (the instrument's and
    the segmentation's), the ring's height in the images (after that blur) and distance from the segmented edge,
    and the reduced chi^2."""

    amplitude: float
    width_px: float
    edge_blur_px: float
    edge_offset_px: float
    contrast_scale: float
    interior_slope: float
    visible_height: float  # amplitude x scale x w^2 / (w^2 + blur^2): a straight edge's ring, particle contrast
    ring_distance_px: float  # offset + sqrt(w^2 + blur^2)
    reduced_chi2: float

    def as_dict(self) -> dict:
        return {k: round(float(v), 5) for k, v in self.__dict__.items()}


@dataclass(frozen=True)
class EdgeProfile:
    """The mean particle edge: per distance bin its mean distance (px, < 0 inside), the profile (0 background, 1
    interior) and its standard error (over particles), the particles per bin and the share of saturated pixels;
    the particles used, their mean contrast (grey, signed) and median radius; the ring the profile shows
    (`find_ring`) and, when there is one, the scene's fringe fitted to the profile (None when the fit failed)."""

    distance_px: np.ndarray
    profile: np.ndarray
    standard_error: np.ndarray
    particles_per_bin: np.ndarray
    saturated_share: np.ndarray
    particles: int
    contrast: float
    radius_px: float
    ring: Ring
    fringe: FringeFit | None

    @property
    def fringe_detected(self) -> bool:
        return self.ring.kind != "none"

    @property
    def usable(self) -> np.ndarray:
        """The bins the rule and the fit use: enough particles, few saturated pixels."""
        return (
            (self.particles_per_bin >= MIN_BIN_PARTICLES)
            & (self.saturated_share <= MAX_SATURATED)
            & np.isfinite(self.standard_error)
        )

    def as_dict(self) -> dict:
        def values(array):
            return [None if not np.isfinite(v) else round(float(v), 5) for v in array]

        return {
            "distance_px": values(self.distance_px),
            "profile": values(self.profile),
            "standard_error": values(self.standard_error),
            "particles_per_bin": [int(v) for v in self.particles_per_bin],
            "saturated_share": values(self.saturated_share),
            "particles": self.particles,
            "contrast": round(self.contrast, 5),
            "radius_px": round(self.radius_px, 3),
            "ring": self.ring.as_dict(),
            "fringe": self.fringe.as_dict() if self.fringe is not None else None,
            "rule": f"a ring within {RING_RANGE_PX:g} px outside the edge, >= {FRINGE_SIGNIFICANCE:g} standard errors "
            f"and >= {MIN_FRINGE_CONTRAST:g} of the particle contrast: an overshoot beyond the background (opposite "
            "grey), or a rise back above it (like the particles)",
        }


def edge_profile(samples: list[EdgeSamples]) -> EdgeProfile | None:
    """The mean edge profile of all images' isolated particles, the ring it shows and the fringe fitted to it;
    None with fewer than MIN_EDGE_PARTICLES particles. Each particle weighs the same: per bin the profile is the
    particles' mean grey minus background over their mean contrast, its error their spread over sqrt(particles)."""
    sums = np.concatenate([x.sums for x in samples]) if samples else np.zeros((0, len(EDGE_BINS) - 1))
    if len(sums) < MIN_EDGE_PARTICLES:
        return None
    counts = np.concatenate([x.counts for x in samples])
    pixels = np.maximum(counts.sum(0), 1)
    distance = np.concatenate([x.distance_sums for x in samples]).sum(0) / pixels
    saturated = np.concatenate([x.saturated for x in samples]).sum(0) / pixels
    contrast = float(np.concatenate([x.contrast for x in samples]).mean())
    radius = float(np.median(np.concatenate([x.radius for x in samples])))
    seen = counts > 0
    per_particle = np.where(seen, sums / np.maximum(counts, 1), 0.0)
    n = seen.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        grey = per_particle.sum(0) / n
        variance = np.where(seen, (per_particle - grey) ** 2, 0.0).sum(0) / (n - 1)
        mean = grey / contrast
        se = np.sqrt(variance / n) / abs(contrast)
    mean[n == 0], se[n < 2] = np.nan, np.nan
    edge = EdgeProfile(distance, mean, se, n, saturated, len(sums), contrast, radius, Ring("none", 0, 0, 0), None)
    use = edge.usable
    ring = find_ring(distance[use], mean[use], se[use])
    fit = None
    if ring.kind != "none":
        fit = fit_fringe(distance[use], mean[use], se[use], radius, 1.0 if ring.kind == "opposite" else -1.0)
    return dataclasses.replace(edge, ring=ring, fringe=fit)


_PHI_1 = math.exp(-0.5) / math.sqrt(2 * math.pi)  # the standard normal density at 1


def edge_model(s, scale, slope, offset, blur, amplitude, width, radius: float = np.inf) -> np.ndarray:
    """The transmission scene's mean edge seen at signed distance ``s`` (px): a step of height ``scale`` (with a
    linear ``slope`` inside: particles thicken inwards) at ``offset`` blurred by a Gaussian of stddev ``blur``,
    minus ``amplitude`` x scale x the scene's fringe term (`drgan.scene.transmission.edge_fringe`: w^2 / phi(1) x
    Laplacian of the step blurred by w, here also by ``blur``) of a disc of ``radius``, in polar coordinates:
    f'' + f' / r, with f'' = u phi(u / t) / t^3, f' = -phi(u / t) / t at u = s - offset, t^2 = w^2 + blur^2."""
    from scipy.special import erfc

    u = np.asarray(s, np.float64) - offset
    t = math.sqrt(width * width + blur * blur)
    density = np.exp(-0.5 * (u / t) ** 2) / math.sqrt(2 * math.pi)
    r = np.maximum(radius + u, 0.5 * radius) if np.isfinite(radius) else np.inf
    laplacian = u * density / t**3 - density / (t * r)
    step = (scale + slope * np.minimum(u, 0.0)) * 0.5 * erfc(u / (math.sqrt(2) * blur))
    return step - amplitude * scale * (width * width / _PHI_1) * laplacian


# Weak priors of the fit (pseudo-observations): the step's height is the measured interior's (1) within
# SCALE_PRIOR, its inward slope 0 within SLOPE_PRIOR per px. Where the bins inside the edge are there, they
# outweigh these; where saturation took them out, the priors keep the fit from trading the step's height for the
# fringe's amplitude.
SCALE_PRIOR, SLOPE_PRIOR = 0.25, 0.1


def fit_fringe(distance, profile, se, radius: float, sign: float) -> FringeFit | None:
    """Least squares of `edge_model` with an amplitude of ``sign`` on the given bins (weights 1 / se^2, and the
    priors above), from a few starting widths; None with fewer than 8 bins or no converged fit."""
    from scipy.optimize import least_squares

    s, p = np.asarray(distance, np.float64), np.asarray(profile, np.float64)
    if len(s) < 8:
        return None
    sigma = np.maximum(np.asarray(se, np.float64), 1e-4)

    def model(x, scale, slope, offset, blur, amplitude, width):
        return edge_model(x, scale, slope, offset, blur, sign * amplitude, width, radius)

    def residuals(theta):
        priors = [(theta[0] - 1.0) / SCALE_PRIOR, theta[1] / SLOPE_PRIOR]
        return np.concatenate([(model(s, *theta) - p) / sigma, priors])

    bounds = ([0.2, -1.0, -3.0, 0.3, 0.0, MIN_FRINGE_WIDTH_PX], [3.0, 1.0, 3.0, 6.0, 3.0, 8.0])
    best = None
    for width in (0.7, 1.5, 3.0):
        fit = least_squares(residuals, [1.0, 0.0, 0.0, 1.0, 0.2, width], bounds=bounds, max_nfev=2000)
        if fit.success and (best is None or fit.cost < best.cost):
            best = fit
    if best is None:
        return None
    scale, slope, offset, blur, amplitude, width = (float(v) for v in best.x)
    chi2 = float((((model(s, *best.x) - p) / sigma) ** 2).sum())
    t2 = width * width + blur * blur
    return FringeFit(
        sign * amplitude, width, blur, offset, scale, slope, sign * amplitude * scale * width * width / t2,
        offset + math.sqrt(t2), chi2 / max(1, len(s) - 6),
    )  # fmt: skip


# --- size distribution ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SizeFit:
    kind: str  # normal | lognormal | bimodal
    params: dict  # normal: mean, std; lognormal: median, sigma; bimodal: weight1, median1, sigma1, median2, sigma2
    log_likelihood: float
    n_params: int
    bic: float

    def pdf(self, d: np.ndarray) -> np.ndarray:
        d = np.asarray(d, np.float64)
        p = self.params
        if self.kind == "normal":
            return _normal_pdf(d, p["mean"], p["std"])
        with np.errstate(divide="ignore", invalid="ignore"):
            logd = np.log(np.where(d > 0, d, np.nan))
            if self.kind == "lognormal":
                out = _normal_pdf(logd, math.log(p["median"]), p["sigma"]) / d
            else:
                out = (
                    p["weight1"] * _normal_pdf(logd, math.log(p["median1"]), p["sigma1"])
                    + (1 - p["weight1"]) * _normal_pdf(logd, math.log(p["median2"]), p["sigma2"])
                ) / d
        return np.nan_to_num(out)

    def as_dict(self) -> dict:
        return {
            "kind": self.kind,
            "params": {k: round(float(v), 5) for k, v in self.params.items()},
            "log_likelihood": round(self.log_likelihood, 3),
            "n_params": self.n_params,
            "bic": round(self.bic, 3),
        }


def _normal_pdf(x, mean, std):
    return np.exp(-0.5 * ((x - mean) / std) ** 2) / (std * math.sqrt(2 * math.pi))


MIN_SPREAD = 0.05  # least relative spread of a fit (std / mean, sigma of log d)
MIN_MIXTURE = 20  # fewer diameters than this: no two-component fit


def fit_sizes(diameters: np.ndarray, seed: int = 0) -> tuple[list[SizeFit], SizeFit]:
    """Fit normal, lognormal and (from MIN_MIXTURE diameters) a two-lognormal mixture to the diameters (px) by
    maximum likelihood; pick the lowest BIC = k ln(n) - 2 ln(L), all likelihoods in diameter space (so they
    compare)."""
    d = np.asarray(diameters, np.float64)
    d = d[np.isfinite(d) & (d > 0)]
    if d.size == 0:
        raise DataError("profile: no particle diameter measured: nothing to fit a size distribution to")
    n, logd = d.size, np.log(d)

    def make(kind, params, loglik, k):
        return SizeFit(kind, params, float(loglik), k, float(k * math.log(n) - 2 * loglik))

    # A few particles (one image of a user's) may all measure alike: spreads below MIN_SPREAD are kept at it.
    mean = float(d.mean())
    std = max(float(d.std()), MIN_SPREAD * mean)
    normal = make("normal", {"mean": mean, "std": std}, np.log(_normal_pdf(d, mean, std)).sum(), 2)
    mu, sigma = float(logd.mean()), max(float(logd.std()), MIN_SPREAD)
    lognormal = make(
        "lognormal", {"median": math.exp(mu), "sigma": sigma}, (np.log(_normal_pdf(logd, mu, sigma)) - logd).sum(), 2
    )
    fits = [normal, lognormal] + ([_fit_mixture(logd, seed, make)] if n >= MIN_MIXTURE else [])
    return fits, min(fits, key=lambda f: f.bic)


def _fit_mixture(logd: np.ndarray, seed: int, make) -> SizeFit:
    from sklearn.mixture import GaussianMixture

    gm = GaussianMixture(2, covariance_type="full", n_init=5, random_state=seed, reg_covar=1e-6).fit(logd[:, None])
    order = np.argsort(gm.means_.ravel())
    w = gm.weights_[order]
    m = gm.means_.ravel()[order]
    s = np.sqrt(gm.covariances_.ravel()[order])
    loglik = float(gm.score(logd[:, None]) * logd.size - logd.sum())
    return make(
        "bimodal",
        {
            "weight1": float(w[0]),
            "median1": float(math.exp(m[0])),
            "sigma1": float(s[0]),
            "median2": float(math.exp(m[1])),
            "sigma2": float(s[1]),
        },
        loglik,
        5,
    )


def lognormal_to_normal(median: float, sigma: float) -> tuple[float, float]:
    """Mean and std of a lognormal given its median and log-sigma (the size group's bimodal is a normal mixture)."""
    mean = median * math.exp(sigma**2 / 2)
    return mean, mean * math.sqrt(math.exp(sigma**2) - 1)


# --- shape, placement, pixel size -------------------------------------------------------------------------


def mesh_kind(axis_ratio: float) -> str:
    """sphere below 1.3, rod above 2.5 (wires, needles), potato between (rounded, irregular)."""
    if axis_ratio < 1.3:
        return "sphere"
    return "rod" if axis_ratio > 2.5 else "potato"


def placement_kind(touching_fraction: float, clark_evans_ratio: float | None) -> str:
    """poisson (3-D agglomerates) when particles cluster: over 30 % touch another, or Clark-Evans < 0.9."""
    clustered = touching_fraction > 0.3 or (clark_evans_ratio is not None and clark_evans_ratio < 0.9)
    return "poisson" if clustered else "random_2d"


_INCH_NM, _CM_NM = 2.54e7, 1e7


def pixel_size_nm(path: str | Path) -> tuple[float | None, str]:
    """(pixel size in nm or None, where it came from) from a TIFF's Zeiss CZ_SEM tag or resolution tags."""
    path = Path(path)
    if path.suffix.lower() not in (".tif", ".tiff"):
        return None, "unknown (not a TIFF)"
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            tags = tif.pages[0].tags
            cz = tags.get(34118)
            if cz is not None and isinstance(cz.value, dict) and "ap_image_pixel_size" in cz.value:
                _, value, unit = cz.value["ap_image_pixel_size"]
                factor = {"pm": 1e-3, "nm": 1.0, "µm": 1e3, "um": 1e3, "mm": 1e6}.get(unit)
                if factor and float(value) > 0:
                    return float(value) * factor, "CZ_SEM ap_image_pixel_size"
            res, unit = tags.get(282), tags.get(296)
            if res is not None and unit is not None and int(unit.value) in (2, 3):
                num, den = res.value
                per_unit = num / den if den else 0.0
                # 72/96/150/300 per inch are display or print resolutions, not the microscope's pixel.
                if per_unit > 0 and not (int(unit.value) == 2 and per_unit in (72, 96, 150, 300)):
                    return (_INCH_NM if int(unit.value) == 2 else _CM_NM) / per_unit, "XResolution/ResolutionUnit"
    except Exception as exc:  # metadata is optional: an unreadable tag must not stop the profile
        return None, f"unknown ({type(exc).__name__} reading TIFF tags)"
    return None, "unknown"
