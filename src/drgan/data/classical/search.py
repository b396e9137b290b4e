"""The particle diameter and the watershed's neck depth, searched together (`resolve_params`, `search_scale`).

The particle diameter is a scale whose own segmentation (smoothing, seed distance and area limits set from it) gives
segments of that size: a fixed point of s -> median diameter of the segments. Textured images have several (grain
specks, particles, agglomerates), and which one a walk along the map from a given start reaches moves with any small
change of the foreground. So the map is segmented on a grid of scales (`scale_grid`), every fixed point on it is found
(`fixed_points`), and they are judged by what makes a segmentation trustworthy in scale space: a structure that
persists. Particles segment to the same size over a wide range of settings (their median holds from a fraction of
their size to several times it: the basin), specks and texture follow the smoothing and hold over a step or two;
and particles are alike in size, specks come in every size (the size spread). The one whose size holds over the
most scales, less its segments' spread in size, is chosen (`Fixed.evidence`). Where no scale agrees with its
segments, a size they keep over an octave of smoothing is the particles' (`_plateau`: small particles on a noisy
film).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from typing import NamedTuple

import numpy as np

from drgan.core.progress import track
from drgan.data.classical.calibration import CALIBRATION as CAL
from drgan.data.classical.foreground import Prepared, cut_foreground, prepare, retry_separability
from drgan.data.classical.params import NoParticles, SegmentParams
from drgan.data.classical.scale import Fixed, Point, ScaleEstimate, estimate_scale
from drgan.data.classical.watershed import split_by_depth


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
        f"particle size: {why}; nor did the segments keep one size over {CAL.plateau_scales} scales where they separate"
        f" enough; {polarity} particles"
    )


def scale_grid(shape: tuple[int, int]) -> np.ndarray:
    """The scales searched: CAL.min_scale up to half the shorter side, CAL.scale_step apart (at least CAL.min_scale)."""
    top = CAL.max_diameter_share * min(shape)
    n = max(1, int(math.floor(math.log(max(top, CAL.min_scale) / CAL.min_scale) / math.log(CAL.scale_step) + 1e-9)) + 1)
    return CAL.min_scale * CAL.scale_step ** np.arange(n)


def search_scale(
    prepared: Sequence[Prepared], params: SegmentParams, progress: bool = False
) -> tuple[Fixed | None, list[Fixed], list[Point]]:
    """The particle diameter and the neck depth (where not given): every image segmented at each scale of
    `scale_grid` with each neck depth (0: every maximum seeds, CAL.neck_depth: seeds at necks only; `split_touching`),
    and where the grid steps over a fixed point or ends below one, there too (`_between_and_above`); the fixed
    points of each depth's map found (`fixed_points`), and of those separating at least ``min_separability`` (or
    alike, CAL.alike_*) the one with the most `Fixed.evidence`: the widest basin, less the size spread; seeds at necks
    only where they make the sizes more alike (`_plain_unless_more_alike`). The chosen one is refined to its
    segments' own median (`refine`). Where no fixed point is a candidate, the same on the segments' area-weighted
    median (specks outnumbering a few particles pull the plain median below the particles' size at every scale;
    their share of the area is small); where none is either, a size the segments keep over an octave of scales that
    separate (`_plateau`). A scale given is the grid (its depth chosen the same way, agreement not required).
    Returns (the chosen or None, every fixed point found, every grid point)."""
    depths = (0.0, CAL.neck_depth) if params.neck_depth is None else (float(params.neck_depth),)
    given = params.scale is not None
    shape = min((p.bright.shape for p in prepared), key=min)
    scales = [float(params.scale)] if given else scale_grid(shape)
    bar = track(scales, "particle scale search", unit="scales") if progress else scales
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


def _plateau(row: Sequence[Point], params: SegmentParams) -> Fixed | None:
    """Where no fixed point is a candidate: the longest run of at least CAL.plateau_scales consecutive scales of
    ``row`` (one depth, in order of scale) that all separate at least ``min_separability`` and whose segments' medians
    lie within twice CAL.consistent of each other (in log), at its smallest scale; None where there is none. Particles
    a few px across on a noisy film separate only when smoothed more than their own scale asks: at their own scale
    the noise's specks join them and nothing separates, and from about twice it they come out at their size, whatever the smoothing, for an octave and more. Noise and grain have no such run:
    their specks grow with the smoothing."""
    best: tuple[int, int] | None = None
    for start in range(len(row)):
        end, low, high = start, math.inf, -math.inf
        while end < len(row) and math.isfinite(row[end].median) and row[end].separability >= params.min_separability:
            low, high = min(low, row[end].median), max(high, row[end].median)
            if math.log(high / low) >= 2 * CAL.consistent:
                break
            end += 1
        if end - start >= CAL.plateau_scales and (best is None or end - start > best[1] - best[0]):
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
    its scale (size spread at most CAL.neck_spread of that), else the plain segmentation: its best candidate within
    CAL.neck_near of ``best``'s scale, or where it has none, itself at ``best``'s scale where its segments come within
    twice CAL.consistent of that scale. Seeds at necks make a segmentation persist over scales by themselves (fewer
    seeds, whatever the scale), so persistence cannot choose them over the plain seeds: merging touching particles
    at shallow necks needs the sizes to say so (rods and irregular particles cut along their ridges come out in every
    length; touching particles merged come out as singles, pairs and triples). Twice CAL.consistent: where
    annotators split agglomerates at shallow necks, the plain map may come near its scale without agreeing with it."""

    near = [c for c in candidates if c.depth == 0.0 and abs(math.log(c.scale / best.scale)) <= CAL.neck_near]
    if near:
        plain = max(near, key=lambda f: (f.evidence, f.separability))
    else:
        row = [p for p in points if p.depth == 0.0]
        at = min(row, key=lambda p: abs(math.log(p.scale / best.scale)))
        size = at.size(weighted)
        if not (math.isfinite(size) and abs(math.log(size / at.scale)) < 2 * CAL.consistent):
            return best
        plain = _candidate(_as_fixed(at, size, _basin(row, size, weighted)), params, alike_spread)
        if plain is None:
            return best
    return best if _more_alike(best, plain) else plain


def _more_alike(deep: Fixed, plain: Fixed) -> bool:
    """Whether ``deep``'s segments spread in size less than CAL.neck_spread of ``plain``'s (unknown: CAL.spread_unknown)."""

    def spread(f: Fixed) -> float:
        return CAL.spread_unknown if math.isnan(f.spread) else f.spread

    return spread(deep) < CAL.neck_spread * spread(plain)


def _between_and_above(prepared, params: SegmentParams, points: list[Point], side: int) -> list[Point]:
    """The scales the grid steps over: where the segments of one grid scale are larger than it and those of the next
    smaller (beyond CAL.consistent both), a fixed point lies between, and the scale where the map crosses its diagonal
    (interpolated in log scale) is segmented too; where the top scale's segments are still larger than it, the map
    is followed up from there (its segments' median, CAL.refine_rounds at most, up to the image's shorter side)."""
    extra = []
    for depth in sorted({p.depth for p in points}):
        row = [p for p in points if p.depth == depth]
        g = [math.log(p.median / p.scale) if math.isfinite(p.median) else math.nan for p in row]
        for a, b, ga, gb in zip(row, row[1:], g, g[1:]):
            if ga >= CAL.consistent and gb <= -CAL.consistent:
                t = ga / (ga - gb)
                extra.append(_point(prepared, params, a.scale ** (1 - t) * b.scale**t, depth))
        top = row[-1]
        for _ in range(CAL.refine_rounds):
            if not (
                math.isfinite(top.median) and top.median >= top.scale * math.exp(CAL.consistent) and top.median < side
            ):
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
    segment to within CAL.consistent of its size."""
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
    """How many of ``points`` segment to within CAL.consistent of ``size``."""
    sizes = np.array([p.size(weighted) for p in points])
    with np.errstate(invalid="ignore"):
        return int(np.sum(np.abs(np.log(sizes / size)) < CAL.consistent))


def _alike_spread(plain: Sequence[Fixed]) -> float:
    """The size spread below which a fixed point under min_separability is alike: CAL.alike_spread, or CAL.alike_share of
    the spread of the one of ``plain`` (fixed points separating min_separability) the search would choose, where
    that is more."""
    if not plain:
        return CAL.alike_spread
    chosen = max(plain, key=lambda f: (f.evidence, f.separability))
    return max(CAL.alike_spread, CAL.alike_share * (CAL.spread_unknown if math.isnan(chosen.spread) else chosen.spread))


def _candidate(f: Fixed, params: SegmentParams, alike_spread: float) -> Fixed | None:
    """``f`` where it may be chosen: separating at least min_separability, or alike (CAL.alike_*; spread at most
    ``alike_spread``, `_alike_spread`) where that is the default; None otherwise."""
    if f.separability >= params.min_separability:
        return f
    alike = (
        params.min_separability == CAL.min_separability
        and f.lowest >= CAL.alike_separability  # on every image: one image separating nothing lowers nothing
        and f.segments >= CAL.alike_segments
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
    """``f`` moved to its segments' own (area-weighted) median while that lies CAL.refine_until (in log) or more
    from its scale (CAL.refine_rounds at most), as long as the segmentation there still agrees with its scale, is
    still a candidate and still segments to within CAL.consistent of ``f``'s size; else where it last did. The scale returned is one segmented
    with, so that the final segmentation separates as the search saw it. ``alike_spread``: the search's
    (`_alike_spread`)."""
    current = f
    for _ in range(CAL.refine_rounds):
        if abs(math.log(current.median / current.scale)) < CAL.refine_until:
            break
        point = _point(prepared, params, current.median, f.depth)
        size = point.size(weighted)
        if not point.agrees(weighted) or abs(math.log(size / f.median)) >= CAL.consistent:
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
    """`cut_foreground` (``retry_below`` as there) and `split_touching` of ``prepared`` with resolved ``params``,
    measured; each foreground and each split made once per image (memoised on ``prepared.measured``; both neck
    depths split at once). The foreground does not depend on the neck depth, and below ``min_separability`` it is empty (the same threshold
    otherwise), so the searches with either depth and either separability share it."""
    retry = retry_separability(params) if retry_below is None else retry_below
    plain = replace(params, min_separability=0.0)
    cut_key = (replace(plain, neck_depth=None), retry)
    if cut_key not in prepared.measured:
        cut = cut_foreground(prepared, cut_key[0], retry_below=retry)
        prepared.measured[cut_key] = (np.packbits(cut.foreground), cut.separability)
    packed, separability = prepared.measured[cut_key]
    kept = separability >= params.min_separability
    key = (plain, retry, kept)
    if key not in prepared.measured:
        shape = prepared.bright.shape
        foreground = np.unpackbits(packed, count=shape[0] * shape[1]).reshape(shape).astype(bool)
        # the search asks both depths at each scale: split with both at once (`split_by_depth`)
        depths = {plain.neck_depth, *((0.0, CAL.neck_depth) if plain.neck_depth in (0.0, CAL.neck_depth) else ())}
        for depth, labels in split_by_depth(foreground & kept, plain, sorted(depths)).items():
            at = (replace(plain, neck_depth=depth), retry, kept)
            prepared.measured[at] = Measure(segment_diameters(labels, params), int(labels.max()), separability)
    return prepared.measured[key]


def size_spread(diameters: np.ndarray) -> float:
    """log(q90 / q10) of the diameters: how unlike the segments are in size (NaN for fewer than two)."""
    if diameters.size < 2:
        return math.nan
    low, high = np.quantile(diameters, [0.1, 0.9])
    return float(math.log(high / low))


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
