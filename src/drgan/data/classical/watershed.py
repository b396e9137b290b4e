"""Splitting touching particles: the watershed of a distance transform from seeds at its maxima.

One core (`distance_seeds`, `flood`, `distance_watershed`) serves both of drgan's splits: the classical
segmentation's (`split_touching` here: seeds at maxima ``min_distance`` apart, optionally ``seed_depth`` px deep,
kept where they stand at a neck (`_neck_caps`)) and the U-Net's (drgan.segmenters.inference.split_touching: seeds
at the h-maxima of the smoothed distance transform of the particle class's core, flooded over the particle and
contour classes).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import ndimage as ndi
from skimage.feature import peak_local_max
from skimage.morphology import h_maxima
from skimage.segmentation import watershed

from drgan.data.classical.params import SegmentParams


def cluster_h_maxima(distance: np.ndarray, depth: float) -> np.ndarray:
    """bool: skimage's ``h_maxima(distance, depth)`` of a map that is >= 0 (a distance transform), computed cluster
    by cluster: each 8-connected piece of ``distance > 0`` in its bounding box and the 1-px ring of zeros around it
    (what separates it from the others: nothing reaches across a ring of the map's lowest value). The same maxima
    at a fraction of the cost on large images with many particles (the reconstruction sorts every pixel it is given:
    a 1024 x 712 image of 120 particles, 0.7 s at once, 0.08 s by clusters)."""
    distance = np.asarray(distance)
    out = np.zeros(distance.shape, bool)
    clusters, _ = ndi.label(distance > 0, structure=np.ones((3, 3), bool))
    for i, box in enumerate(ndi.find_objects(clusters), start=1):
        if box is None:
            continue
        ring = tuple(slice(max(b.start - 1, 0), min(b.stop + 1, n)) for b, n in zip(box, distance.shape))
        own = clusters[ring] == i
        out[ring] |= h_maxima(np.where(own, distance[ring], 0.0), depth).astype(bool) & own
    return out


def distance_seeds(
    core: np.ndarray,
    *,
    smooth: float = 0.0,
    depth: float = 0.0,
    min_distance: int | None = None,
    components: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(distance, seeds): the Euclidean distance transform of the bool ``core`` (smoothed by a Gaussian of ``smooth``
    px where > 0) and the bool seeds at its maxima: at least ``min_distance`` px apart within each labelled piece of
    ``components`` (None: the whole image) where given, and standing at least ``depth`` px above the saddle to a
    higher maximum (h-maxima) where ``depth`` > 0; at least one of the two rules."""
    if min_distance is None and not depth > 0:
        raise ValueError("distance_seeds: give min_distance, a depth > 0, or both")
    distance = ndi.distance_transform_edt(core)
    if smooth > 0:
        distance = ndi.gaussian_filter(distance, smooth)
    if min_distance is None:
        return distance, cluster_h_maxima(distance, depth)
    peaks = peak_local_max(distance, min_distance=min_distance, labels=components, exclude_border=False)
    seeds = np.zeros(np.shape(core), bool)
    seeds[tuple(peaks.T)] = True
    if depth > 0:
        seeds &= cluster_h_maxima(distance, depth)
    return distance, seeds


def component_seeds(core: np.ndarray, *, smooth: float = 0.0, depth: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(distance, seeds) as `distance_seeds` with ``depth`` (h-maxima), but every 4-connected piece of ``core`` keeps at
    least one seed (at its largest distance) and the smoothed distance is 0 off the core: a piece the network cut off
    from its neighbours by the contour class is one particle, however small or shallow its dome (with the distance
    smoothed across the gap, two small cores 2 px apart share a saddle and h-maxima keeps one of them)."""
    four = ndi.generate_binary_structure(2, 1)
    pieces, n = ndi.label(core, structure=four)
    distance = ndi.distance_transform_edt(core)
    if smooth > 0:
        distance = ndi.gaussian_filter(distance, smooth)
    distance = np.where(core, distance, 0.0)
    seeds = cluster_h_maxima(distance, depth) & np.asarray(core, bool) if depth > 0 else np.zeros(core.shape, bool)
    missing = np.setdiff1d(np.arange(1, n + 1), np.unique(pieces[seeds]))
    for position in ndi.maximum_position(distance, pieces, missing) if len(missing) else []:
        seeds[position] = True
    return distance, seeds


def flood(distance: np.ndarray, seeds: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Labels (0 outside ``mask``): the watershed of ``-distance`` from the connected pieces of the bool ``seeds``
    (a flat top yields adjacent maxima: one seed, not several), restricted to ``mask``; a piece of the mask that
    holds no seed stays 0."""
    markers, _ = ndi.label(seeds)
    return watershed(-distance, markers, mask=mask)


def merge_specks(labels: np.ndarray, min_px: float) -> np.ndarray:
    """``labels`` with every region smaller than ``min_px`` pixels (a speck: drgan.evaluate neither counts nor sizes it)
    given to the larger region it shares the most 8-connected border with, or set to 0 where it touches none: a seed
    that floods only a sliver between particles, or a stray blob, is no particle of its own. Larger regions keep their
    labels; specks merge into them in one pass, never into one another."""
    labels = np.asarray(labels)
    if min_px <= 1 or not labels.any():
        return labels
    areas = np.bincount(labels.ravel())
    small = areas < min_px
    small[0] = False
    if not small.any():
        return labels
    out = labels.copy()
    eight = np.ones((3, 3), bool)
    for k, box in enumerate(ndi.find_objects(labels), start=1):
        if box is None or not small[k]:
            continue
        # the speck's bounding box grown by 1 px: its 8-connected ring lies inside it
        box = tuple(slice(max(s.start - 1, 0), s.stop + 1) for s in box)
        window = labels[box]
        speck = window == k
        ring = window[ndi.binary_dilation(speck, eight) & ~speck]
        ring = ring[(ring > 0) & ~small[ring]]
        out[box][speck] = np.bincount(ring).argmax() if ring.size else 0
    return out


def distance_watershed(core: np.ndarray, mask: np.ndarray, **seeding) -> np.ndarray:
    """`flood` of `distance_seeds` (``core`` and ``seeding`` as there) over ``mask``."""
    distance, seeds = distance_seeds(core, **seeding)
    return flood(distance, seeds, mask)


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
    distance, seed_mask = distance_seeds(
        foreground, depth=params.seed_depth, min_distance=params.min_distance, components=components
    )
    split: dict[float, np.ndarray] = {}
    made: list[tuple[np.ndarray, np.ndarray]] = []
    for depth in depths:
        seeds_at = _neck_caps(distance, depth, seed_mask, components) if depth > 0 else seed_mask
        same = next((labels for seeds, labels in made if np.array_equal(seeds, seeds_at)), None)
        if same is None:
            same = flood(distance, seeds_at, foreground).astype(np.int32)
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
