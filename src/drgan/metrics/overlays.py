"""Pictures of a segmentation against its truth: one image's overlay (`overlay`: found particles matched to a true
one green, false ones red, true ones nothing covers yellow) and a contact sheet of several (`sheet`, each captioned
with its image's id), as
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


CAPTION_PX = 12  # the strip above a captioned tile


def sheet(
    tiles: Sequence[np.ndarray], columns: int = 6, gap: int = 4, captions: Sequence[str] | None = None
) -> np.ndarray:
    """(H, W, 3) uint8: RGB ``tiles`` in rows of ``columns``, each in a cell of the largest tile's size (top-left
    aligned), ``gap`` white pixels between cells; with ``captions`` (one per tile, e.g. the image's id) each cell has a
    CAPTION_PX-high white strip above its tile with the caption in black, clipped to the cell's width."""
    if not tiles:
        raise ValueError("sheet: no tiles")
    if captions is not None and len(captions) != len(tiles):
        raise ValueError(f"sheet: {len(captions)} captions for {len(tiles)} tiles")
    strip = CAPTION_PX if captions is not None else 0
    height = max(t.shape[0] for t in tiles) + strip
    width = max(t.shape[1] for t in tiles)
    columns = min(columns, len(tiles))
    rows = -(-len(tiles) // columns)
    out = np.full((rows * height + (rows - 1) * gap, columns * width + (columns - 1) * gap, 3), 255, np.uint8)
    for k, tile in enumerate(tiles):
        top, left = (k // columns) * (height + gap), (k % columns) * (width + gap)
        out[top + strip : top + strip + tile.shape[0], left : left + tile.shape[1]] = tile
        if captions is not None:
            out[top : top + strip, left : left + width] = _caption(str(captions[k]), width, strip)
    return out


def _caption(text: str, width: int, height: int) -> np.ndarray:
    """(height, width, 3) uint8: ``text`` in black on white, from the left edge, cut at ``width``."""
    from PIL import Image, ImageDraw, ImageFont

    strip = Image.new("RGB", (width, height), (255, 255, 255))
    ImageDraw.Draw(strip).text((1, 0), text, fill=(0, 0, 0), font=ImageFont.load_default(size=height - 2))
    return np.asarray(strip)
