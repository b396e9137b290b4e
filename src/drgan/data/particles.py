"""Finding particles in an unannotated image, whatever their size: drgan's one classical segmentation.

Profiling, patch mining, background selection and the FID brightness guards all ask the same question (which pixels
are particles, and which particle is which), so they all call this module. Nothing here is tuned to one data set:
every length follows from the particles' own scale, measured first.

1. **Grey**: 8/16-bit, float and RGB(A) arrays become one grey channel in [0, 1]; dark particles are turned bright
   (``1 - grey``), so everything below looks for bright particles.
2. **Annotations** (`annotation_mask`): scale bars, their text, panel letters and label boxes are drawn in pure black
   or white (a bar softened by resampling: nearly, and solid and straight); they are found by shape (long thin solid
   bars, solid boxes, character-sized thin strokes near an edge) and filled from their surroundings, so that they
   are neither particles nor background.
3. **Scale** (`estimate_scale`): the scale-normalised Laplacian of Gaussian, ``-s^2 LoG_s``, peaks at
   ``s = d / (2 sqrt 2)`` on a disc of diameter ``d`` whatever its contrast (Lindeberg's scale selection). Its
   maxima over position and scale, from 3 px to half the image, are the image's blobs; the strong ones (well above
   the response's noise at their scale) vote, weighted by their response, for the particle diameter. Grain and noise
   respond at small scales only weakly and are outvoted; an agglomerate still shows its particles' seams (the
   report's reference). `search_scale` segments the images at every scale of a quarter-octave grid, finds every
   scale whose segments have that median size (a fixed point), and keeps the one whose size holds over the most
   scales, less its segments' spread in size (particles persist and are alike; specks follow the smoothing).
   Where no scale agrees with its segments, a size they keep over an octave of smoothing is the particles'
   (`_plateau`: small particles on a noisy film).
4. **Settings from the scale** (`SegmentParams.resolved`): smoothing, seed distance and plausible areas are fixed
   fractions of the diameter (calibrated where the TiO2 sets meet their masks: sigma 1.5 px and seeds 6 px apart
   at 26 px); the uneven illumination is removed at 3 diameters (a grey opening: larger than any particle, so none
   is flattened away); a value set by the user is kept exactly.
5. **Foreground and watershed**: Otsu's threshold of the smoothed, flattened image over the pixels within one
   diameter of the blobs of that size (`blob_centres`; on a grainy film with a few particles, taken again around the
   blobs that stand out of the film's noise), refused when it does not separate two classes (separability below
   ``min_separability``); pieces that reach no blob centre within half a diameter are grain or texture specks; the
   distance transform's maxima, at least ``min_distance`` apart, seed a watershed that splits touching particles.
6. **Outlines at the edges** (`grow_to_edges`): where the particles' strongest edges lie below Otsu's threshold (a
   sphere's contrast falls off towards its outline), each segment grows out to them, none merging.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import NamedTuple

import numpy as np
from scipy import ndimage as ndi
from skimage.feature import peak_local_max
from skimage.filters import threshold_otsu
from skimage.morphology import h_maxima
from skimage.segmentation import watershed
from tqdm import tqdm

from drgan.data.annotations import ANNOTATION_LEVEL, EDGE_BAND, annotation_mask, as_grey  # noqa: F401 (re-exported)
from drgan.data.polarity import to_bright
from drgan.errors import ConfigError, DataError

# --- settings ---------------------------------------------------------------------------------------------

# Fractions of the particle diameter d (px). sigma reproduces the calibration on the TiO2 train images (sigma 1.5 for
# particles of ~26 px); min_distance was 6 / 26 there too, and is 0.17 since the TiO2 SEM film's black specks are no
# longer taken for text (the scale settles at ~30 px, where 0.23 d left -25 % particles per patch against the masks,
# 0.17 d -19 %; experiments/profile/README.md).
SIGMA_PER_DIAMETER = 1.5 / 26
MIN_DISTANCE_PER_DIAMETER = 0.17
MIN_AREA_DIAMETER = 0.27  # a segment narrower than 0.27 d is a speck or a watershed sliver
MAX_AREA_DIAMETER = 4.0  # one wider than 4 d is an agglomerate the watershed could not split
BACKGROUND_PER_DIAMETER = 3.0  # the illumination is flattened at this many diameters
# `SegmentParams.neck_depth` left None: 0 or NECK_DEPTH, searched with the scale (`search_scale`); NECK_DEPTH only
# where it narrows the spread of the segments' sizes, log(q90 / q10), to NECK_SPREAD of the plain seeds' near the
# same scale (within NECK_NEAR in log scale) or less (`_plain_unless_more_alike`).
NECK_DEPTH = 0.2
NECK_SPREAD = 0.8
NECK_NEAR = 0.35
# Otsu's separability (between-class / total variance) below which a threshold separates no two classes (a Gaussian's
# 2 / pi = 0.64). Left at this default, the scale search may lower it for a dense packing (`search_scale`).
MIN_SEPARABILITY = 0.66


@dataclass(frozen=True)
class SegmentParams:
    """Classical particle segmentation; lengths in pixels, areas in square pixels.

    Every length left None follows from the particle diameter ``scale`` (itself estimated from the image when
    None): see `resolved`. A value given is used exactly as given.
    """

    scale: float | None = None  # particle diameter, px; None: estimated (`estimate_scale`)
    sigma: float | None = None  # Gaussian smoothing before thresholding, px; None: 0.058 scale
    min_distance: int | None = None  # least distance between watershed seeds, px; None: 0.17 scale
    min_area: int | None = None  # smaller segments are noise, specks or slivers, px^2; None: disc of 0.27 scale
    max_area: int | None = None  # larger segments are unsplit agglomerates, px^2; None: disc of 4 scale
    background: float | None = None  # illumination flattened at this size, px (0: not); None: 3 scale
    annotations: bool = True  # find scale bars, text and panel letters, and leave them out
    # A watershed seed must stand this many px above the saddle to its neighbour in the foreground's distance
    # transform (h-maxima). Thin foreground (film wrinkles and lines, grain strands, rims) has a maximum every
    # min_distance along its length, each < 1 px deep, and breaks into particle-sized "segments" that pull the
    # measured scale down; 1 px fixes that (EMPS 2c6c108b4d: 6.9 -> 13.7 px, instances 15.1 px) but also merges
    # touching TiO2 particles, whose necks are as shallow (tio2_sem patch count -17 % -> -34 %), so it is off by
    # default: a key to set for images with strands (experiments/profile/README.md). 0: every maximum seeds.
    seed_depth: float = 0.0
    # A watershed seed must stand this share of its own height above the saddle to a higher peak of the distance
    # transform (its neck; `_neck_caps`): most touching particles meet at deep necks (EMPS instance maps: 95 % of
    # touching pairs at >= 0.22 of the lower particle's radius, median 0.74), while a rod's ridge and an irregular
    # particle's bumps rise a few % above theirs (median 0.03, 90 % <= 0.12), so 0.2 keeps rods and irregular
    # particles whole. But agglomerated TiO2 particles are split by their annotators at necks as shallow (tio2_sem
    # masks: half of the touching pairs below 0.13), and 0.2 merges them (experiments/profile/README.md). 0: every
    # maximum min_distance apart seeds. None (the default): 0 or NECK_DEPTH, searched with the scale: the one whose
    # segments persist over more scales and are more alike in size (`search_scale`).
    neck_depth: float | None = None
    # Segments grow out to the particles' strongest edges where those lie below Otsu's threshold (`grow_to_edges`);
    # False: Otsu's outlines.
    grow_outlines: bool = True
    # Otsu's between-class / total variance around the blobs of the particles' size. Smoothed noise scores
    # 0.635-0.64 (2/pi for Gaussian noise) at any scale; particles at their own scale 0.66-0.91 (EMPS, most > 0.7).
    min_separability: float = MIN_SEPARABILITY

    def __post_init__(self) -> None:
        for key in ("scale", "sigma", "background"):
            value = getattr(self, key)
            if value is not None and not (isinstance(value, (int, float)) and value >= 0 and math.isfinite(value)):
                raise ConfigError(f"data.segment.{key}={value!r}: expected a number >= 0 (px) or null (from the scale)")
        if self.scale is not None and self.scale <= 0:
            raise ConfigError(f"data.segment.scale={self.scale}: expected a particle diameter > 0 px or null")
        if self.min_distance is not None and self.min_distance < 1:
            raise ConfigError(f"data.segment.min_distance={self.min_distance}: expected >= 1 px or null")
        low, high = self.min_area, self.max_area
        if (low is not None and low <= 0) or (low is not None and high is not None and low > high):
            raise ConfigError(
                f"data.segment min_area={low}, max_area={high}: expected 0 < min_area <= max_area (px^2) or null"
            )
        if self.neck_depth is not None and not (isinstance(self.neck_depth, (int, float)) and 0 <= self.neck_depth < 1):
            raise ConfigError(
                f"data.segment.neck_depth={self.neck_depth!r}: expected a share of a seed's height in [0, 1), or null"
                " (chosen from the images)"
            )
        if not (isinstance(self.seed_depth, (int, float)) and 0 <= self.seed_depth < math.inf):
            raise ConfigError(f"data.segment.seed_depth={self.seed_depth!r}: expected a depth >= 0 px")
        if not isinstance(self.grow_outlines, bool):
            raise ConfigError(f"data.segment.grow_outlines={self.grow_outlines!r}: expected true or false")
        if not 0 <= self.min_separability < 1:
            raise ConfigError(f"data.segment.min_separability={self.min_separability}: expected in [0, 1)")

    @classmethod
    def from_config(cls, segment) -> SegmentParams:
        """From a ``data.segment`` mapping (None or {} = everything from the image); unknown keys are named."""
        if isinstance(segment, SegmentParams):
            return segment
        values = dict(segment or {})
        unknown = sorted(set(values) - set(cls.__dataclass_fields__))
        if unknown:
            raise ConfigError(
                f"data.segment: unknown key(s) {unknown}; expected some of {', '.join(cls.__dataclass_fields__)}"
            )
        return cls(**values)

    @property
    def is_resolved(self) -> bool:
        lengths = (self.scale, self.sigma, self.min_distance, self.min_area, self.max_area, self.background)
        return None not in (*lengths, self.neck_depth)

    def resolved(self, scale: float | None = None) -> SegmentParams:
        """Every length set: those given kept, the others from ``scale`` (or self.scale), the particle diameter. A
        neck depth left None becomes 0 here (every maximum seeds): `resolve_params` chooses it from images."""
        d = float(self.scale if self.scale is not None else scale) if (self.scale or scale) else None
        if d is None:
            raise ConfigError("SegmentParams.resolved: no particle scale (give data.segment.scale or an image)")
        d = round(d, 2)  # the lengths follow from the scale as recorded: set by hand, it resolves to the same
        min_area = self.min_area or max(4, int(round(math.pi / 4 * (MIN_AREA_DIAMETER * d) ** 2)))
        max_area = self.max_area or max(min_area, int(round(math.pi / 4 * (MAX_AREA_DIAMETER * d) ** 2)))
        return replace(
            self,
            scale=d,
            sigma=self.sigma if self.sigma is not None else round(SIGMA_PER_DIAMETER * d, 2),
            min_distance=self.min_distance or max(1, int(round(MIN_DISTANCE_PER_DIAMETER * d))),
            min_area=min_area,
            max_area=max_area,
            background=self.background if self.background is not None else round(BACKGROUND_PER_DIAMETER * d, 1),
            neck_depth=self.neck_depth or 0.0,
        )

    def scaled(self, factor: float) -> SegmentParams:
        """The same settings for the image resized by ``factor`` (e.g. patches area-averaged from a window of W px
        to S px: factor S / W): lengths times factor, areas times factor squared; None stays None."""
        if not (factor > 0 and math.isfinite(factor)):
            raise ConfigError(f"SegmentParams.scaled: factor={factor!r}, expected a number > 0")
        if factor == 1:
            return self

        def length(value):
            return None if value is None else round(float(value) * factor, 2)

        def area(value):
            return None if value is None else max(1, int(round(value * factor * factor)))

        return replace(
            self,
            scale=length(self.scale),
            sigma=length(self.sigma),
            min_distance=None if self.min_distance is None else max(1, int(round(self.min_distance * factor))),
            min_area=area(self.min_area),
            max_area=area(self.max_area),
            background=length(self.background),
        )

    def as_dict(self) -> dict:
        return asdict(self)


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


# --- the particle scale -----------------------------------------------------------------------------------

SCALE_STEP = 2**0.25  # between LoG scales
MIN_DIAMETER = 3.0  # px: smaller blobs are pixels, not particles
MAX_DIAMETER_SHARE = 0.5  # of the image's shorter side
WORKING_PIXELS = 1024 * 1024  # larger images are averaged down for the scale estimate (lengths scaled back)
SIGNIFICANCE = 4.0  # a blob votes when its response exceeds this many robust stds of the response at its scale


@dataclass(frozen=True)
class ScaleEstimate:
    """The particle diameter one or more images show, and how it was found."""

    diameter_px: float | None  # None: no blob stood out
    blobs: int  # scale-space maxima that voted
    response: float  # median response of the voting blobs (grey levels: ~ the particles' contrast)
    diameters_tried_px: tuple[float, float]  # the range of the LoG scales, as disc diameters
    refined_px: float | None = None  # the diameter chosen by `search_scale`
    candidates: tuple = ()  # every fixed point `search_scale` found (`Fixed`)
    alike: bool = False  # min_separability lowered for a scale of alike segments (`search_scale`; `resolve_params`)
    plateau: bool = False  # the scale smooths more than the particles' size asks (`_plateau`)
    depth: float | None = None  # the neck depth chosen with the scale
    grid: tuple = ()  # (scale, neck depth, segments' median, separability) of every scale segmented

    def as_dict(self) -> dict:
        return {
            "diameter_px": None if self.diameter_px is None else round(self.diameter_px, 2),
            "blobs": self.blobs,
            "response": round(self.response, 4),
            "diameters_tried_px": [round(v, 1) for v in self.diameters_tried_px],
            "refined_px": None if self.refined_px is None else round(self.refined_px, 2),
            "candidates": [f.as_list() for f in self.candidates],
            "candidate_fields": list(Fixed._fields),
            "alike": self.alike,
            "plateau": self.plateau,
            "neck_depth": self.depth,
            "grid": [[round(s, 2), d, None if math.isnan(m) else round(m, 2), round(q, 3)] for s, d, m, q in self.grid],
        }


def _diameters(shape: tuple[int, int]) -> np.ndarray:
    top = MAX_DIAMETER_SHARE * min(shape)
    n = max(1, int(math.floor(math.log(top / MIN_DIAMETER) / math.log(SCALE_STEP))) + 1)
    return MIN_DIAMETER * SCALE_STEP ** np.arange(n)


def _log_stack(bright: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
    """-s^2 LoG_s of ``bright`` per scale s (len(sigmas), H, W); large scales on an averaged-down copy (effective
    sigma 2-4 px), interpolated back."""
    from skimage.transform import resize

    h, w = bright.shape
    out = np.empty((len(sigmas), h, w), np.float32)
    image = np.asarray(bright, np.float64)
    for k, s in enumerate(sigmas):
        f = 1
        while s / (2 * f) >= 2 and min(h, w) // (2 * f) >= 16:
            f *= 2
        small = image if f == 1 else resize(image, (h // f, w // f), order=1, anti_aliasing=True)
        r = -((s / f) ** 2) * ndi.gaussian_laplace(small, s / f, mode="reflect")
        out[k] = r if f == 1 else resize(r, (h, w), order=1)
    return out


def blob_responses(bright: np.ndarray, exclude: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Scale-space maxima of the bright blobs: (diameters px, responses) of those standing out of their scale's
    noise (SIGNIFICANCE robust stds). ``exclude``: pixels whose blobs do not count (annotations)."""
    bright = np.asarray(bright, np.float32)
    factor = max(1, int(math.ceil(math.sqrt(bright.size / WORKING_PIXELS))))
    if factor > 1:
        from skimage.transform import resize

        shape = (bright.shape[0] // factor, bright.shape[1] // factor)
        bright = resize(bright, shape, order=1, anti_aliasing=True).astype(np.float32)
        exclude = None if exclude is None else resize(exclude.astype(float), shape, order=0) > 0.5
    diameters = _diameters(bright.shape)
    sigmas = diameters / (2 * math.sqrt(2))
    stack = _log_stack(bright, sigmas)
    found_d, found_r = [], []
    h, w = bright.shape
    for k, s in enumerate(sigmas):
        r = stack[k]
        centre = np.median(r)
        noise = 1.4826 * np.median(np.abs(r - centre)) + 1e-6
        window = 2 * int(math.ceil(s)) + 1
        peak = (r == ndi.maximum_filter(r, size=window, mode="nearest")) & (r > centre + SIGNIFICANCE * noise)
        if k > 0:
            peak &= r >= stack[k - 1]
        if k + 1 < len(sigmas):
            peak &= r >= stack[k + 1]
        margin = int(math.ceil(s))  # blobs centred within one sigma of the edge are mostly outside it
        peak[:margin], peak[h - margin :], peak[:, :margin], peak[:, w - margin :] = False, False, False, False
        if exclude is not None:
            peak &= ~exclude
        values = r[peak]
        found_d.append(np.full(values.size, diameters[k] * factor))
        found_r.append(values)
    return np.concatenate(found_d), np.concatenate(found_r)


def estimate_scale(bright_images: Sequence[np.ndarray], excludes: Sequence[np.ndarray | None] | None = None):
    """The particle diameter (px) of bright-particle images: the response-weighted median diameter of the blobs
    whose response is at least a third of the strongest ones' (the 90th percentile), so faint texture and grain
    do not vote."""
    excludes = excludes or [None] * len(bright_images)
    ds, rs = [], []
    shape = min((np.shape(b) for b in bright_images), key=min)
    for bright, exclude in zip(bright_images, excludes):
        d, r = blob_responses(bright, exclude)
        ds.append(d)
        rs.append(r)
    d, r = np.concatenate(ds), np.concatenate(rs)
    tried = _diameters(shape)
    tried = (float(tried[0]), float(tried[-1]))
    if d.size == 0:
        return ScaleEstimate(None, 0, 0.0, tried)
    strong = r >= np.quantile(r, 0.9) / 3
    d, r = d[strong], r[strong]
    order = np.argsort(d)
    cumulative = np.cumsum((r * d**2)[order])
    median = float(d[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])
    return ScaleEstimate(median, int(d.size), float(np.median(r)), tried)


# --- foreground and particles -----------------------------------------------------------------------------


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


def resolve_params(
    images: Sequence[np.ndarray], params: SegmentParams | None = None, polarity: str = "bright", progress: bool = False
) -> tuple[SegmentParams, ScaleEstimate | None]:
    """``params`` with every length and the neck depth set: the scale and the neck depth searched together on
    ``images`` (`search_scale`) where not given; the estimate is None when the scale was given. ``progress``: a bar
    over the scales segmented (each a segmentation of every image: minutes on large images)."""
    params = SegmentParams.from_config(params)
    if params.is_resolved:
        return params, None
    if params.neck_depth is not None and params.scale is not None:
        return params.resolved(), None
    prepared = [prepare(image, polarity, params.annotations) for image in images]
    # No blob standing out of the response's noise is no proof of no particles: where particles fill the image (a
    # dense layer of rods), they *are* the response's spread at their scale. The grid is segmented regardless.
    estimate = None
    if params.scale is None:
        estimate = estimate_scale([p.bright for p in prepared], [p.annotations for p in prepared])
    chosen, fixed, points = search_scale(prepared, params, progress=progress)
    grid = tuple((p.scale, p.depth, p.median, p.separability) for p in points)
    if chosen is None:
        search = None if estimate is None else replace(estimate, candidates=tuple(fixed), grid=grid)
        raise NoParticles(_nothing_consistent(estimate, points, fixed, params, polarity), params, search)
    resolved = replace(params, neck_depth=chosen.depth)
    if chosen.alike:  # lowered to the least-separating image's (two decimals, down): every image keeps its particles
        resolved = replace(resolved, min_separability=math.floor(100 * chosen.lowest + 1e-9) / 100)
    resolved = resolved.resolved(chosen.scale)
    if estimate is None:
        return resolved, None
    return resolved, replace(
        estimate,
        refined_px=chosen.scale,
        alike=chosen.alike,
        plateau=chosen.plateau,
        depth=chosen.depth,
        candidates=tuple(fixed),
        grid=grid,
    )


def _nothing_consistent(estimate: ScaleEstimate, points, fixed, params: SegmentParams, polarity: str) -> str:
    """What the search tried, for `NoParticles` (a scale given always resolves)."""
    if estimate.diameter_px is None:
        log_scale = (
            f"no blob stood out of the noise at any scale (LoG diameters {estimate.diameters_tried_px[0]:.0f}-"
            f"{estimate.diameters_tried_px[1]:.0f} px), and"
        )
    else:
        log_scale = f"the LoG scale {estimate.diameter_px:.1f} px and"
    scales = sorted({p.scale for p in points})
    if fixed:
        best = max(f.separability for f in fixed)
        why = (
            f"{len(fixed)} scale(s) whose segments agree with it, none separating enough (Otsu separability at most "
            f"{best:.2f} there, needed {params.min_separability}; nor segments alike enough to go below it)"
        )
    else:
        why = "at no scale were the segments of its own size (specks smaller, agglomerates larger)"
    return (
        f"{log_scale} segmenting at {len(scales)} scales ({scales[0]:.0f}-{scales[-1]:.0f} px) gave no consistent "
        f"particle size: {why}; nor did the segments keep one size over {PLATEAU_SCALES} scales where they separate"
        f" enough; {polarity} particles"
    )


def size_spread(diameters: np.ndarray) -> float:
    """log(q90 / q10) of the diameters: how unlike the segments are in size (NaN for fewer than two)."""
    if diameters.size < 2:
        return math.nan
    low, high = np.quantile(diameters, [0.1, 0.9])
    return float(math.log(high / low))


# --- the particle scale --------------------------------------------------------------------------------------------
#
# The particle diameter is a scale whose own segmentation (smoothing, seed distance and area limits set from it)
# gives segments of that size: a fixed point of s -> median diameter of the segments. Textured images have several
# (grain specks, particles, agglomerates). Following the map from a few starts (what this search did before) lands in
# one basin or another, and a small change anywhere moved which (EMPS: a one-line change to the smoothing moved 121
# of 240 medians, 13 across the 20 % line). So the map is segmented on a quarter-octave grid, every fixed point on it
# is found, and they are judged by what makes a segmentation trustworthy in scale space: a structure that persists.
# Particles segment to the same size over a wide range of settings (their median holds from a fraction of their size
# to several times it: the basin), specks and texture follow the smoothing and hold over a step or two; and
# particles are alike in size, specks come in every size (the size spread). experiments/profile/README.md.

REFINE_ROUNDS = 4
CONSISTENT = 0.15  # |log(segments' median / scale)| below this: the segmentation agrees with its scale
MIN_SCALE = 6.0  # px: smaller fixed points are grain, texture or JPEG blocks (EMPS' smallest particles: 7 px)
# The size spread log(q90 / q10) a fixed point of fewer than two segments is judged with: one segment shows
# nothing of how alike the particles are (specks of every size spread 1.4-1.8, alike particles 0.03-0.7)
SPREAD_UNKNOWN = 3.0
# A dense packing of large textured particles: their narrow gaps make a lopsided histogram that Otsu separates at
# 0.55-0.65 (below min_separability), while the texture cut into specks separates at 0.72-0.79. A fixed point below
# min_separability is a candidate where it separates at least ALIKE_SEPARABILITY on every image and its segments
# are alike (spread at most ALIKE_SPREAD) and at least ALIKE_SEGMENTS; where the default min_separability is kept
# (a value set by hand is kept as given). Alike: a spread of at most ALIKE_SPREAD, or at most ALIKE_SHARE of the
# spread of the candidate separating min_separability that would be chosen without it. Specks of every size spread
# 1.4-1.8 (the wrong fixed points' median 1.63), particles 0.03-0.77 (the right ones' median 0.38): half lies at the
# geometric middle of the two. Absolute alone, 0.5 cut into the particles' range (EMPS ce41e4e56d's spheres: 0.77,
# against texture specks' 1.70), and smoothed noise alone on a film spreads 0.94: with no candidate to be more alike
# than, only ALIKE_SPREAD counts.
ALIKE_SEPARABILITY = 0.55
ALIKE_SPREAD = 0.5
ALIKE_SHARE = 0.5
ALIKE_SEGMENTS = 5


class Point(NamedTuple):
    """Every image segmented with the settings of one scale and neck depth (`search_scale`)."""

    scale: float  # px
    depth: float  # neck depth of the watershed's seeds
    median: float  # of the segments' equivalent diameters (not touching the border, of plausible area); NaN: none
    weighted: float  # their area-weighted median
    spread: float  # `size_spread`
    segments: int  # how many
    separability: float  # of the threshold, mean over the images
    lowest: float  # the least of the images'

    def size(self, weighted: bool) -> float:
        return self.weighted if weighted else self.median

    def agrees(self, weighted: bool) -> bool:
        """Its segments' (area-weighted) median lies within CONSISTENT of its scale."""
        size = self.size(weighted)
        return math.isfinite(size) and abs(math.log(size / self.scale)) < CONSISTENT


class Fixed(NamedTuple):
    """A fixed point of the scale map: of a run of grid scales whose segments agree with them, the one agreeing best
    (refined to its segments' own median when chosen)."""

    scale: float  # px
    depth: float
    median: float  # its segments' (area-weighted where the search followed that)
    separability: float
    lowest: float
    spread: float
    segments: int
    basin: int  # grid scales (same depth) whose segments' median lies within CONSISTENT of this one's
    alike: bool = False  # a candidate below min_separability for its alike segments (ALIKE_*)
    plateau: bool = False  # not a fixed point: a size held below the scale over an octave and more (`_plateau`)

    @property
    def evidence(self) -> float:
        """How persistent and how alike: the basin (quarter-octave steps) less the size spread."""
        return self.basin - (SPREAD_UNKNOWN if math.isnan(self.spread) else self.spread)

    def as_list(self) -> list:
        """The fields in order (JSON: NaN spread as None)."""
        f = self
        spread = None if math.isnan(f.spread) else round(f.spread, 3)
        return [round(f.scale, 2), f.depth, round(f.median, 2), round(f.separability, 3), round(f.lowest, 3), spread,
                f.segments, f.basin, f.alike, f.plateau]  # fmt: skip

    @classmethod
    def from_list(cls, values: Sequence) -> Fixed:
        """Back from `as_list` (a profile.json's candidates; one written before `plateau` existed has one field less)."""
        f = cls(*values)
        return f._replace(spread=math.nan if f.spread is None else f.spread)


def scale_grid(shape: tuple[int, int]) -> np.ndarray:
    """The scales searched: MIN_SCALE up to half the shorter side, SCALE_STEP apart (at least MIN_SCALE)."""
    top = MAX_DIAMETER_SHARE * min(shape)
    n = max(1, int(math.floor(math.log(max(top, MIN_SCALE) / MIN_SCALE) / math.log(SCALE_STEP) + 1e-9)) + 1)
    return MIN_SCALE * SCALE_STEP ** np.arange(n)


def search_scale(
    prepared: Sequence[Prepared], params: SegmentParams, progress: bool = False
) -> tuple[Fixed | None, list[Fixed], list[Point]]:
    """The particle diameter and the neck depth (where not given): every image segmented at each scale of
    `scale_grid` with each neck depth (0: every maximum seeds, NECK_DEPTH: seeds at necks only; `split_touching`),
    and where the grid steps over a fixed point or ends below one, there too (`_between_and_above`); the fixed
    points of each depth's map found (`fixed_points`), and of those separating at least ``min_separability`` (or
    alike, ALIKE_*) the one with the most `Fixed.evidence`: the widest basin, less the size spread; seeds at necks
    only where they make the sizes more alike (`_plain_unless_more_alike`). The chosen one is refined to its
    segments' own median (`refine`). Where no fixed point is a
    candidate, the same on the segments' area-weighted median (specks outnumbering a few particles pull the plain
    median below the particles' size at every scale; their share of the area is small); where none is either, a
    size the segments keep over an octave of scales that separate (`_plateau`). A scale given is
    the grid (its depth chosen the same way, agreement not required).
    Returns (the chosen or None, every fixed point found, every grid point)."""
    depths = (0.0, NECK_DEPTH) if params.neck_depth is None else (float(params.neck_depth),)
    given = params.scale is not None
    shape = min((p.bright.shape for p in prepared), key=min)
    scales = [float(params.scale)] if given else scale_grid(shape)
    bar = tqdm(scales, desc="particle scale", unit="scale", disable=not progress)
    points = [_point(prepared, params, s, depth) for s in bar for depth in depths]
    if given:  # every depth at that scale; seeds at necks where they make the sizes more alike (`_more_alike`)
        fixed = [_as_fixed(p, p.median, 1) for p in points]
        return (fixed[-1] if _more_alike(fixed[-1], fixed[0]) else fixed[0]), fixed, points
    points += _between_and_above(prepared, params, points, min(shape))
    points.sort(key=lambda p: (p.depth, p.scale))
    found: list[Fixed] = []
    for weighted in (False, True):
        fixed = [f for depth in depths for f in fixed_points([p for p in points if p.depth == depth], weighted)]
        found += fixed
        alike_spread = _alike_spread([f for f in fixed if f.separability >= params.min_separability])
        candidates = [c for c in (_candidate(f, params, alike_spread) for f in fixed) if c is not None]
        if candidates:
            best = max(candidates, key=lambda f: (f.evidence, f.separability))
            if best.depth != 0.0 and params.neck_depth is None:
                best = _plain_unless_more_alike(best, candidates, points, params, weighted, alike_spread)
            return refine(prepared, params, best, weighted, alike_spread), found, points
    plateau = _plateau([p for p in points if p.depth == 0.0], params)
    if plateau is not None:
        found.append(plateau)
    return plateau, found, points


PLATEAU_SCALES = 5  # grid scales (an octave) over which segments must hold their size to be particles (`_plateau`)


def _plateau(row: Sequence[Point], params: SegmentParams) -> Fixed | None:
    """Where no fixed point is a candidate: the longest run of at least PLATEAU_SCALES consecutive scales of
    ``row`` (one depth, in order of scale) that all separate at least ``min_separability`` and whose segments' medians
    lie within twice CONSISTENT of each other (in log), at its smallest scale; None where there is none. Particles
    a few px across on a noisy film separate only when smoothed more than their own scale asks: at their own scale
    the noise's specks join them (EMPS ed3a3cb76b: 7 px particles, separability 0.65 at 6-10 px), and from twice it
    they come out at their size, whatever the smoothing, for an octave and more. Noise and grain have no such run:
    their specks grow with the smoothing."""
    best: tuple[int, int] | None = None
    for start in range(len(row)):
        end, low, high = start, math.inf, -math.inf
        while end < len(row) and math.isfinite(row[end].median) and row[end].separability >= params.min_separability:
            low, high = min(low, row[end].median), max(high, row[end].median)
            if math.log(high / low) >= 2 * CONSISTENT:
                break
            end += 1
        if end - start >= PLATEAU_SCALES and (best is None or end - start > best[1] - best[0]):
            best = (start, end)
    if best is None:
        return None
    p = row[best[0]]
    return _as_fixed(p, p.median, best[1] - best[0])._replace(plateau=True)


def _plain_unless_more_alike(
    best: Fixed,
    candidates: list[Fixed],
    points: list[Point],
    params: SegmentParams,
    weighted: bool,
    alike_spread: float,
) -> Fixed:
    """``best`` (seeds at necks only) where it makes the segments more alike than every maximum seeding does near
    its scale (size spread at most NECK_SPREAD of that), else the plain segmentation: its best candidate within
    NECK_NEAR of ``best``'s scale, or where it has none, itself at ``best``'s scale where its segments come within
    twice CONSISTENT of that scale. Seeds at necks make a segmentation persist over scales by themselves (fewer
    seeds, whatever the scale), so persistence cannot choose them over the plain seeds: merging touching particles
    at shallow necks needs the sizes to say so (rods and irregular particles cut along their ridges come out in every
    length; touching particles merged come out as singles, pairs and triples). On tio2_sem, whose annotators split
    agglomerates at shallow necks, the plain map comes within 0.24 of its scale but never within CONSISTENT."""

    near = [c for c in candidates if c.depth == 0.0 and abs(math.log(c.scale / best.scale)) <= NECK_NEAR]
    if near:
        plain = max(near, key=lambda f: (f.evidence, f.separability))
    else:
        row = [p for p in points if p.depth == 0.0]
        at = min(row, key=lambda p: abs(math.log(p.scale / best.scale)))
        size = at.size(weighted)
        if not (math.isfinite(size) and abs(math.log(size / at.scale)) < 2 * CONSISTENT):
            return best
        plain = _candidate(_as_fixed(at, size, _basin(row, size, weighted)), params, alike_spread)
        if plain is None:
            return best
    return best if _more_alike(best, plain) else plain


def _more_alike(deep: Fixed, plain: Fixed) -> bool:
    """Whether ``deep``'s segments spread in size less than NECK_SPREAD of ``plain``'s (unknown: SPREAD_UNKNOWN)."""

    def spread(f: Fixed) -> float:
        return SPREAD_UNKNOWN if math.isnan(f.spread) else f.spread

    return spread(deep) < NECK_SPREAD * spread(plain)


def _between_and_above(prepared, params: SegmentParams, points: list[Point], side: int) -> list[Point]:
    """The scales the grid steps over: where the segments of one grid scale are larger than it and those of the next
    smaller (beyond CONSISTENT both), a fixed point lies between, and the scale where the map crosses its diagonal
    (interpolated in log scale) is segmented too; where the top scale's segments are still larger than it, the map
    is followed up from there (its segments' median, REFINE_ROUNDS at most, up to the image's shorter side)."""
    extra = []
    for depth in sorted({p.depth for p in points}):
        row = [p for p in points if p.depth == depth]
        g = [math.log(p.median / p.scale) if math.isfinite(p.median) else math.nan for p in row]
        for a, b, ga, gb in zip(row, row[1:], g, g[1:]):
            if ga >= CONSISTENT and gb <= -CONSISTENT:
                t = ga / (ga - gb)
                extra.append(_point(prepared, params, a.scale ** (1 - t) * b.scale**t, depth))
        top = row[-1]
        for _ in range(REFINE_ROUNDS):
            if not (math.isfinite(top.median) and top.median >= top.scale * math.exp(CONSISTENT) and top.median < side):
                break
            top = _point(prepared, params, top.median, depth)
            extra.append(top)
    return extra


def _point(prepared: Sequence[Prepared], params: SegmentParams, scale: float, depth: float) -> Point:
    resolved = replace(params, neck_depth=depth, min_separability=0.0).resolved(scale)
    measures = [_measure(p, resolved, retry_below=retry_separability(params)) for p in prepared]
    d = np.concatenate([m.diameters for m in measures])
    separabilities = [m.separability for m in measures]
    median, weighted = (float(np.median(d)), area_weighted_median(d)) if d.size else (math.nan, math.nan)
    return Point(
        resolved.scale, depth, median, weighted, size_spread(d), int(d.size),
        float(np.mean(separabilities)), min(separabilities),
    )  # fmt: skip


def _as_fixed(point: Point, median: float, basin: int, alike: bool = False) -> Fixed:
    p = point
    return Fixed(p.scale, p.depth, median, p.separability, p.lowest, p.spread, p.segments, basin, alike)


def fixed_points(points: Sequence[Point], weighted: bool = False) -> list[Fixed]:
    """The fixed points of one depth's map (``points`` in order of scale): of each run of consecutive scales whose
    segments agree with them (`Point.agrees`), the one agreeing best, with its basin: how many of ``points``
    segment to within CONSISTENT of its size."""
    sizes = [p.size(weighted) for p in points]
    fixed, k = [], 0
    while k < len(points):
        if not points[k].agrees(weighted):
            k += 1
            continue
        end = k
        while end + 1 < len(points) and points[end + 1].agrees(weighted):
            end += 1
        best = min(range(k, end + 1), key=lambda j: abs(math.log(sizes[j] / points[j].scale)))
        fixed.append(_as_fixed(points[best], float(sizes[best]), _basin(points, float(sizes[best]), weighted)))
        k = end + 1
    return fixed


def _basin(points: Sequence[Point], size: float, weighted: bool) -> int:
    """How many of ``points`` segment to within CONSISTENT of ``size``."""
    sizes = np.array([p.size(weighted) for p in points])
    with np.errstate(invalid="ignore"):
        return int(np.sum(np.abs(np.log(sizes / size)) < CONSISTENT))


def _alike_spread(plain: Sequence[Fixed]) -> float:
    """The size spread below which a fixed point under min_separability is alike: ALIKE_SPREAD, or ALIKE_SHARE of
    the spread of the one of ``plain`` (fixed points separating min_separability) the search would choose, where
    that is more."""
    if not plain:
        return ALIKE_SPREAD
    chosen = max(plain, key=lambda f: (f.evidence, f.separability))
    return max(ALIKE_SPREAD, ALIKE_SHARE * (SPREAD_UNKNOWN if math.isnan(chosen.spread) else chosen.spread))


def _candidate(f: Fixed, params: SegmentParams, alike_spread: float) -> Fixed | None:
    """``f`` where it may be chosen: separating at least min_separability, or alike (ALIKE_*; spread at most
    ``alike_spread``, `_alike_spread`) where that is the default; None otherwise."""
    if f.separability >= params.min_separability:
        return f
    alike = (
        params.min_separability == MIN_SEPARABILITY
        and f.lowest >= ALIKE_SEPARABILITY  # on every image: one image separating nothing lowers nothing
        and f.segments >= ALIKE_SEGMENTS
        and f.spread <= alike_spread  # NaN (fewer than two segments): never
    )
    return f._replace(alike=True) if alike else None


def refine(
    prepared: Sequence[Prepared],
    params: SegmentParams,
    f: Fixed,
    weighted: bool,
    alike_spread: float,
) -> Fixed:
    """``f`` moved to its segments' own (area-weighted) median while that lies 10 % or more from its scale
    (REFINE_ROUNDS at most), as long as the segmentation there still agrees with its scale, is still a candidate and
    still segments to within CONSISTENT of ``f``'s size; else where it last did. The scale returned is one segmented
    with, so that the final segmentation separates as the search saw it. ``alike_spread``: the search's
    (`_alike_spread`)."""
    current = f
    for _ in range(REFINE_ROUNDS):
        if abs(math.log(current.median / current.scale)) < 0.1:
            break
        point = _point(prepared, params, current.median, f.depth)
        size = point.size(weighted)
        if not point.agrees(weighted) or abs(math.log(size / f.median)) >= CONSISTENT:
            break
        moved = _candidate(_as_fixed(point, size, f.basin), params, alike_spread)
        if moved is None:
            break
        current = moved
    return current


class Measure(NamedTuple):
    """What the scale search needs of one segmentation (`_measure`)."""

    diameters: np.ndarray  # `segment_diameters`
    segments: int  # all watershed segments
    separability: float  # of the threshold


def _measure(prepared: Prepared, params: SegmentParams, retry_below: float | None = None) -> Measure:
    """`_foreground` (``retry_below`` as there) and `split_touching` of ``prepared`` with resolved ``params``,
    measured; each foreground and each split made once per image (memoised on ``prepared.measured``; both neck
    depths split at once). The foreground does not depend on the neck depth, and below ``min_separability`` it is empty (the same threshold
    otherwise), so the searches with either depth and either separability share it."""
    retry = retry_separability(params) if retry_below is None else retry_below
    plain = replace(params, min_separability=0.0)
    cut_key = (replace(plain, neck_depth=None), retry)
    if cut_key not in prepared.measured:
        cut = _foreground(prepared, cut_key[0], retry_below=retry)
        prepared.measured[cut_key] = (np.packbits(cut.foreground), cut.separability)
    packed, separability = prepared.measured[cut_key]
    kept = separability >= params.min_separability
    key = (plain, retry, kept)
    if key not in prepared.measured:
        shape = prepared.bright.shape
        foreground = np.unpackbits(packed, count=shape[0] * shape[1]).reshape(shape).astype(bool)
        # the search asks both depths at each scale: split with both at once (`split_by_depth`)
        depths = {plain.neck_depth, *((0.0, NECK_DEPTH) if plain.neck_depth in (0.0, NECK_DEPTH) else ())}
        for depth, labels in split_by_depth(foreground & kept, plain, sorted(depths)).items():
            at = (replace(plain, neck_depth=depth), retry, kept)
            prepared.measured[at] = Measure(segment_diameters(labels, params), int(labels.max()), separability)
    return prepared.measured[key]


def area_weighted_median(diameters: np.ndarray) -> float:
    """The diameter below which half the segments' *area* lies: specks of grain, noise or texture are many but
    small, so they move it far less than they move the plain median (a few particles among hundreds of specks)."""
    d = np.sort(np.asarray(diameters, dtype=np.float64))
    cumulative = np.cumsum(d * d)
    return float(d[np.searchsorted(cumulative, 0.5 * cumulative[-1])])


def segment_diameters(labels: np.ndarray, params: SegmentParams) -> np.ndarray:
    """Equivalent diameters (px) of the segments of plausible area (min_area..max_area) that touch no border."""
    areas = np.bincount(labels.ravel())
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    keep = (areas >= params.min_area) & (areas <= params.max_area)
    keep[0] = False
    keep[border] = False
    return 2.0 * np.sqrt(areas[keep] / np.pi)


class NoParticles(DataError):
    """No particle found; the message says what was tried and which keys to set. ``search``: the scale search's
    `ScaleEstimate` (its grid and fixed points) where one ran."""

    def __init__(self, what: str, params: SegmentParams, search: ScaleEstimate | None = None):
        self.what, self.params, self.search = what, params, search
        super().__init__(
            f"no particles found: {what}. Set the particle size by hand with data.segment.scale=DIAMETER_PX (and, "
            "if needed, data.segment.sigma, min_distance, min_area, max_area, min_separability), or data.polarity="
            "bright|dark when the particles' side of the grey scale was misread"
        )


def blob_centres(bright: np.ndarray, diameter: float, significant: bool = False) -> np.ndarray:
    """bool (H, W): centres of the bright blobs of about ``diameter`` px: maxima of -s^2 LoG_s at s = d / (2 sqrt 2),
    at least d / 2 apart, of at least a quarter of the strong ones' response (their 90th percentile).
    ``significant``: they must also stand out of the film's noise (`_out_of_film_noise`). Not by default: on a dense
    packing the film is the gaps and the particles' shaded sides, whose response is as strong as the particles',
    and real centres would be lost."""
    response, centres = _blob_maxima(bright, diameter)
    return _out_of_film_noise(bright, response, centres) if significant else centres


def _blob_maxima(bright: np.ndarray, diameter: float) -> tuple[np.ndarray, np.ndarray]:
    """(-s^2 LoG_s of ``bright``, `blob_centres` without ``significant``): the response is kept for the retry."""
    s = diameter / (2 * math.sqrt(2))
    r = _log_stack(bright, np.array([s]))[0]
    window = max(3, int(diameter / 2) | 1)
    peak = (r == ndi.maximum_filter(r, size=window, mode="nearest")) & (r > 0)
    if peak.any():
        peak &= r >= 0.25 * np.quantile(r[peak], 0.9)
    return r, peak


def _out_of_film_noise(bright: np.ndarray, response: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """The ``centres`` whose ``response`` stands SIGNIFICANCE robust stds out of the response on the film (the
    pixels below the image's Otsu threshold): on a grainy film with a few particles most maxima are grain, and the
    90th percentile of the maxima is grain too."""
    if not centres.any() or np.ptp(bright) == 0:
        return centres
    film = response[bright <= threshold_otsu(bright)]
    centre = np.median(film)
    return centres & (response >= centre + SIGNIFICANCE * 1.4826 * np.median(np.abs(film - centre)))


def retry_separability(params: SegmentParams) -> float:
    """The separability below which `_foreground` thresholds again around the blobs standing out of the film's
    noise: the default MIN_SEPARABILITY, or ``params.min_separability`` where it is higher. A threshold below the
    default (the scale search's, lowered for a dense packing, or one set by hand) says which cuts to accept, not
    which to try again: the search measured its fixed points retrying below the default, so the final segmentation
    with the lowered threshold segments what the search measured."""
    return max(params.min_separability, MIN_SEPARABILITY)


def _foreground(prepared: Prepared, params: SegmentParams, retry_below: float | None = None) -> Cut:
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

    A connected piece of the foreground is kept when it is at least ``min_area`` and reaches within half a
    diameter of a blob centre: grain, noise and texture specks past the threshold away from every blob of the
    particles' size are not particles (on a grainy film they outnumber a few particles and would set the median);
    a hollow particle's rim lies within half a diameter of its centre."""
    images = [prepared.bright]
    if params.background:  # the illumination flattened only where it separates particles better
        images.insert(0, flatten(prepared.bright, params.background))
    # "nearest", not "reflect": mirrored, a particle a few px from the border and its image blur across the gap
    # and its segment reaches the border (not measured: the synthetic sweep's 110 px discs)
    smooths = [ndi.gaussian_filter(im, params.sigma, mode="nearest") if params.sigma > 0 else im for im in images]
    maxima = [_blob_maxima(im, params.scale) for im in images]

    def best(centre_sets: list[np.ndarray]) -> Cut:
        return max(
            (_threshold(smooth, c & ~prepared.annotations, prepared.annotations, params.scale)
             for smooth, c in zip(smooths, centre_sets)),
            key=lambda cut: cut.separability,
        )  # fmt: skip

    cut = best([peak for _, peak in maxima])
    if cut.separability < (retry_separability(params) if retry_below is None else retry_below):
        retry = best([_out_of_film_noise(im, r, peak) for im, (r, peak) in zip(images, maxima)])
        cut = retry if retry.separability >= cut.separability else cut
    if cut.separability < params.min_separability:
        return cut._replace(foreground=np.zeros(cut.foreground.shape, bool))
    components, n = ndi.label(cut.foreground)
    keep = np.bincount(components.ravel(), minlength=n + 1) >= params.min_area
    near = ndi.distance_transform_edt(~cut.centres) <= 0.5 * params.scale
    keep &= np.bincount(components[near], minlength=n + 1) > 0
    keep[0] = False
    return cut._replace(foreground=_fill_holes(keep[components], params, prepared.annotations))


# A hole at least this convex, and filling at least this share of the disc of its length, is a particle's own darker
# centre, not a gap between several particles (concave, or a square between four: 0.64 of its disc at most)
ROUND_HOLE_SOLIDITY = 0.85
ROUND_HOLE_FILL = 0.7


def _fill_holes(foreground: np.ndarray, params: SegmentParams, marks: np.ndarray) -> np.ndarray:
    """``foreground`` with its marked and its round holes filled (the holes found once for both).

    A hole that lies wholly in ``marks`` (the annotation mask) is a mark enclosed by one piece of the foreground: it
    lies on a particle, and the particle goes on under it. Most are the particles' own texture read as marks (specks
    and strokes of character size and contrast: EMPS bb3d8c922b's textured spheres lost 5,697 px of pinholes this
    way, and the distance transform around them cut each sphere into pieces); a label printed on a particle hides
    part of it. Marks on the film or reaching it are left out as before.

    A round hole: a particle seen as a bright rim around a centre as grey as the background (SEM edge effect on
    spheres, hollow shells) thresholds into a ring, which the watershed would cut into arcs of a fraction of its
    size. A hole is the particle's own centre when it is round (solidity at least ROUND_HOLE_SOLIDITY, area at least
    ROUND_HOLE_FILL of the disc of its major axis) and of plausible area; a gap among touching particles is bounded
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
        if region.area >= ROUND_HOLE_FILL * disc and region.solidity >= ROUND_HOLE_SOLIDITY:  # the hull last: dearest
            filled[region.slice] |= region.image
    return filled


class Cut(NamedTuple):
    """A threshold's foreground and how well it separates (`_threshold`)."""

    foreground: np.ndarray  # bool
    separability: float  # Otsu's between-class / total variance
    centres: np.ndarray  # bool: the blob centres whose surroundings were thresholded
    smooth: np.ndarray | None = None  # the smoothed image thresholded (None: nothing was)
    threshold: float = math.nan


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


OUTLINE_LEVELS = np.linspace(0.05, 0.95, 19)  # of the way from the film's grey to the particles': levels tried
OUTLINE_BAND = 0.25  # x the diameter: the band around the outlines whose contours count
MIN_CONTOUR = 20  # px: a level whose contour in the band is shorter says nothing


def edge_level(cut: Cut, scale: float, outside: np.ndarray | None = None) -> float | None:
    """The grey level of the particles' strongest edges, where it lies below the threshold (None elsewhere).

    Otsu's threshold sits where the two classes' histograms part, about halfway up the particles' edge or above
    it (EMPS: 0.58 of the way from the film's grey to the particles', median over 240 images), and that is where
    a step edge blurred by the optics and the smoothing lies. A particle whose projected thickness or shading
    falls off towards its outline (a sphere in transmission: contrast sqrt(1 - r^2 / R^2)) has its steepest
    gradient, and its outline, further out: the instance maps' outlines lie at 0.38 (median). Of the iso-grey
    contours in a band around the outlines (OUTLINE_BAND diameters either side), the level whose contour has the
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
    for level in low + (high - low) * OUTLINE_LEVELS:
        above = smooth >= level
        contour = above & ~ndi.binary_erosion(above) & near
        strength.append(gradient[contour].mean() if contour.sum() >= MIN_CONTOUR else 0.0)
    level = float(low + (high - low) * OUTLINE_LEVELS[int(np.argmax(strength))])
    return level if level < cut.threshold else None


def _outline_band(scale: float) -> float:
    """px: OUTLINE_BAND diameters, at least 2 px."""
    return max(2.0, OUTLINE_BAND * scale)


def grow_to_edges(
    cut: Cut, labels: np.ndarray, scale: float, min_area: int, annotations: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(labels, foreground) with every segment grown out to the particles' edge level (`edge_level`) over the
    pixels connected to it, each pixel to the segment it is reached from first going down the grey (a watershed):
    segments of ``min_area`` or more grow, none merge and none appear, none into the ``annotations``. Unchanged
    where the edges lie at the threshold or above."""
    extent = _grown_foreground(cut, scale, annotations)
    if extent is cut.foreground:
        return labels, extent
    grown = watershed(-cut.smooth, labels, mask=extent).astype(np.int32)
    # A watershed sliver or speck below min_area stays as it was: grown, hundreds of them on a textured film
    # would cross min_area and count as particles.
    small = np.bincount(labels.ravel(), minlength=grown.max() + 1) < min_area
    small[0] = False
    kept = ~small[grown] | (labels > 0)
    return np.where(kept, grown, 0).astype(np.int32), extent & kept


def _grown_foreground(cut: Cut, scale: float, annotations: np.ndarray) -> np.ndarray:
    """The foreground grown out to the edge level (`edge_level`), over connected pixels at most OUTLINE_BAND
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


def particle_foreground(image: np.ndarray, params: SegmentParams | None = None, polarity: str = "bright") -> np.ndarray:
    """The bool foreground of `segment_particles` without splitting it into particles (cheaper): pixels past
    the Otsu threshold of the smoothed, flattened image in the particles' direction, less annotations and
    connected specks below ``min_area``, grown out to the particles' edges (`grow_to_edges`; unsplit, every piece
    grows, watershed slivers too: a superset of `segment_particles`' foreground). All False when no particle
    stands out."""
    params = SegmentParams.from_config(params)
    try:  # the neck depth splits the foreground, it does not change it: none chosen
        params, _ = resolve_params([image], replace(params, neck_depth=params.neck_depth or 0.0), polarity)
    except NoParticles:
        return np.zeros(np.shape(image)[:2], bool)
    prepared = prepare(image, polarity, params.annotations)
    cut = _foreground(prepared, params)
    return _grown_foreground(cut, params.scale, prepared.annotations) if params.grow_outlines else cut.foreground


def segment_particles(
    image: np.ndarray, params: SegmentParams | None = None, polarity: str = "bright"
) -> tuple[np.ndarray, np.ndarray]:
    """Segment particles: brighter than the background (polarity "bright") or darker ("dark").

    Returns (labels, foreground): int32 labels (0 = none) of the watershed segments, and the bool
    foreground mask: everything above the threshold except annotations and connected specks smaller than
    min_area (it keeps agglomerates too large to count as particles), grown out to the particles' edges where
    those lie below the threshold (`grow_to_edges`; the labels with it). ``params`` not resolved (the default):
    the lengths follow from this image's particle scale. Empty when no particle stands out.
    """
    try:
        params, _ = resolve_params([image], params, polarity)
    except NoParticles:
        shape = np.shape(image)[:2]
        return np.zeros(shape, np.int32), np.zeros(shape, bool)
    found = segment_with_report(image, params, polarity)
    return found.labels, found.foreground


def split_touching(foreground: np.ndarray, params: SegmentParams) -> np.ndarray:
    """Watershed of the distance transform: seeds at its maxima at least min_distance apart (one per particle core)
    that stand neck_depth of their height above the saddle to a higher one (a neck, not a bump on a ridge)."""
    return split_by_depth(foreground, params, (params.neck_depth,))[params.neck_depth]


def split_by_depth(foreground: np.ndarray, params: SegmentParams, depths: Sequence[float]) -> dict[float, np.ndarray]:
    """`split_touching` with each neck depth of ``depths``, sharing the distance transform and its maxima (the
    scale search segments every scale with two depths); a depth whose caps remove no seed shares the watershed too."""
    if not foreground.any():
        return {depth: np.zeros(foreground.shape, np.int32) for depth in depths}
    components, _ = ndi.label(foreground)
    distance = ndi.distance_transform_edt(foreground)
    peaks = peak_local_max(distance, min_distance=params.min_distance, labels=components, exclude_border=False)
    seed_mask = np.zeros(foreground.shape, bool)
    seed_mask[tuple(peaks.T)] = True
    if params.seed_depth > 0:
        seed_mask &= h_maxima(distance, params.seed_depth).astype(bool)
    split: dict[float, np.ndarray] = {}
    made: list[tuple[np.ndarray, np.ndarray]] = []
    for depth in depths:
        seeds_at = _neck_caps(distance, depth, seed_mask, components) if depth > 0 else seed_mask
        same = next((labels for seeds, labels in made if np.array_equal(seeds, seeds_at)), None)
        if same is None:
            seeds, _ = ndi.label(seeds_at)  # a flat top (plateau) yields adjacent peaks: one seed, not several
            same = watershed(-distance, seeds, mask=foreground).astype(np.int32)
            made.append((seeds_at, same))
        split[depth] = same
    return split


def _neck_caps(distance: np.ndarray, depth: float, peaks: np.ndarray, components: np.ndarray) -> np.ndarray:
    """bool: the seeds at ``depth``: the caps of the distance transform's domes that stand ``depth`` of their height
    above the saddle to a higher dome (s + 1 <= (1 - depth) (p + 1) for a peak p over a saddle s: the dynamic of
    log(1 + distance); the 1 px keeps pixel-high bumps of thin pieces from counting as necks), those holding one of
    ``peaks``. A cap is the dome's top lowered by that depth, so a ridge of equal or nearly equal maxima (a rod) is
    one cap: one seed, where h-maxima would keep each of its equal tops. Every component keeps its top, which stands
    log(1 + p) above the background's 0.

    The same caps as one reconstruction over the image (`_caps`), at a fraction of its cost (it sorts every pixel):
    nothing outside an 8-connected cluster of the foreground reaches its caps (the background's 0 lies below every
    pixel of the foreground). A cluster that is one component (``components``: 4-connected labels) with one peak, its
    top, has one cap: the pixels connected to the top that lie within the depth of it (a threshold). The other
    clusters are reconstructed each on its bounding box, or all at once where those boxes would cover the image."""
    height = np.log1p(distance)
    n = int(components.max())
    clusters, m = ndi.label(distance > 0, structure=np.ones((3, 3), bool))
    cluster_of = np.zeros(n + 1, np.int64)
    cluster_of[components] = clusters
    alone = np.bincount(cluster_of[1:], minlength=m + 1)[cluster_of] == 1  # the component is its whole cluster
    count = np.bincount(components[peaks], minlength=n + 1)
    top = np.zeros(n + 1)
    np.maximum.at(top, components, height)
    at_peak = np.zeros(n + 1)
    np.maximum.at(at_peak, components[peaks], height[peaks])
    simple = alone & (count == 1) & (at_peak == top)
    simple[0] = False
    within = (height >= (top + math.log(1 - depth))[components]) & simple[components]
    pieces, _ = ndi.label(within)
    held = np.unique(pieces[peaks])
    seeds = np.isin(pieces, held[held > 0])
    rest = np.unique(cluster_of[(count > 0) & ~simple])
    rest = rest[rest > 0]
    if rest.size == 0:
        return seeds
    objects = ndi.find_objects(clusters)
    boxes = [objects[c - 1] for c in rest]
    if sum((r.stop - r.start + 2) * (c.stop - c.start + 2) for r, c in boxes) >= distance.size:
        everywhere = _caps(distance, depth, peaks)  # the clusters' boxes cover the image: one pass is cheaper
        return np.where(np.isin(clusters, rest), everywhere, seeds)
    for c, (rows, cols) in zip(rest, boxes):
        box = (slice(max(rows.start - 1, 0), rows.stop + 1), slice(max(cols.start - 1, 0), cols.stop + 1))
        inside = clusters[box] == c
        caps = _caps(np.where(inside, distance[box], 0.0), depth, peaks[box] & inside)
        seeds[box] |= caps & inside
    return seeds


def _caps(distance: np.ndarray, depth: float, peaks: np.ndarray) -> np.ndarray:
    """bool: the caps at ``depth`` holding one of ``peaks`` over all of ``distance`` (`_neck_caps`)."""
    from skimage.morphology import local_maxima, reconstruction

    height = np.log1p(distance)
    lowered = reconstruction(height + math.log(1 - depth), height, method="dilation")  # each dome lowered by depth
    caps, _ = ndi.label(local_maxima(lowered) & (distance > 0))
    held = np.unique(caps[peaks])
    return np.isin(caps, held[held > 0])


class Segmentation(NamedTuple):
    """`segment_with_report`: the segmentation and what the profile reports of it."""

    labels: np.ndarray  # int32, 0 = none
    foreground: np.ndarray  # bool
    separability: float  # Otsu's
    grown: float  # the share of foreground the outlines' growth added (`grow_to_edges`; 0: none)


def segment_with_report(image: np.ndarray, params: SegmentParams, polarity: str) -> Segmentation:
    """`segment_particles` with resolved ``params``, and what the profile reports of it (`Segmentation`)."""
    prepared = prepare(image, polarity, params.annotations)
    cut = _foreground(prepared, params)
    labels = split_touching(cut.foreground, params)
    if not params.grow_outlines:
        return Segmentation(labels, cut.foreground, cut.separability, 0.0)
    labels, foreground = grow_to_edges(cut, labels, params.scale, params.min_area, prepared.annotations)
    grown = float(foreground.sum() / cut.foreground.sum() - 1) if cut.foreground.any() else 0.0
    return Segmentation(labels, foreground, cut.separability, grown)
