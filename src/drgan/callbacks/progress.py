"""The training progress bar: Lightning's tqdm bar, except that an epoch the FID callback's KID screen turned
away shows ``val/fid=screened``.

Such an epoch logs ``val/fid`` = NaN (drgan.callbacks.fid), so that a checkpoint or early-stopping monitor never
counts it as an improvement; Lightning's bar would print it as ``nan.0``, which reads like a failed evaluation.
"""

from __future__ import annotations

import math

from lightning.pytorch import LightningModule, Trainer
from lightning.pytorch.callbacks import TQDMProgressBar

from drgan.callbacks.fid import FIDCallback

SCREENED = "screened"


def screened_out(trainer: Trainer) -> bool:
    """Whether the FID callback's latest evaluation was screened out by KID (no full FID)."""
    fid_callback = next((c for c in trainer.callbacks if isinstance(c, FIDCallback)), None)
    if fid_callback is None or not fid_callback.history:
        return False
    latest = fid_callback.history[-1]
    return latest.get("screen_kid") is not None and not math.isfinite(latest["fid"])


class TrainingProgressBar(TQDMProgressBar):
    """``TQDMProgressBar`` (same arguments) whose ``val/fid`` reads "screened" for an epoch the KID screen skipped."""

    def get_metrics(self, trainer: Trainer, pl_module: LightningModule) -> dict:
        metrics = super().get_metrics(trainer, pl_module)
        fid = metrics.get("val/fid")
        if isinstance(fid, float) and math.isnan(fid) and screened_out(trainer):
            metrics["val/fid"] = SCREENED
        return metrics
