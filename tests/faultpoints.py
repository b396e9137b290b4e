"""Kill switches for the fault tests: each SIGKILLs its own process once, at one point of a training run.

A self-inflicted SIGKILL is an external kill at a known point: nothing of Python's shutdown runs (no finally,
no atexit, no logger finalisation). The marker file makes each switch fire once, so the resumed run goes on.
Imported by the training subprocess through PYTHONPATH (the tests folder).
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

from lightning.pytorch import Callback

from drgan.callbacks import RandomProjectionFeatures, ResumeCheckpoint


def kill_once(marker: str) -> None:
    path = Path(marker)
    if path.exists():
        return
    path.write_text(str(os.getpid()))
    os.kill(os.getpid(), signal.SIGKILL)


class KillAtBatch(Callback):
    """Mid-epoch: after batch ``batch`` of epoch ``epoch`` has trained."""

    def __init__(self, epoch: int, batch: int, marker: str):
        self.epoch, self.batch, self.marker = epoch, batch, marker

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if trainer.current_epoch == self.epoch and batch_idx == self.batch:
            kill_once(self.marker)


class ResumeThenKill(ResumeCheckpoint):
    """Right after the epoch's data loop and its last.ckpt write, before FID and the other epoch-end work."""

    def __init__(self, epoch: int, marker: str, **kwargs):
        super().__init__(**kwargs)
        self.kill_epoch, self.marker = epoch, marker

    def on_train_epoch_end(self, trainer, pl_module):
        super().on_train_epoch_end(trainer, pl_module)
        if trainer.current_epoch == self.kill_epoch:
            kill_once(self.marker)


class KillingFeatures(RandomProjectionFeatures):
    """During the FID pass: on the ``call``-th feature extraction (the renders of that pass are done)."""

    def __init__(self, call: int, marker: str, **kwargs):
        super().__init__(**kwargs)
        self.call, self.marker, self.calls = call, marker, 0

    def features(self, images):
        self.calls += 1
        if self.calls == self.call:
            kill_once(self.marker)
        return super().features(images)
