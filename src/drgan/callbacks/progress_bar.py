"""The training progress bar: Lightning's tqdm bar, except that an epoch the FID callback's KID screen turned
away shows ``val/fid=screened``; and ``StepProgress``, the training steps as a drgan.core.progress task.

Such an epoch logs ``val/fid`` = NaN (drgan.callbacks.fid), so that a checkpoint or early-stopping monitor never
counts it as an improvement; Lightning's bar would print it as ``nan.0``, which reads like a failed evaluation.
"""

from __future__ import annotations

import math

from lightning.pytorch import LightningModule, Trainer
from lightning.pytorch.callbacks import Callback, TQDMProgressBar

from drgan.callbacks.fid import FIDCallback
from drgan.core.progress import Task

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


class StepProgress(Callback):
    """Training steps as a drgan.core.progress task (the console line off a terminal, the pipeline's progress file): its
    total is ``max_epochs`` x the batches of an epoch, a resumed run counting the epochs it had done. ``task``: its
    name in the lines (the GAN's says it may stop earlier: its estimate is an upper bound)."""

    def __init__(self, task: str = "training"):
        self.task_name = task
        self._task: Task | None = None
        self._per_epoch = 0

    def on_train_start(self, trainer: Trainer, pl_module: LightningModule) -> None:
        per_epoch = trainer.num_training_batches
        self._per_epoch = int(per_epoch) if isinstance(per_epoch, (int, float)) and math.isfinite(per_epoch) else 0
        epochs = trainer.max_epochs if trainer.max_epochs not in (None, -1) else None
        total = self._per_epoch * epochs if self._per_epoch and epochs else None
        self._task = Task(self.task_name, total, "steps", start=trainer.current_epoch * self._per_epoch)

    def on_train_batch_end(self, trainer: Trainer, pl_module: LightningModule, outputs, batch, batch_idx: int) -> None:
        if self._task is not None and trainer.is_global_zero:
            self._task.update(trainer.current_epoch * self._per_epoch + batch_idx + 1)

    def on_train_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        if self._task is not None and trainer.is_global_zero:
            self._task.close()
        self._task = None
