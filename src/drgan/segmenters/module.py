"""SegmenterModule: U-Net, loss = soft Dice (mean over classes) + cross-entropy, Adam.

Touching particles: the cross-entropy can weigh the pixels between two particles (the contact line of the contour
class, and narrow background gaps) ``1 + contact_weight`` times (`contact_pixels`): the weight map of Ronneberger et
al. (U-Net, 2015), who weighed the borders between touching cells so the network learns to separate them, here as a
binary map found from the class mask alone (no instance labels needed, so real masks and generated ones alike).

Logged keys: train/loss, train/ce, train/dice_loss, val/loss, val/dsc (particle-class Dice of the argmax
map, over the whole validation batch). Mask pixels of value ``IGNORE`` (255, drgan.scene.labels: the particles of
a partial background) count nowhere: cross-entropy averages over the other pixels (``ignore_index``), the soft
Dice and val/dsc sum over them only; a batch of ignored pixels only has loss 0 and zero gradients, never NaN. Registered as a segmenter (drgan.segmenters.registry), so its checkpoints
load by the ``_target_`` among their hyperparameters; ``load_segmenter`` is the registry's loader.
"""

from __future__ import annotations

import math

import lightning.pytorch as L
import torch
import torch.nn.functional as F

from drgan.core.errors import ConfigError
from drgan.scene.labels import IGNORE
from drgan.segmenters.pairs import check_normalize
from drgan.segmenters.registry import load_segmenter, register_segmenter
from drgan.segmenters.unet import UNet

__all__ = [
    "SegmenterModule",
    "contact_pixels",
    "cross_entropy",
    "load_segmenter",
    "particle_dsc",
    "extent_dice_loss",
    "soft_dice_loss",
]


def soft_dice_loss(
    logits: torch.Tensor, target: torch.Tensor, eps: float = 1.0, ignore_index: int = IGNORE
) -> torch.Tensor:
    """1 - mean over classes of 2|P.T| / (|P| + |T|), P softmax probabilities, sums over batch and the pixels whose
    target is not ``ignore_index`` (all ignored: 0)."""
    probs = logits.softmax(dim=1)
    valid = (target != ignore_index).unsqueeze(1).to(probs.dtype)  # (B, 1, H, W)
    onehot = F.one_hot(torch.where(target == ignore_index, 0, target), logits.shape[1]).permute(0, 3, 1, 2)
    onehot = onehot.to(probs.dtype) * valid
    probs = probs * valid
    inter = (probs * onehot).sum(dim=(0, 2, 3))
    total = probs.sum(dim=(0, 2, 3)) + onehot.sum(dim=(0, 2, 3))
    return 1.0 - ((2 * inter + eps) / (total + eps)).mean()


def extent_dice_loss(
    logits: torch.Tensor, target: torch.Tensor, eps: float = 1.0, ignore_index: int = IGNORE
) -> torch.Tensor:
    """`soft_dice_loss` of the two-class map the instances are cut from: background against the particle's extent
    (particle + contour probabilities; target classes 1 and 2), so that a thin contour class is not a Dice class of
    its own (whose soft Dice rewards a wider predicted rim, partly outside the particle)."""
    probs = logits.softmax(dim=1)
    extent = torch.stack([probs[:, 0], probs[:, 1:].sum(dim=1)], dim=1)
    two = torch.where(target == ignore_index, target, (target > 0).to(target.dtype))
    return soft_dice_loss(extent.clamp_min(1e-12).log(), two, eps, ignore_index)


DICE_MODES = ("classes", "extent")  # SegmenterModule's dice: over the three classes, or over background / extent


def cross_entropy(
    logits: torch.Tensor, target: torch.Tensor, ignore_index: int = IGNORE, weight: torch.Tensor | None = None
) -> torch.Tensor:
    """Mean cross-entropy over the pixels whose target is not ``ignore_index``, each weighted by ``weight`` (B, H, W)
    when given (a weighted mean: sum w ce / sum w); 0 (with zero gradients) when all are ignored, where torch's mean
    would divide 0 by 0."""
    valid = target != ignore_index
    if weight is None:
        total = F.cross_entropy(logits, target, ignore_index=ignore_index, reduction="sum")
        return total / valid.sum().clamp(min=1)
    per_pixel = F.cross_entropy(logits, target, ignore_index=ignore_index, reduction="none")
    weight = weight.to(per_pixel.dtype) * valid
    return (weight * per_pixel).sum() / weight.sum().clamp(min=1e-12)


# Row, column and both diagonals: a pixel lies between two particles when it has particle pixels on both sides along one.
_DIRECTIONS = ((0, 1), (1, 0), (1, 1), (1, -1))


def _shifted(x: torch.Tensor, dy: int, dx: int) -> torch.Tensor:
    """x (B, H, W) moved so that out[y, x] = x[y + dy, x + dx], zero where that falls outside."""
    h, w = x.shape[-2:]
    out = torch.zeros_like(x)
    ys, yd = (slice(dy, h), slice(0, h - dy)) if dy >= 0 else (slice(0, h + dy), slice(-dy, h))
    xs, xd = (slice(dx, w), slice(0, w - dx)) if dx >= 0 else (slice(0, w + dx), slice(-dx, w))
    out[..., yd, xd] = x[..., ys, xs]
    return out


def contact_pixels(target: torch.Tensor, reach: int = 3, ignore_index: int = IGNORE) -> torch.Tensor:
    """bool (B, H, W): the pixels of ``target`` (B, H, W; 0 background, 1 particle, 2 contour) that are not particle
    (nor ignored) and have particle pixels on two opposite sides within ``reach`` px, along a row, a column or a
    diagonal: the contact line between touching particles (contour class) and narrow gaps between close ones, where a
    segmenter merges neighbours. A lone particle's outline has particle on one side only; a concave outline
    (a bean's waist) within ``reach`` counts too."""
    if reach < 1:
        raise ValueError(f"contact_pixels: reach={reach}, expected >= 1 px")
    particle = target == 1
    contact = torch.zeros_like(particle)
    for dy, dx in _DIRECTIONS:
        ahead = torch.zeros_like(particle)
        behind = torch.zeros_like(particle)
        for step in range(1, reach + 1):
            ahead |= _shifted(particle, step * dy, step * dx)
            behind |= _shifted(particle, -step * dy, -step * dx)
        contact |= ahead & behind
    return contact & ~particle & (target != ignore_index)


def particle_dsc(logits: torch.Tensor, target: torch.Tensor, ignore_index: int = IGNORE) -> torch.Tensor:
    """Dice of the particle class (1) between the argmax map and ``target``, over the whole batch and the pixels
    whose target is not ``ignore_index`` (they are neither particle nor not); 1 when neither has a particle pixel."""
    valid = target != ignore_index
    pred, true = (logits.argmax(1) == 1) & valid, target == 1
    denom = pred.sum() + true.sum()
    return (2 * (pred & true).sum() / denom).float() if denom > 0 else torch.tensor(1.0)


@register_segmenter
class SegmenterModule(L.LightningModule):
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
        dice: str = "classes",
        lr_schedule: str = "constant",
    ):
        super().__init__()
        # "none" by default: the synthetic images' grey levels are the real ones, so no normalisation is needed.
        check_normalize(normalize, "model.normalize")
        if not (isinstance(contact_weight, (int, float)) and math.isfinite(contact_weight) and contact_weight >= 0):
            raise ConfigError(f"model.contact_weight={contact_weight!r}: expected a number >= 0 (0: every pixel alike)")
        if isinstance(contact_reach, bool) or not isinstance(contact_reach, int) or contact_reach < 1:
            raise ConfigError(f"model.contact_reach={contact_reach!r}: expected a whole number of px >= 1")
        if dice not in DICE_MODES:
            raise ConfigError(f"model.dice={dice!r}: expected one of {', '.join(DICE_MODES)}")
        if lr_schedule not in LR_SCHEDULES:
            raise ConfigError(f"model.lr_schedule={lr_schedule!r}: expected one of {', '.join(LR_SCHEDULES)}")
        self.save_hyperparameters()
        self.net = UNet(1, n_classes, depth, base)

    @property
    def input_normalization(self) -> str:
        """How `predict_probs` normalises a whole image before tiling it (the training crops saw the same)."""
        return self.hparams.normalize

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)

    @staticmethod
    def probabilities(output: torch.Tensor) -> torch.Tensor:
        """Network output (B, 3, H, W) -> class probabilities (what `predict_probs` blends over tiles)."""
        return output.softmax(dim=1)

    def _losses(self, batch):
        image, mask = batch
        logits = self(image)
        ce, dl = self.class_losses(logits, mask)
        return logits, ce, dl, self.hparams.ce_weight * ce + self.hparams.dice_weight * dl

    def class_losses(self, logits: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(cross-entropy, soft Dice loss) of the class logits: the contact pixels weighted 1 + ``contact_weight``
        times in the cross-entropy, the Dice of ``model.dice``. Every segmenter built on this one shares them."""
        weight = None
        if self.hparams.contact_weight > 0:
            weight = 1.0 + self.hparams.contact_weight * contact_pixels(mask, self.hparams.contact_reach).float()
        return cross_entropy(logits, mask, weight=weight), self.dice_loss(logits, mask)

    def dice_loss(self, logits: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """The soft Dice of ``model.dice``: over the three classes, or over background and the particles' extent."""
        if self.hparams.get("dice", "classes") == "extent":
            return extent_dice_loss(logits, mask)
        return soft_dice_loss(logits, mask)

    def training_step(self, batch, batch_idx):
        _, ce, dl, loss = self._losses(batch)
        self.log_dict(
            {"train/loss": loss, "train/ce": ce, "train/dice_loss": dl}, prog_bar=True, batch_size=len(batch[0])
        )
        return loss

    def validation_step(self, batch, batch_idx):
        logits, _, _, loss = self._losses(batch)
        dsc = particle_dsc(logits, batch[1])
        self.log_dict({"val/loss": loss, "val/dsc": dsc}, prog_bar=True, batch_size=len(batch[0]))

    def configure_optimizers(self):
        """Adam at ``lr``; with ``lr_schedule: poly`` the rate falls each step as (1 - step / steps)^0.9 over the
        run's ``max_epochs`` (`poly_factor`), so the weights the run ends with are settled ones, not those of
        whichever step the last epoch stopped at. Checkpoints from before the setting train at a constant rate."""
        optimizer = torch.optim.Adam(self.parameters(), lr=self.hparams.lr)
        # no trainer (the optimizer built by hand) or max_epochs unbounded (inf): no run length to decay over
        steps = self.trainer.estimated_stepping_batches if self._trainer is not None else math.inf
        if self.hparams.lr_schedule == "constant" or not math.isfinite(steps):
            return optimizer
        schedule = poly_schedule(optimizer, max(int(steps), 1))
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": schedule, "interval": "step"}}


LR_SCHEDULES = ("constant", "poly")
POLY_POWER = 0.9  # nnU-Net's polynomial decay (Isensee et al. 2021)


def poly_factor(step: int, total: int) -> float:
    """The learning rate's factor at optimizer ``step`` of ``total``: (1 - step / total)^POLY_POWER, 0 from the end."""
    return max(1.0 - step / total, 0.0) ** POLY_POWER


def poly_schedule(optimizer: torch.optim.Optimizer, total: int) -> torch.optim.lr_scheduler.LambdaLR:
    """``optimizer``'s rate times `poly_factor` of its step over ``total`` steps (stepped once per optimizer step)."""
    return torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: poly_factor(step, total))


SETTLE_EPOCHS, SETTLE_GAIN = 3, 0.01  # settled: the last 3 epochs raised the best val/dsc by less than 0.01


class ScoreHistory(L.Callback):
    """val/dsc of every validation epoch, saved in checkpoints (a resumed run knows its whole history)."""

    def __init__(self):
        self.history: list[float] = []

    def on_validation_epoch_end(self, trainer, pl_module) -> None:
        value = trainer.callback_metrics.get("val/dsc")
        if value is not None and not trainer.sanity_checking:
            self.history.append(float(value))

    def state_dict(self) -> dict:
        return {"history": list(self.history)}

    def load_state_dict(self, state_dict: dict) -> None:
        self.history = [float(v) for v in state_dict.get("history", [])]


class CheckpointEntries(L.Callback):
    """Writes ``entries`` (key -> value; None values are left out) into every checkpoint the run saves, last.ckpt and
    the epoch files: what inference needs of the training pairs, read back by load_segmenter. drgan.segment stores
    the pairs' pixel scale (drgan.segmenters.calibrate.PIXEL_SCALE_KEY: inference resamples real images by it),
    their area-weighted median particle diameter (WORKING_DIAMETER_KEY: inference's per-image scale aims at it) and their
    fine-noise level (drgan.segmenters.noise_match.NOISE_KEY: inference brings cleaner images up to it)."""

    def __init__(self, entries: dict):
        self.entries = {key: value for key, value in entries.items() if value is not None}

    def on_save_checkpoint(self, trainer, pl_module, checkpoint: dict) -> None:
        checkpoint.update(self.entries)


def settled(history: list[float]) -> tuple[bool, str]:
    """(whether the validation score had settled when training stopped, why): the best val/dsc of the last
    SETTLE_EPOCHS epochs is less than SETTLE_GAIN above the best before them."""
    if len(history) <= SETTLE_EPOCHS:
        return False, f"only {len(history)} validation epoch(s)"
    before, last = max(history[:-SETTLE_EPOCHS]), max(history[-SETTLE_EPOCHS:])
    if last - before >= SETTLE_GAIN:
        return False, f"val/dsc still rose from {before:.3f} to {last:.3f} over the last {SETTLE_EPOCHS} epochs"
    return True, f"val/dsc gained {last - before:+.3f} over the last {SETTLE_EPOCHS} epochs"
