"""Masks from instance labels: background 0, particle 1, contour 2; and the ignore value 255 (``IGNORE``).

The contour class marks the inner rim of each particle, ``contour_px`` pixels wide: a particle pixel is
contour when another label (background or another particle) lies within ``contour_px`` pixels
(Euclidean disk). The rim is taken inside each particle, so a contour never overwrites a neighbour.
The image border does not count as a boundary: a particle cut by the border has no contour there.

``IGNORE`` (255) marks mask pixels that are no class at all: nothing is known about them, so a segmenter's loss
and scores leave them out (cross-entropy's ``ignore_index``, the soft Dice and val/dsc over the other pixels;
drgan.segmentation.module). drgan.generate writes it in the masks of partial backgrounds (real windows with
particles: their particles and a margin around them, drgan.dataset.backgrounds); a renderer's own masks never
hold it. nnU-Net's exports declare it as the label "ignore" (drgan.export_nnunet).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from drgan.errors import ConfigError

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
