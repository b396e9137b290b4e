"""A star-convex segmenter: each particle as the polygon its centre sees, so that touching particles come apart by
construction (the representation of StarDist, Schmidt et al., MICCAI 2018, for round objects that touch; here in
torch, on drgan's U-Net, with the U-Net's own outline kept).

**Targets**, from exact instance labels (a generated set's ``labels/``; a real set's components or instance map):
- the object probability: the centre map of drgan.segmenters.instances (per particle its distance transform over its
  own maximum: 1 on the core, 0 where it touches a neighbour), as StarDist's normalised distance;
- per particle pixel and ray k (``n_rays`` directions, evenly spaced), the distance along the ray to the first pixel
  of another label or beyond the crop (`ray_distances`, px, marched in 1-px steps up to ``ray_px``; the boundary is
  put half-way between the last pixel inside and the first outside).

**The network**: the U-Net with 3 class channels (the U-Net's loss: Dice + cross-entropy), one object-probability
logit (binary cross-entropy against the centre map) and ``n_rays`` distance channels (mean absolute error of the
distances over ``ray_px``, each pixel weighted by its centre-map target: the core's rays count most, as in
StarDist), weighted by ``distance_weight``.

**Inference** (`split_by_stars`): candidate centres are the local maxima of the object probability above
``seed_level`` inside the foreground (particle + contour > 0.5); from the most probable down, each candidate's
polygon (its predicted distances along the rays) is kept unless more than ``STAR_NMS`` of it lies in polygons kept
before (non-maximum suppression by overlap), and claims its free pixels. The kept polygons seed a watershed of the
foreground over the negative object probability: the instances are the polygons' (one per particle, whatever the
neck between two), their outlines the U-Net's (pixel-exact where the polygons are coarse). ``seed_level`` is chosen
per checkpoint on the validation pairs (drgan.segmenters.calibrate), as the other segmenters' splits are.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from drgan.errors import ConfigError
from drgan.scene.labels import IGNORE
from drgan.segmenters.instances import CentreSegmenterModule
from drgan.segmenters.registry import register_segmenter
from drgan.segmenters.unet import UNet

__all__ = ["StarSegmenterModule", "ray_distances", "split_by_stars"]

SPLIT = "star"  # the module's own split (inference.split: auto picks it)
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


def split_by_stars(probs: np.ndarray, seed_level: float = 0.5, nms: float = STAR_NMS) -> np.ndarray:
    """(3 + 1 + n_rays, H, W) probabilities (classes, object probability, ray distances in px) -> (H, W) uint8 class map
    with one 4-connected particle region per kept polygon (module docstring)."""
    from scipy import ndimage as ndi
    from skimage.feature import peak_local_max
    from skimage.segmentation import watershed

    from drgan.segmenters.inference import check_seed_level, separate_regions

    probs = np.asarray(probs)
    if probs.ndim != 3 or probs.shape[0] < 6:
        raise ConfigError(f"split_by_stars: expected (3 + 1 + rays, H, W) outputs, got shape {probs.shape}")
    check_seed_level(seed_level)
    foreground = probs[1] + probs[2] > 0.5
    centre, distances = probs[3], probs[4:]
    shape = foreground.shape
    if not foreground.any():
        return np.zeros(shape, np.uint8)
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
        return np.zeros(shape, np.uint8)
    markers = np.where(foreground, claimed, 0)
    present = np.unique(markers)
    # a polygon that lies off the foreground still seeds its centre pixel
    for index in np.setdiff1d(np.arange(1, kept + 1), present):
        ys, xs = np.nonzero(claimed == index)
        centre_pixel = ndi.center_of_mass(claimed == index)
        y, x = (int(round(v)) for v in centre_pixel)
        if 0 <= y < shape[0] and 0 <= x < shape[1] and foreground[y, x] and markers[y, x] == 0:
            markers[y, x] = index
    labels = watershed(-centre, markers, mask=foreground)
    return separate_regions(labels)


@register_segmenter
class StarSegmenterModule(CentreSegmenterModule):
    """The instance-aware segmenter's classes and centre map plus ``n_rays`` ray distances (module docstring):
    ``ray_px`` the longest ray (px at the network's scale; also the distances' unit in the loss)."""

    instance_split = SPLIT
    needs_centres = True

    def __init__(self, n_rays: int = 16, ray_px: int = 64, **centres):
        super().__init__(**centres)
        for key, value, low in (("n_rays", n_rays, 3), ("ray_px", ray_px, 2)):
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ConfigError(f"model.{key}={value!r}: expected a whole number >= {low}")
        self.save_hyperparameters()
        self.net = UNet(1, self.hparams.n_classes + 1 + n_rays, self.hparams.depth, self.hparams.base)

    @property
    def rays(self) -> int:
        """Ray distances its training crops carry (drgan.segmenters.pairs.CropDataset): ``n_rays``."""
        return int(self.hparams.n_rays)

    def probabilities(self, output: torch.Tensor) -> torch.Tensor:
        """(B, 3 + 1 + rays, H, W): class probabilities, the object probability and the ray distances in px."""
        n = self.hparams.n_classes
        distances = F.relu(output[:, n + 1 :]) * float(self.hparams.ray_px)
        return torch.cat([output[:, :n].softmax(dim=1), output[:, n : n + 1].sigmoid(), distances], dim=1)

    def _losses(self, batch):
        from drgan.segmenters.module import contact_pixels, cross_entropy

        image, mask, centre, rays = batch
        output = self(image)
        n = self.hparams.n_classes
        logits = output[:, :n]
        weight = None
        if self.hparams.contact_weight > 0:
            weight = 1.0 + self.hparams.contact_weight * contact_pixels(mask, self.hparams.contact_reach).float()
        ce = cross_entropy(logits, mask, weight=weight)
        dl = self.dice_loss(logits, mask)
        valid = (mask != IGNORE).to(output.dtype)
        probability = F.binary_cross_entropy_with_logits(output[:, n], centre, reduction="none")
        probability = (probability * valid).sum() / valid.sum().clamp(min=1.0)
        weight_rays = (centre * valid)[:, None]
        error = (F.relu(output[:, n + 1 :]) - rays / float(self.hparams.ray_px)).abs()
        ray_loss = (error * weight_rays).sum() / (weight_rays.sum() * rays.shape[1]).clamp(min=1e-6)
        self._last_distance = (probability + ray_loss).detach()
        loss = (
            self.hparams.ce_weight * ce
            + self.hparams.dice_weight * dl
            + self.hparams.distance_weight * (probability + ray_loss)
        )
        return logits, ce, dl, loss
