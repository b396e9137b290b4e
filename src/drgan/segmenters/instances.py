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

**The network**: `drgan.segmenters.unet.UNet` with a fourth output channel, the centre map's logit. Loss: the
U-Net's Dice + cross-entropy on the classes, plus ``distance_weight`` x the mean squared error of the sigmoid centre
map, over the pixels whose mask is not IGNORE.

**Inference** (`drgan.segmenters.inference.split_by_centres`): the foreground is where particle and contour probabilities sum over 0.5; the
seeds are the connected pieces of the predicted centre map above ``seed_level`` (inside the foreground); the
foreground is flooded from them over the negative centre map (watershed), and neighbouring regions are separated by a
1-px contour line (`drgan.segmenters.inference.separate_regions`), so that drgan.evaluate and drgan.analyze read its
instances from the class map as they read every segmenter's. ``seed_level`` is chosen per checkpoint on its
validation pairs (drgan.segmenters.calibrate), as the U-Net's split is.
"""

from __future__ import annotations

import torch

from drgan.core.errors import ConfigError
from drgan.scene.labels import IGNORE, centre_distance
from drgan.segmenters.module import SegmenterModule
from drgan.segmenters.registry import register_segmenter
from drgan.segmenters.unet import UNet

__all__ = ["CentreSegmenterModule", "centre_distance"]

SPLIT = "centres"  # the module's own split (inference.split: auto picks it)


@register_segmenter
class CentreSegmenterModule(SegmenterModule):
    """The U-Net segmenter (its classes, loss and settings) with the centre map of the module docstring:
    distance_weight: weight of the centre map's squared error in the loss (the class losses weigh 1 each)."""

    instance_split = SPLIT
    needs_centres = True  # its training pairs carry centre_distance targets (drgan.segmenters.pairs)

    def __init__(self, distance_weight: float = 5.0, **unet):
        super().__init__(**unet)  # the U-Net's keywords (SegmenterModule), all recorded with distance_weight
        if isinstance(distance_weight, bool) or not isinstance(distance_weight, (int, float)) or distance_weight < 0:
            raise ConfigError(f"model.distance_weight={distance_weight!r}: expected a number >= 0")
        self.save_hyperparameters()
        self.net = UNet(1, self.hparams.n_classes + 1, self.hparams.depth, self.hparams.base)  # classes, then centre

    @staticmethod
    def probabilities(output: torch.Tensor) -> torch.Tensor:
        """Network output (B, 4, H, W) -> class probabilities (softmax of the first three) and the centre map
        (sigmoid of the fourth), (B, 4, H, W)."""
        return torch.cat([output[:, :-1].softmax(dim=1), output[:, -1:].sigmoid()], dim=1)

    def _losses(self, batch):
        image, mask, centre = batch
        output = self(image)
        logits = output[:, :-1]
        ce, dl = self.class_losses(logits, mask)
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
