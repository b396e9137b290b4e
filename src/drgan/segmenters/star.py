"""A star-convex segmenter: each particle as the polygon its centre sees, so that touching particles come apart by
construction (the representation of StarDist, Schmidt et al., MICCAI 2018, for round objects that touch; here in
torch, on drgan's U-Net, with the U-Net's own outline kept).

**Targets** (drgan.segmenters.polygons), from exact instance labels (a generated set's ``labels/``; a real set's components or instance map):
- the object probability: the centre map of drgan.segmenters.instances (per particle its distance transform over its
  own maximum: 1 on the core, 0 where it touches a neighbour), as StarDist's normalised distance;
- per particle pixel and ray k (``n_rays`` directions, evenly spaced), the distance along the ray to the first pixel
  of another label or beyond the crop (`ray_distances`, px, marched in 1-px steps up to ``ray_px``; the boundary is
  put half-way between the last pixel inside and the first outside).

**The network**: the U-Net with 3 class channels (the U-Net's loss: Dice + cross-entropy), one object-probability
logit (binary cross-entropy against the centre map) and ``n_rays`` distance channels (mean absolute error of the
distances over ``ray_px``, each pixel weighted by its centre-map target: the core's rays count most, as in
StarDist), weighted by ``distance_weight``.

**Inference** (drgan.segmenters.inference.split_by_stars, on drgan.segmenters.polygons): candidate centres are the local maxima of the object probability above
``seed_level`` inside the foreground (particle + contour > 0.5); from the most probable down, each candidate's
polygon (its predicted distances along the rays) is kept unless more than ``STAR_NMS`` of it lies in polygons kept
before (non-maximum suppression by overlap), and claims its free pixels. The kept polygons seed a watershed of the
foreground over the negative object probability: the instances are the polygons' (one per particle, whatever the
neck between two), their outlines the U-Net's (pixel-exact where the polygons are coarse). ``seed_level`` is chosen
per checkpoint on the validation pairs (drgan.segmenters.calibrate), as the other segmenters' splits are.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from drgan.core.errors import ConfigError
from drgan.scene.labels import IGNORE
from drgan.segmenters.instances import CentreSegmenterModule
from drgan.segmenters.registry import register_segmenter
from drgan.segmenters.unet import UNet

__all__ = ["StarSegmenterModule"]

SPLIT = "star"  # the module's own split (inference.split: auto picks it)


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
        image, mask, centre, rays = batch
        output = self(image)
        n = self.hparams.n_classes
        logits = output[:, :n]
        ce, dl = self.class_losses(logits, mask)
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
