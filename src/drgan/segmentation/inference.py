"""Sliding-window inference: a full image (e.g. 1024 x 712) -> class probabilities -> class map.

The image is covered by `tile` x `tile` windows at stride tile * (1 - overlap) (the last row/column of
windows is shifted to end at the image border); windows go through the network in batches, and their
softmax probabilities are blended with a Gaussian weight (sigma = tile / 8, peak at the tile centre,
floored at 1e-3 so borders still count) that down-weights tile borders, where the network sees least
context. Images smaller than a tile are reflect-padded to one tile. One tile covering the whole image
gives exactly the network's direct output (the weights cancel).
"""

from __future__ import annotations

import numpy as np
import torch

from drgan.errors import ConfigError, DataError


def gaussian_weight(tile: int, sigma_fraction: float = 0.125) -> torch.Tensor:
    r = torch.arange(tile, dtype=torch.float32) - (tile - 1) / 2
    g = torch.exp(-0.5 * (r / (tile * sigma_fraction)) ** 2)
    w = g[:, None] * g[None, :]
    return (w / w.max()).clamp_min(1e-3)


def _starts(size: int, tile: int, stride: int) -> list[int]:
    starts = list(range(0, size - tile + 1, stride))
    if starts[-1] != size - tile:
        starts.append(size - tile)
    return starts


@torch.no_grad()
def predict_probs(model: torch.nn.Module, image: np.ndarray, tile: int = 384, overlap: float = 0.125,
                  batch_size: int = 8) -> np.ndarray:
    """(H, W) float image in [0, 1] -> (C, H, W) float32 class probabilities."""
    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 2:
        raise DataError(f"predict: expected a 2-D grey image, got shape {image.shape}")
    if not 0.0 <= overlap < 1.0 or tile < 1:
        raise ConfigError(f"predict: need tile >= 1 and overlap in [0, 1), got tile={tile}, overlap={overlap}")
    model.eval()
    h, w = image.shape
    padded = image
    if h < tile or w < tile:
        pad = ((0, max(tile - h, 0)), (0, max(tile - w, 0)))
        padded = np.pad(image, pad, mode="reflect" if h > 1 and w > 1 and tile < 2 * min(h, w) else "edge")
    ph, pw = padded.shape
    stride = max(1, int(round(tile * (1 - overlap))))
    corners = [(y, x) for y in _starts(ph, tile, stride) for x in _starts(pw, tile, stride)]
    weight = gaussian_weight(tile)
    src = torch.from_numpy(padded)
    acc, norm = None, torch.zeros(ph, pw)
    for k in range(0, len(corners), batch_size):
        chunk = corners[k : k + batch_size]
        batch = torch.stack([src[y : y + tile, x : x + tile] for y, x in chunk])[:, None]
        probs = model(batch).softmax(dim=1)
        if acc is None:
            acc = torch.zeros(probs.shape[1], ph, pw)
        for (y, x), p in zip(chunk, probs):
            acc[:, y : y + tile, x : x + tile] += p * weight
            norm[y : y + tile, x : x + tile] += weight
    return (acc / norm)[:, :h, :w].numpy()


def predict(model: torch.nn.Module, image: np.ndarray, **kw) -> np.ndarray:
    """(H, W) image -> (H, W) uint8 class map (0 background, 1 particle, 2 contour)."""
    return predict_probs(model, image, **kw).argmax(axis=0).astype(np.uint8)
