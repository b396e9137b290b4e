"""``last.ckpt`` that a killed run resumes from, losing at most the epoch in progress.

Lightning's ``ModelCheckpoint(save_last=True)`` rewrites ``last.ckpt`` only in epochs where it also saves a
top-k file, and only after every other epoch-end callback (FID, best epoch, plots: minutes at real sizes).
A run killed in between restarted from an older epoch or from scratch. This callback owns ``last.ckpt``:

1. At every epoch end, *before* the other epoch-end callbacks (it must come first in the callback list; see
   conf/gan/callbacks/default.yaml), it writes the full training state atomically: weights, optimisers,
   schedulers, loop counters, the phi bank and its generator, the global RNG states, the callbacks' state
   (FID history) and the MLflow run id (kept beside it in the run folder). The checkpoint records that the
   epoch-end work of that epoch is still *pending*.
2. When that work is done it writes the file again with nothing pending. (Lightning runs checkpoint callbacks
   after all others at an epoch end, so a companion ``Checkpoint`` that this callback adds to the trainer
   makes this second write, after ModelCheckpoint's.)
3. A run resumed from a checkpoint with pending epoch-end work first redoes that work for that epoch (FID,
   best epoch, plots, the top-k checkpoint), logging its metrics at that epoch's step, then trains on.

The epoch-end work is made neutral for the global RNG (its state is restored after it), so a resumed run
draws the same dropout masks, data order and augmentations as one that was never interrupted.
"""

from __future__ import annotations

import logging
import random
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch
from lightning.pytorch import Callback, LightningModule, Trainer
from lightning.pytorch.callbacks import Checkpoint, ProgressBar

from drgan.callbacks.fid import checkpoint_dir

log = logging.getLogger(__name__)


def rng_state() -> dict:
    """torch, numpy and Python global RNG states, as plain tensors and lists (loadable with weights_only)."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    version, internal, gauss = random.getstate()
    return {
        "torch": torch.get_rng_state(),
        "numpy": {
            "kind": kind,
            "keys": torch.from_numpy(keys.astype(np.int64)),
            "pos": int(pos),
            "has_gauss": int(has_gauss),
            "cached": float(cached),
        },
        "python": {"version": int(version), "internal": list(internal), "gauss": gauss},
    }


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state((n["kind"], n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["cached"]))
    p = state["python"]
    random.setstate((p["version"], tuple(p["internal"]), p["gauss"]))


@contextmanager
def rng_neutral():
    """Run a block without changing the global RNG states seen by what follows it."""
    state = rng_state()
    try:
        yield
    finally:
        set_rng_state(state)


class ResumeCheckpoint(Callback):
    """filename: written in the checkpoint folder (ModelCheckpoint's ``dirpath``, else ``<run>/checkpoints``)."""

    def __init__(self, filename: str = "last.ckpt"):
        self.filename = str(filename)
        self.pending_epoch: int | None = None  # epoch whose epoch-end work is not done yet
        self._epoch_end_rng: dict | None = None  # global RNG states when that epoch's steps ended
        self._restored_pending: int | None = None

    @property
    def state_key(self) -> str:
        return type(self).__name__

    def path(self, trainer: Trainer) -> Path:
        return checkpoint_dir(trainer) / self.filename

    def save(self, trainer: Trainer) -> None:
        # Trainer.save_checkpoint writes through the strategy (rank 0 under DDP, collective call on every rank);
        # the checkpoint IO writes the file whole, and we rename it into place so a kill never leaves half a file.
        path = self.path(trainer)
        tmp = path.with_name(f".{path.name}.partial")
        # weights_only=False: the whole training state (said, so that Lightning logs no default on every save)
        trainer.save_checkpoint(tmp, weights_only=False)
        if trainer.is_global_zero:
            tmp.replace(path)
        trainer.strategy.barrier("drgan_resume_checkpoint")

    # --- the two writes ----------------------------------------------------------------------------------------

    def on_train_epoch_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        if trainer.sanity_checking or trainer.fast_dev_run:
            return
        self.pending_epoch = trainer.current_epoch
        self._epoch_end_rng = rng_state()
        self.save(trainer)

    def _finish_pending(self, trainer: Trainer, restore_rng: bool = True) -> None:
        if self.pending_epoch is None:
            return
        if (
            restore_rng and self._epoch_end_rng is not None
        ):  # whatever the epoch-end work drew, the next epoch starts as if it drew nothing
            set_rng_state(self._epoch_end_rng)
        self.pending_epoch = None
        self.save(trainer)

    def setup(self, trainer: Trainer, pl_module: LightningModule, stage: str) -> None:
        if not any(isinstance(c, _EpochEndDone) and c.owner is self for c in trainer.callbacks):
            trainer.callbacks.append(_EpochEndDone(self))  # last: after every other epoch-end hook

    def on_train_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        self._finish_pending(trainer)

    # --- resuming ----------------------------------------------------------------------------------------------

    def state_dict(self) -> dict:
        return {
            "pending_epoch": self.pending_epoch,
            "rng": self._epoch_end_rng if self.pending_epoch is not None else rng_state(),
        }

    def load_state_dict(self, state_dict: dict) -> None:
        self._restored_pending = state_dict.get("pending_epoch")
        self.pending_epoch = self._restored_pending
        if state_dict.get("rng") is not None:
            self._epoch_end_rng = state_dict["rng"]
            set_rng_state(state_dict["rng"])

    def on_train_start(self, trainer: Trainer, pl_module: LightningModule) -> None:
        epoch, self._restored_pending = self._restored_pending, None
        if epoch is None:
            return
        log.info(
            "resume: epoch %d ended before its epoch-end work (FID, best epoch, plots) finished; redoing it", epoch
        )
        with rng_neutral():
            replay_epoch_end(trainer, pl_module, epoch, skip=self)
        # The RNG states came from the checkpoint, and Lightning has already drawn from them (the data loader's
        # first batch is fetched before on_train_start): resetting them here would repeat those draws.
        self._finish_pending(trainer, restore_rng=False)


def _lightnings_own(callback: Callback) -> bool:
    """Lightning's callbacks and progress bars (drgan's is one): they keep their own state, and a bar has no
    epoch to close before the loop has opened one."""
    return isinstance(callback, ProgressBar) or type(callback).__module__.startswith(
        ("lightning.", "pytorch_lightning.")
    )


class _EpochEndDone(Checkpoint):
    """The second write of ``ResumeCheckpoint``: a ``Checkpoint`` so that Lightning calls its epoch-end hook in
    the last group (after ModelCheckpoint), when every other epoch-end hook has run."""

    def __init__(self, owner: ResumeCheckpoint):
        self.owner = owner

    @property
    def state_key(self) -> str:
        return "ResumeCheckpoint.done"

    def on_train_epoch_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        self.owner._finish_pending(trainer)


def replay_epoch_end(trainer: Trainer, pl_module: LightningModule, epoch: int, skip: Callback | None = None) -> dict:
    """Run every callback's ``on_train_epoch_end`` again for ``epoch`` (already trained and counted as done).

    Replayed: the project's callbacks (FID, best epoch, plots; not Lightning's own progress bars and monitors,
    which track the live loop) and then the checkpoint callbacks. The callbacks see ``trainer.current_epoch == epoch``; what they log with ``pl_module.log`` is collected and
    sent to the loggers at the step where Lightning logged that epoch's metrics, and put in
    ``trainer.callback_metrics`` for the checkpoint callbacks (which run last, as in a normal epoch end).
    Returns the metrics logged.
    """
    progress = trainer.fit_loop.epoch_progress.current
    if progress.completed != epoch + 1:
        raise RuntimeError(f"replay_epoch_end: epoch {epoch} is not the last completed one ({progress.completed - 1})")
    logged: dict[str, float] = {}

    def collect(name, value, *args, **kwargs):
        logged[name] = float(value.detach().float().mean()) if torch.is_tensor(value) else float(value)

    progress.completed -= 1  # trainer.current_epoch reads this counter
    pl_module.log = collect  # an instance attribute shadows LightningModule.log for the replay only
    try:
        checkpoints = [c for c in trainer.checkpoint_callbacks if not isinstance(c, _EpochEndDone)]
        for callback in trainer.callbacks:
            if callback is not skip and not isinstance(callback, Checkpoint) and not _lightnings_own(callback):
                callback.on_train_epoch_end(trainer, pl_module)
        trainer.callback_metrics.update({k: torch.tensor(v) for k, v in logged.items()})
        for callback in checkpoints:
            callback.on_train_epoch_end(trainer, pl_module)
    finally:
        del pl_module.log
        progress.completed += 1
    step = max(trainer.fit_loop.epoch_loop._batches_that_stepped - 1, 0)  # the step Lightning gives epoch metrics
    if trainer.is_global_zero and logged:
        for logger in trainer.loggers:
            logger.log_metrics(logged, step=step)
    return logged
