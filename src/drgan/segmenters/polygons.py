"""Star-convex polygons (StarDist's representation, Schmidt et al., MICCAI 2018): the ray-distance targets of exact
instance labels, and the instances a set of predicted polygons gives (drgan.segmenters.star's segmenter learns them;
drgan.segmenters.inference.split_by_stars turns its outputs into a class map).

``ray_distances``: per particle pixel and ray k (``n_rays`` directions, evenly spaced), the distance along the ray to
the first pixel of another label or beyond the image, marched in 1-px steps up to ``ray_px``, the boundary put
half-way between the last pixel inside and the first outside. ``star_labels``: candidate centres are the local maxima
of the object probability above a seed level inside the foreground; from the most probable down, each candidate's
polygon is kept unless more than ``STAR_NMS`` of it lies in polygons kept before, and claims its free pixels; the kept
polygons seed a watershed of the foreground over the negative object probability.
"""

from __future__ import annotations

import math

import numpy as np

STAR_NMS = 0.4  # a candidate polygon with more than this share of its pixels already claimed is suppressed
PEAK_PX = 2  # candidate centres are local maxima within this radius (px)


def ray_angles(n_rays: int) -> np.ndarray:
    return 2.0 * np.pi * np.arange(n_rays) / n_rays


def ray_distances(labels: np.ndarray, n_rays: int, ray_px: int) -> np.ndarray:
    """(n_rays, H, W) float32: for every pixel of a particle (label > 0), the distance (px) along each ray to the first
    pixel of another label or outside the image, half-way between the last pixel inside and the first outside (at most
    ``ray_px`` - 0.5); 0 off the particles."""
    labels = np.asarray(labels)
    h, w = labels.shape
    out = np.zeros((n_rays, h, w), np.float32)
    ys, xs = np.nonzero(labels > 0)
    if not len(ys):
        return out
    own = labels[ys, xs]
    for k, angle in enumerate(ray_angles(n_rays)):
        dy, dx = math.sin(angle), math.cos(angle)
        distance = np.full(len(ys), float(ray_px) - 0.5, np.float32)
        alive = np.ones(len(ys), bool)
        for step in range(1, int(ray_px) + 1):
            index = np.nonzero(alive)[0]
            if not len(index):
                break
            py = np.rint(ys[index] + step * dy).astype(np.int64)
            px = np.rint(xs[index] + step * dx).astype(np.int64)
            inside = (py >= 0) & (py < h) & (px >= 0) & (px < w)
            same = np.zeros(len(index), bool)
            same[inside] = labels[py[inside], px[inside]] == own[index[inside]]
            left = index[~same]
            distance[left] = step - 0.5
            alive[left] = False
        out[k, ys, xs] = distance
    return out


def polygon_pixels(y: float, x: float, distances: np.ndarray, shape: tuple[int, int]):
    """(rows, cols) of the pixels inside the polygon whose vertices lie ``distances`` px from (y, x) along the rays."""
    from skimage.draw import polygon

    angles = ray_angles(len(distances))
    return polygon(y + distances * np.sin(angles), x + distances * np.cos(angles), shape)


def star_labels(probs: np.ndarray, seed_level: float = 0.5, nms: float = STAR_NMS) -> np.ndarray:
    """(3 + 1 + n_rays, H, W) outputs (class probabilities, object probability, ray distances in px) -> (H, W) int
    instance labels, one per kept polygon (module docstring); ``probs`` checked by the caller."""
    from scipy import ndimage as ndi
    from skimage.feature import peak_local_max
    from skimage.segmentation import watershed

    probs = np.asarray(probs)
    foreground = probs[1] + probs[2] > 0.5
    centre, distances = probs[3], probs[4:]
    shape = foreground.shape
    if not foreground.any():
        return np.zeros(shape, np.int32)
    peaks = peak_local_max(
        np.where(foreground, centre, 0.0), min_distance=PEAK_PX, threshold_abs=seed_level, exclude_border=False
    )
    order = np.argsort(-centre[peaks[:, 0], peaks[:, 1]], kind="stable") if len(peaks) else []
    claimed = np.zeros(shape, np.int32)
    kept = 0
    for y, x in peaks[order]:
        rows, cols = polygon_pixels(float(y), float(x), distances[:, y, x], shape)
        if not len(rows):
            continue
        taken = claimed[rows, cols] > 0
        if taken.mean() > nms:
            continue
        kept += 1
        claimed[rows[~taken], cols[~taken]] = kept
    if not kept:
        return np.zeros(shape, np.int32)
    markers = np.where(foreground, claimed, 0)
    present = np.unique(markers)
    # a polygon that lies off the foreground still seeds its centre pixel
    for index in np.setdiff1d(np.arange(1, kept + 1), present):
        centre_pixel = ndi.center_of_mass(claimed == index)
        y, x = (int(round(v)) for v in centre_pixel)
        if 0 <= y < shape[0] and 0 <= x < shape[1] and foreground[y, x] and markers[y, x] == 0:
            markers[y, x] = index
    return watershed(-centre, markers, mask=foreground).astype(np.int32)
