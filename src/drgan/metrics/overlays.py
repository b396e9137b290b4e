"""Pictures of a segmentation against its truth: one image's overlay (`overlay`: found particles matched to a true
one green, false ones red, true ones nothing covers yellow) and a contact sheet of several (`sheet`), as
drgan.evaluate writes for real test images and drgan.segment for its closed-loop check's generated pairs."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from drgan.metrics.instance_scores import match_instances

GREEN, RED, YELLOW = (0, 200, 0), (230, 0, 0), (255, 220, 0)


def overlay(image: np.ndarray, pred_labels: np.ndarray, true_labels: np.ndarray, alpha: float = 0.5) -> np.ndarray:
    """(H, W, 3) uint8: grey image with matched predicted instances green, unmatched predictions red and
    unmatched true instances yellow (where no prediction covers them), blended with weight alpha."""
    m = match_instances(pred_labels, true_labels, 0.5)
    grey = np.round(np.clip(image, 0, 1) * 255.0)
    rgb = np.repeat(grey[..., None], 3, axis=2)
    tp_pred = np.isin(pred_labels, [p for p, _ in m.pairs])
    fp = np.isin(pred_labels, m.unmatched_pred)
    fn = np.isin(true_labels, m.unmatched_true) & (pred_labels == 0)
    for where, colour in ((fn, YELLOW), (fp, RED), (tp_pred, GREEN)):
        rgb[where] = (1 - alpha) * rgb[where] + alpha * np.array(colour, dtype=np.float64)
    return np.round(rgb).astype(np.uint8)


def sheet(tiles: Sequence[np.ndarray], columns: int = 6, gap: int = 4) -> np.ndarray:
    """(H, W, 3) uint8: RGB ``tiles`` in rows of ``columns``, each in a cell of the largest tile's size (top-left
    aligned), ``gap`` white pixels between cells."""
    if not tiles:
        raise ValueError("sheet: no tiles")
    height = max(t.shape[0] for t in tiles)
    width = max(t.shape[1] for t in tiles)
    columns = min(columns, len(tiles))
    rows = -(-len(tiles) // columns)
    out = np.full((rows * height + (rows - 1) * gap, columns * width + (columns - 1) * gap, 3), 255, np.uint8)
    for k, tile in enumerate(tiles):
        top, left = (k // columns) * (height + gap), (k % columns) * (width + gap)
        out[top : top + tile.shape[0], left : left + tile.shape[1]] = tile
    return out
