"""Masks from instance labels: background 0, particle 1, contour 2; and the ignore value 255 (``IGNORE``).

The contour class marks the inner rim of each particle, ``contour_px`` pixels wide: a particle pixel is
contour when another label (background or another particle) lies within ``contour_px`` pixels
(Euclidean disk). The rim is taken inside each particle, so a contour never overwrites a neighbour.
The image border does not count as a boundary: a particle cut by the border has no contour there.

``IGNORE`` (255) marks mask pixels that are no class at all: nothing is known about them, so a segmenter's loss
and scores leave them out (cross-entropy's ``ignore_index``, the soft Dice and val/dsc over the other pixels;
drgan.segmenters.module). drgan.generate writes it in the masks of partial backgrounds (real windows with
particles: their particles and a margin around them, drgan.synthetic.backgrounds); a renderer's own masks never
hold it. nnU-Net's exports declare it as the label "ignore" (drgan.export_nnunet).

``centre_distance``: the target of the instance-aware segmenter (drgan.segmenters.instances), per particle its
distance transform over its own maximum: 1 on its core, 0 where it touches a neighbour.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from drgan.core.errors import ConfigError

BACKGROUND, PARTICLE, CONTOUR = 0, 1, 2
IGNORE = 255  # a mask pixel of no class: left out of the loss and the scores


def disk(radius: int) -> np.ndarray:
    r = int(radius)
    y, x = np.mgrid[-r : r + 1, -r : r + 1]
    return (x * x + y * y) <= r * r


def class_mask(labels: np.ndarray, contour_px: int) -> np.ndarray:
    """(H, W) instance ids -> (H, W) uint8 classes {0, 1, 2}."""
    labels = np.asarray(labels)
    if labels.ndim != 2:
        raise ConfigError(f"labels: expected a 2-D instance label image, got shape {labels.shape}")
    if isinstance(contour_px, bool) or int(contour_px) != contour_px or contour_px < 0:
        raise ConfigError(f"contour_px={contour_px!r}: expected an integer >= 0")
    mask = np.where(labels > 0, PARTICLE, BACKGROUND).astype(np.uint8)
    if contour_px == 0:
        return mask
    footprint = disk(contour_px)
    # Labels differ somewhere in the disk iff the disk's max or min differs from the centre pixel.
    highest = ndimage.maximum_filter(labels, footprint=footprint, mode="nearest")
    lowest = ndimage.minimum_filter(labels, footprint=footprint, mode="nearest")
    mask[(labels > 0) & ((highest != labels) | (lowest != labels))] = CONTOUR
    return mask


def centre_distance(labels: np.ndarray) -> np.ndarray:
    """(H, W) instance ids (0 background) -> float32 (H, W): per particle, its distance transform (to the nearest
    pixel of any other id, background or particle) over the particle's own maximum; 0 outside particles. A particle
    cut by the image border is extended beyond it (edge padding), so the border is not its boundary."""
    labels = np.asarray(labels)
    if labels.ndim != 2:
        raise ConfigError(f"centre_distance: expected a 2-D instance label image, got shape {labels.shape}")
    out = np.zeros(labels.shape, np.float32)
    h, w = labels.shape
    for index, box in enumerate(ndimage.find_objects(labels.astype(np.int64, copy=False)), start=1):
        if box is None:
            continue
        # the box grown by one pixel, clipped to the image; what lies past the image border repeats the edge
        y0, y1 = max(box[0].start - 1, 0), min(box[0].stop + 1, h)
        x0, x1 = max(box[1].start - 1, 0), min(box[1].stop + 1, w)
        inside = labels[y0:y1, x0:x1] == index
        pad = ((1, 1), (1, 1))
        grown = np.pad(inside, pad, mode="edge")
        # a pad row or column outside the image repeats it (the particle goes on); inside the image it is outside
        if y0 > 0:
            grown[0] = False
        if y1 < h:
            grown[-1] = False
        if x0 > 0:
            grown[:, 0] = False
        if x1 < w:
            grown[:, -1] = False
        distance = ndimage.distance_transform_edt(grown)[1:-1, 1:-1] * inside
        peak = distance.max()
        if peak > 0:
            region = out[y0:y1, x0:x1]
            region[inside] = (distance[inside] / peak).astype(np.float32)
    return out
