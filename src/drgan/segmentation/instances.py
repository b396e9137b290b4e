"""An instance-aware segmenter: the U-Net's three classes plus a map of where each particle's centre is, learned
from exact instance labels, which separates touching particles by construction.

**The target** (`centre_distance`): inside each particle, the Euclidean distance to the nearest pixel that is not
that particle (the background *or another particle*), divided by the particle's own largest such distance. So it is
1 on every particle's medial core whatever its size, falls to ~0 on its outline, and is 0 on the line where two
particles touch: a neck between touching particles is a valley of the target even where the particle class runs
through it unbroken. (Deep regression of the distance map, Naylor et al., IEEE TMI 2019, here normalised per
particle so that one seed level serves small and large particles alike; an elongated particle's target is a ridge
of 1 along its axis, so a rod stays one seed.) A particle cut by the image border continues beyond it: the border
is no boundary (as in drgan.scene.labels' contour class). drgan's generated pairs carry the exact instances
(``labels/`` of a generated set: every particle, with its true contact line); real annotations give a binary mask's
4-connected components or an instance map's ids.

**The network**: `drgan.segmentation.unet.UNet` with a fourth output channel, the centre map's logit. Loss: the
U-Net's Dice + cross-entropy on the classes, plus ``distance_weight`` x the mean squared error of the sigmoid centre
map, over the pixels whose mask is not IGNORE.

**Inference** (`split_by_centres`): the foreground is where particle and contour probabilities sum over 0.5; the
seeds are the connected pieces of the predicted centre map above ``seed_level`` (inside the foreground); the
foreground is flooded from them over the negative centre map (watershed), and neighbouring regions are separated by a
1-px contour line (`drgan.segmentation.inference.separate_regions`), so that drgan.evaluate and drgan.analyze read its
instances from the class map as they read every segmenter's. ``seed_level`` is chosen per checkpoint on its
validation pairs (drgan.segmentation.calibrate), as the U-Net's split is.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy import ndimage

from drgan.errors import ConfigError, DataError
from drgan.scene.labels import IGNORE, centre_distance
from drgan.segmentation.module import SegmenterModule, contact_pixels, cross_entropy, soft_dice_loss
from drgan.segmentation.registry import register_segmenter
from drgan.segmentation.unet import UNet

__all__ = ["CentreSegmenterModule", "centre_distance", "split_by_centres"]

SPLIT = "centres"  # the module's own split (inference.split: auto picks it)


def split_by_centres(probs: np.ndarray, seed_level: float = 0.5, min_seed_px: int = 2) -> np.ndarray:
    """(4, H, W) probabilities (3 classes, then the centre map) -> (H, W) uint8 class map whose particle class holds
    one 4-connected region per particle (module docstring). Seeds smaller than ``min_seed_px`` pixels are noise."""
    from skimage.segmentation import watershed

    from drgan.segmentation.inference import separate_regions

    probs = np.asarray(probs)
    if probs.ndim != 3 or probs.shape[0] != 4:
        raise DataError(f"split_by_centres: expected (4, H, W) class and centre probabilities, got {probs.shape}")
    check_seed_level(seed_level)
    foreground = probs[1] + probs[2] > 0.5
    centre = probs[3]
    seeds, n = ndimage.label((centre > seed_level) & foreground)
    if n == 0:
        return np.zeros(foreground.shape, np.uint8)
    sizes = np.bincount(seeds.ravel())
    small = sizes < min_seed_px
    small[0] = False
    if small.any():
        seeds[small[seeds]] = 0
    labels = watershed(-centre, seeds, mask=foreground)
    return separate_regions(labels)


def check_seed_level(seed_level) -> float:
    if isinstance(seed_level, bool) or not isinstance(seed_level, (int, float)) or not 0.0 < seed_level < 1.0:
        raise ConfigError(f"inference.seed_level={seed_level!r}: expected a centre-map level in (0, 1)")
    return float(seed_level)


@register_segmenter
class CentreSegmenterModule(SegmenterModule):
    """The U-Net segmenter (its classes, loss and settings) with the centre map of the module docstring:
    distance_weight: weight of the centre map's squared error in the loss (the class losses weigh 1 each)."""

    instance_split = SPLIT
    needs_centres = True  # its training pairs carry centre_distance targets (drgan.segmentation.data)

    def __init__(
        self,
        depth: int = 4,
        base: int = 16,
        n_classes: int = 3,
        lr: float = 1e-3,
        dice_weight: float = 1.0,
        ce_weight: float = 1.0,
        normalize: str = "none",
        contact_weight: float = 0.0,
        contact_reach: int = 3,
        distance_weight: float = 5.0,
    ):
        super().__init__(depth, base, n_classes, lr, dice_weight, ce_weight, normalize, contact_weight, contact_reach)
        if isinstance(distance_weight, bool) or not isinstance(distance_weight, (int, float)) or distance_weight < 0:
            raise ConfigError(f"model.distance_weight={distance_weight!r}: expected a number >= 0")
        self.save_hyperparameters()
        self.net = UNet(1, n_classes + 1, depth, base)  # the classes' logits, then the centre map's

    @staticmethod
    def probabilities(output: torch.Tensor) -> torch.Tensor:
        """Network output (B, 4, H, W) -> class probabilities (softmax of the first three) and the centre map
        (sigmoid of the fourth), (B, 4, H, W)."""
        return torch.cat([output[:, :-1].softmax(dim=1), output[:, -1:].sigmoid()], dim=1)

    def _losses(self, batch):
        image, mask, centre = batch
        output = self(image)
        logits = output[:, :-1]
        weight = None
        if self.hparams.contact_weight > 0:
            weight = 1.0 + self.hparams.contact_weight * contact_pixels(mask, self.hparams.contact_reach).float()
        ce = cross_entropy(logits, mask, weight=weight)
        dl = soft_dice_loss(logits, mask)
        valid = (mask != IGNORE).to(output.dtype)
        squared = (output[:, -1].sigmoid() - centre) ** 2
        distance = (squared * valid).sum() / valid.sum().clamp(min=1.0)
        self._last_distance = distance.detach()
        loss = self.hparams.ce_weight * ce + self.hparams.dice_weight * dl + self.hparams.distance_weight * distance
        return logits, ce, dl, loss

    def training_step(self, batch, batch_idx):
        loss = super().training_step(batch, batch_idx)
        self.log("train/centre_mse", self._last_distance, batch_size=len(batch[0]))
        return loss
