"""Finding particles in an unannotated image, whatever their size: drgan's one classical segmentation.

Profiling, patch mining, background selection and the FID brightness guards all ask the same question (which pixels
are particles, and which particle is which), so they all call this module. Nothing here is tuned to one data set:
every length follows from the particles' own scale, measured first.

1. **Grey**: 8/16-bit, float and RGB(A) arrays become one grey channel in [0, 1]; dark particles are turned bright
   (``1 - grey``), so everything below looks for bright particles.
2. **Annotations** (`annotation_mask`): scale bars, their text, panel letters and label boxes are drawn in pure black
   or white; they are found by shape (long thin solid bars, solid boxes, character-sized thin strokes near an edge)
   and filled from their surroundings, so that they are neither particles nor background.
3. **Scale** (`estimate_scale`): the scale-normalised Laplacian of Gaussian, ``-s^2 LoG_s``, peaks at
   ``s = d / (2 sqrt 2)`` on a disc of diameter ``d`` whatever its contrast (Lindeberg's scale selection). Its
   maxima over position and scale, from 3 px to half the image, are the image's blobs; the strong ones (well above
   the response's noise at their scale) vote, weighted by their response, for the particle diameter. Grain and noise
   respond at small scales only weakly and are outvoted; an agglomerate still shows its particles' seams. From it and
   from 8, 16, .. px, `search_scale` follows each start to a scale whose segments have that median size, and keeps
   the one that separates best; or, where a dense packing's narrow gaps separate less than its particles' texture,
   the larger one whose segments are far more alike in size.
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
# `SegmentParams.neck_depth` left None: NECK_DEPTH is taken when it narrows the spread of the segments' sizes,
# log(q90 / q10) of their diameters, to NECK_SPREAD of that with every maximum seeding or less (`choose_neck`).
NECK_DEPTH = 0.2
NECK_SPREAD = 0.8
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
    # maximum min_distance apart seeds. None (the default): 0 or NECK_DEPTH, whichever the images' sizes say
    # (`choose_neck`).
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
    candidates: tuple = ()  # (start, fixed point, separability) of each search
    alike: bool = False  # min_separability lowered for a scale of alike segments (`search_scale`; `resolve_params`)
    necks: tuple = ()  # (neck depth, size spread log(q90 / q10)) of each depth `choose_neck` tried

    def as_dict(self) -> dict:
        return {
            "diameter_px": None if self.diameter_px is None else round(self.diameter_px, 2),
            "blobs": self.blobs,
            "response": round(self.response, 4),
            "diameters_tried_px": [round(v, 1) for v in self.diameters_tried_px],
            "refined_px": None if self.refined_px is None else round(self.refined_px, 2),
            "candidates": [[round(float(v), 3) for v in c] for c in self.candidates],
            "alike": self.alike,
            "necks": [[float(depth), None if math.isnan(spread) else round(spread, 3)] for depth, spread in self.necks],
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
    # What the scale search has segmented of this image, per setting (`_measure`): it visits the same scales from
    # several starts and with both neck depths.
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
    """``params`` with every length and the neck depth set: the scale estimated from ``images`` when not given (the
    estimate is None when it was), the neck depth chosen from them when None (`choose_neck`). ``progress``: a bar
    per search over its starting diameters (each a few segmentations of every image: minutes on large images)."""
    params = SegmentParams.from_config(params)
    if params.is_resolved:
        return params, None
    if params.neck_depth is not None and params.scale is not None:
        return params.resolved(), None
    prepared = [prepare(image, polarity, params.annotations) for image in images]
    if params.neck_depth is None:
        resolved, estimate = choose_neck(prepared, params, polarity, progress)
    else:
        resolved, estimate = _resolve_scale(prepared, params, polarity, progress=progress)
    alike = resolved.min_separability < params.min_separability  # lowered for a dense packing (`search_scale`)
    return resolved, None if estimate is None else replace(estimate, alike=alike)


def choose_neck(
    prepared: Sequence[Prepared], params: SegmentParams, polarity: str, progress: bool = False
) -> tuple[SegmentParams, ScaleEstimate | None]:
    """Resolve ``params`` twice, with every maximum seeding (neck depth 0) and with NECK_DEPTH, and keep NECK_DEPTH
    where it narrows the spread of the segments' diameters, log(q90 / q10), to NECK_SPREAD of the other's or less.

    A rod or an irregular particle cut along its ridge gives pieces of every length, and merged back the particles
    are alike; touching particles merged at their necks give singles, pairs and triples, no narrower than before.
    EMPS (every third image, 85 with >= 5 instances): where 0.2 set the median right and 0 did not, its spread was
    0.66 of the other's (median; 16 of 19 below 0.8, the 20th found nothing with 0); tio2_sem's train set 0.92,
    tio2_tsem's 1.01 (experiments/profile/README.md). Merging at necks makes particles larger: a deeper search that
    settled at a smaller scale found something else (a field of alike specks), and is not kept. Where one of them
    finds no particle, the other is kept; where neither, the error is the first's. A depth that changes no segment
    at the first's scale is not searched again."""
    tried: list[tuple[float, float]] = []
    first: NoParticles | None = None
    best: tuple[SegmentParams, ScaleEstimate | None, float] | None = None
    for depth in (0.0, NECK_DEPTH):
        smallest = best[0].scale if best is not None else None  # merging at necks makes particles no smaller
        # the first's threshold: lowered for a dense packing (`search_scale`), the deeper search judges its scale too
        threshold = best[0].min_separability if best is not None else params.min_separability
        try:
            resolved, estimate = _resolve_scale(
                prepared, replace(params, neck_depth=depth, min_separability=threshold), polarity, smallest, progress
            )
        except NoParticles as error:
            first = first or error
            tried.append((depth, math.nan))
            continue
        measures = [_measure(p, resolved) for p in prepared]
        spread = size_spread(np.concatenate([m.diameters for m in measures]))
        tried.append((depth, spread))
        if best is None:
            best = (resolved, estimate, spread)
            deeper = replace(resolved, neck_depth=NECK_DEPTH)
            if all(m.segments == _measure(p, deeper).segments for m, p in zip(measures, prepared)):
                break  # no shallow neck at this scale: nothing for the deeper seeds to merge
        elif spread < NECK_SPREAD * best[2] and resolved.scale >= best[0].scale:  # NaN: fewer than two segments
            best = (resolved, estimate, spread)
    if best is None:
        raise first
    resolved, estimate, _ = best
    return resolved, None if estimate is None else replace(estimate, necks=tuple(tried))


def size_spread(diameters: np.ndarray) -> float:
    """log(q90 / q10) of the diameters: how unlike the segments are in size (NaN for fewer than two)."""
    if diameters.size < 2:
        return math.nan
    low, high = np.quantile(diameters, [0.1, 0.9])
    return float(math.log(high / low))


def _resolve_scale(
    prepared: Sequence[Prepared],
    params: SegmentParams,
    polarity: str,
    smallest: float | None = None,
    progress: bool = False,
) -> tuple[SegmentParams, ScaleEstimate | None]:
    """``params`` (neck depth set) with every length set: from the scale given, else from the scale searched
    (started from ``smallest`` and above only, when given)."""
    if params.scale is not None:
        return params.resolved(), None
    estimate = estimate_scale([p.bright for p in prepared], [p.annotations for p in prepared])
    # No blob standing out of the response's noise is no proof of no particles: where particles fill the image (a
    # dense layer of rods), they *are* the response's spread at their scale. The search's own starts still run.
    fixed, tried = search_scale(prepared, params, estimate.diameter_px, smallest=smallest, progress=progress)
    if fixed is None:
        # Every start collapsed to grain: specks that outnumber a few particles pull the plain median of the
        # segments, round after round, below MIN_SCALE. Their share of the segments' *area* is small, so the search
        # follows the area-weighted median instead (only here: where the plain search settles, it measures
        # polydisperse particles better, e.g. TiO2's, whose area-weighted median lies 10-15 % above the median).
        fixed, weighted_tried = search_scale(
            prepared, params, estimate.diameter_px, weighted=True, smallest=smallest, progress=progress
        )
        tried = tried + weighted_tried
    if fixed is None:
        log_scale = (
            f"no blob stood out of the noise at any scale (LoG diameters {estimate.diameters_tried_px[0]:.0f}-"
            f"{estimate.diameters_tried_px[1]:.0f} px), and"
            if estimate.diameter_px is None
            else f"the LoG scale {estimate.diameter_px:.1f} px and"
        )
        raise NoParticles(
            f"{log_scale} the diameters "
            f"{', '.join(f'{t[0]:.0f}' for t in tried)} px tried as starting points gave no consistent particle size "
            f"(Otsu separability at most {max((t[2] for t in tried), default=0):.2f}, needed "
            f"{params.min_separability}; {polarity} particles)",
            params,
        )
    if fixed.separability < params.min_separability:  # chosen for its alike segments (`search_scale`): lowered to
        # the least-separating image's (two decimals, down), so that every image keeps its particles
        params = replace(params, min_separability=math.floor(100 * fixed.lowest + 1e-9) / 100)
    return params.resolved(fixed.scale), replace(estimate, refined_px=fixed.scale, candidates=tuple(tried))


REFINE_ROUNDS = 4
START_DIAMETERS = (8.0, 16.0, 32.0, 64.0, 128.0, 256.0)  # px, besides the LoG's: starting points of the search
CONSISTENT = 0.15  # |log(segments' median / scale)| below this: the segmentation agrees with its scale
MIN_SCALE = 6.0  # px: smaller fixed points are grain, texture or JPEG blocks (EMPS' smallest particles: 7 px)
# Per doubling of the scale: texture inside large particles separates nearly as well as the particles themselves
# (EMPS: 0.88 at 3.7 px against 0.86 at 35 px), so of two fixed points the larger wins unless clearly worse.
LARGER_BONUS = 0.05
# A dense packing of large textured particles: their narrow gaps make a lopsided histogram that Otsu separates at
# 0.58-0.63 (below min_separability), while the texture cut into specks separates at 0.72-0.79. The specks come in
# every size (size spread log(q90 / q10) 1.4-1.8), the particles alike (0.03-0.7): a larger fixed point below
# min_separability but at least ALIKE_SEPARABILITY on every image, whose segments' spread is at most ALIKE_SPREAD of
# the chosen one's, over at least ALIKE_SEGMENTS segments, wins (EMPS: 4 medians won, none lost;
# experiments/profile/README.md). Of several, the most alike.
ALIKE_SEPARABILITY = 0.55
ALIKE_SPREAD = 0.5
ALIKE_SEGMENTS = 5


class Fixed(NamedTuple):
    """Where `refine_scale` ended."""

    scale: float  # px: the last scale segmented with
    consistent: bool  # its segments' median lies within CONSISTENT of it
    separability: float  # mean over the images
    lowest: float = 0.0  # the least of the images' separabilities
    spread: float = math.nan  # `size_spread` of its segments (not touching the border, of plausible area)
    segments: int = 0  # how many those are


def search_scale(
    prepared: Sequence[Prepared],
    params: SegmentParams,
    log_diameter: float | None,
    weighted: bool = False,
    smallest: float | None = None,
    progress: bool = False,
) -> tuple[Fixed | None, list[tuple[float, float, float]]]:
    """The particle diameter: of the scales that segment into particles of their own size (fixed points of
    `refine_scale`, started from the LoG's diameter (None: no blob stood out) and from 8, 16, .. px up to half the
    image), the one whose foreground separates best from the background (Otsu separability, plus LARGER_BONUS per
    doubling). Grain and noise make fixed points at small scales too, but there the threshold cuts noise
    (separability ~2/pi); at the particles' scale it cuts particles from background. Without a fixed point, the best
    scale reached. A larger fixed point below ``min_separability`` whose segments are far more alike in size wins
    although it separates less (ALIKE_*: a dense packing of textured particles, whose texture separates better than
    their narrow gaps), where ``min_separability`` is the default (a value set by hand is kept).
    ``weighted``: each round moves to the segments' area-weighted median instead of their median (`refine_scale`).
    ``progress``: a bar over the starting diameters.
    Returns (where it ended or None, [(start, scale reached, separability)])."""
    limit = MAX_DIAMETER_SHARE * min(min(p.bright.shape) for p in prepared)
    starts = {d for d in START_DIAMETERS if d <= limit}
    if log_diameter is not None:
        starts.add(round(log_diameter, 1))
    if smallest is not None:  # only from this scale up (`choose_neck`)
        starts = {d for d in starts if d > smallest} | {round(smallest, 2)}
    what = f"particle scale, neck depth {params.neck_depth or 0:g}{', area-weighted' if weighted else ''}"
    bar = tqdm(sorted(starts), desc=what, unit="start", disable=not progress)
    tried = [(start, refine_scale(prepared, params, start, weighted)) for start in bar]

    def best(fixed: list[Fixed]) -> Fixed:
        return max(fixed, key=lambda f: (f.consistent, f.separability + LARGER_BONUS * math.log2(f.scale)))

    found = [f for _, f in tried if f.separability >= params.min_separability and f.scale >= MIN_SCALE]
    record = [(start, f.scale, f.separability) for start, f in tried]
    if not found:
        return None, record
    chosen = best(found)
    if params.min_separability != MIN_SEPARABILITY:
        return chosen, record
    alike = [
        f
        for _, f in tried
        if f.consistent
        and f.scale > chosen.scale
        and f.separability < params.min_separability  # above it the plain rule judged it
        and f.lowest >= ALIKE_SEPARABILITY  # on every image: one image separating nothing lowers nothing
        and f.segments >= ALIKE_SEGMENTS
        and f.spread <= ALIKE_SPREAD * chosen.spread  # NaN (fewer than two segments): never
    ]
    return (min(alike, key=lambda f: f.spread) if alike else chosen), record


def refine_scale(prepared: Sequence[Prepared], params: SegmentParams, scale: float, weighted: bool = False) -> Fixed:
    """Segment with the settings of ``scale``, take the median equivalent diameter of the segments not touching the
    border as the next scale, until it moves less than 10 % (a few rounds). Returns where it ended (`Fixed`): the
    scale returned is the last one segmented with, so that its separability is the one the final segmentation will
    have (the next scale's can fall below ``min_separability`` and leave nothing). The LoG sees a particle's core
    (faceted, textured or rimmed particles respond below their size; rods by their width); the segments see its
    area."""
    for round_ in range(REFINE_ROUNDS):
        resolved = replace(params, min_separability=0.0).resolved(scale)
        measures = [_measure(p, resolved, retry_below=retry_separability(params)) for p in prepared]
        d = np.concatenate([m.diameters for m in measures])
        if d.size == 0:  # nothing of plausible area: this scale segments no particle, however well it separates
            return Fixed(scale, False, 0.0)
        new = area_weighted_median(d) if weighted else float(np.median(d))
        if abs(math.log(new / scale)) < 0.1 or round_ == REFINE_ROUNDS - 1:
            separabilities = [m.separability for m in measures]
            consistent = abs(math.log(new / scale)) < CONSISTENT
            return Fixed(scale, consistent, float(np.mean(separabilities)), min(separabilities), size_spread(d), d.size)
        scale = new
    raise AssertionError("unreachable: the last round returns")


class Measure(NamedTuple):
    """What the scale search needs of one segmentation (`_measure`)."""

    diameters: np.ndarray  # `segment_diameters`
    segments: int  # all watershed segments
    separability: float  # of the threshold


def _measure(prepared: Prepared, params: SegmentParams, retry_below: float | None = None) -> Measure:
    """`_foreground` (``retry_below`` as there) and `split_touching` of ``prepared`` with resolved ``params``,
    measured; each foreground and each split made once per image (memoised on ``prepared.measured``). The
    foreground does not depend on the neck depth, and below ``min_separability`` it is empty (the same threshold
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
        labels = split_touching(foreground & kept, params)
        prepared.measured[key] = Measure(segment_diameters(labels, params), int(labels.max()), separability)
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
    """No particle found; the message says what was tried and which keys to set."""

    def __init__(self, what: str, params: SegmentParams):
        self.what, self.params = what, params
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
    return cut._replace(foreground=_fill_round_holes(keep[components], params))


# A hole at least this convex, and filling at least this share of the disc of its length, is a particle's own darker
# centre, not a gap between several particles (concave, or a square between four: 0.64 of its disc at most)
ROUND_HOLE_SOLIDITY = 0.85
ROUND_HOLE_FILL = 0.7


def _fill_round_holes(foreground: np.ndarray, params: SegmentParams) -> np.ndarray:
    """``foreground`` with its round holes filled: a particle seen as a bright rim around a centre as grey as the
    background (SEM edge effect on spheres, hollow shells) thresholds into a ring, which the watershed would cut into
    arcs of a fraction of its size. A hole is the particle's own centre when it is round (solidity at least
    ROUND_HOLE_SOLIDITY, area at least ROUND_HOLE_FILL of the disc of its major axis) and of plausible area; a gap
    among touching particles is bounded by several convex outlines, so it is concave (an equal-sphere packing's:
    solidity ~0.6) or, smoothed at a large scale, a rounded polygon far from a disc, and stays."""
    holes = ndi.binary_fill_holes(foreground) & ~foreground
    if not holes.any():
        return foreground
    from skimage.measure import regionprops

    labels, _ = ndi.label(holes)
    filled = foreground.copy()
    for region in regionprops(labels):
        disc = math.pi / 4 * region.axis_major_length**2  # the disc of the hole's length: a round hole fills most
        if (
            params.min_area <= region.area <= params.max_area
            and region.solidity >= ROUND_HOLE_SOLIDITY
            and region.area >= ROUND_HOLE_FILL * disc
        ):
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
    if not foreground.any():
        return np.zeros(foreground.shape, np.int32)
    components, _ = ndi.label(foreground)
    distance = ndi.distance_transform_edt(foreground)
    peaks = peak_local_max(distance, min_distance=params.min_distance, labels=components, exclude_border=False)
    seed_mask = np.zeros(foreground.shape, bool)
    seed_mask[tuple(peaks.T)] = True
    if params.seed_depth > 0:
        seed_mask &= h_maxima(distance, params.seed_depth).astype(bool)
    if params.neck_depth > 0:
        seed_mask = _neck_caps(distance, params.neck_depth, seed_mask)
    seeds, _ = ndi.label(seed_mask)  # a flat top (plateau) yields adjacent peaks: one seed, not several
    return watershed(-distance, seeds, mask=foreground).astype(np.int32)


def _neck_caps(distance: np.ndarray, depth: float, peaks: np.ndarray) -> np.ndarray:
    """bool: the caps of the distance transform's domes that stand ``depth`` of their height above the saddle to a
    higher dome (s + 1 <= (1 - depth) (p + 1) for a peak p over a saddle s: the dynamic of log(1 + distance); the
    1 px keeps pixel-high bumps of thin pieces from counting as necks), those holding one of ``peaks``. A cap is the
    dome's top lowered by that depth, so a ridge of equal or nearly equal maxima (a rod) is one cap: one seed, where
    h-maxima would keep each of its equal tops. Every component keeps its top, which stands log(1 + p) above the
    background's 0."""
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
