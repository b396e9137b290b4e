"""The mean particle edge of unannotated images, and whether it shows a defocus fringe (`python -m drgan.profile`).

`edge_samples` / `edge_profile`: the mean particle edge, grey against signed distance to the segmented edge
(isolated particles only, segmented by drgan.data.measurements.segment_image), in units of the particle contrast,
and whether it shows a ring (`find_ring`); `fit_fringe`: the transmission scene's fringe term fitted to it
(`edge_model`). Grey images in [0, 1], as drgan.data.images.read_grey gives them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

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


def crossing(distance: np.ndarray, profile: np.ndarray, level: float) -> float:
    """The signed distance (px) where ``profile`` (1 inside, falling outwards) first falls below ``level``, linearly
    interpolated between bins; nan when it never does."""
    distance, profile = np.asarray(distance, float), np.asarray(profile, float)
    ok = np.isfinite(distance) & np.isfinite(profile)
    d, p = distance[ok], profile[ok]
    for k in range(1, len(p)):
        if p[k - 1] >= level > p[k]:
            return float(d[k - 1] + (p[k - 1] - level) / (p[k - 1] - p[k]) * (d[k] - d[k - 1]))
    return math.nan


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
    def ramp_bins(self) -> tuple[np.ndarray, np.ndarray]:
        """(distance, profile) of the bins seen on enough particles, saturated ones too: a clipped background or
        rim still places the ramp, which the fringe fit cannot use."""
        use = (self.particles_per_bin >= MIN_BIN_PARTICLES) & np.isfinite(self.profile)
        return self.distance_px[use], self.profile[use]

    @property
    def half_contrast_px(self) -> float:
        """Where the mean edge crosses half contrast, px from the segmented edge (> 0 outside; nan when it never
        does): static image analysis puts a particle's boundary there (ISO 13322-1), and so do drgan's rendered
        masks and the annotations measured (experiments/statistics)."""
        return crossing(*self.ramp_bins, 0.5)

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


# A half-contrast crossing farther than this from the segmented edge is not taken for the outline (a profile that
# wide is a fringe or a halo, not a ramp): sizes then stay at the segmented outline.
MAX_OUTLINE_SHIFT_PX = 3.0


def outline_shift(edge: EdgeProfile | None) -> float:
    """px the segmented outlines move to reach half contrast (``edge.half_contrast_px``; < 0: inwards); 0 without
    an edge profile, a crossing, or beyond MAX_OUTLINE_SHIFT_PX."""
    half = edge.half_contrast_px if edge is not None else math.nan
    return float(half) if math.isfinite(half) and abs(half) <= MAX_OUTLINE_SHIFT_PX else 0.0


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
