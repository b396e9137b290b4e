"""Stop a run when its FID has stopped improving, and say why every run stopped.

A DiffRenderGAN run on ~130 real patches improves for a few hundred steps and then drifts (the recorded TiO2 SEM
curves in experiments/tio2_sem/README.md: lowest FID after 230-270 steps, then rising), so the paper's 50 epochs
mostly cost time. ``FIDEarlyStopping`` reads the FIDCallback's evaluations (it must come after it in the callback
list) and stops the trainer when the lowest FID has not improved by more than ``min_delta`` for ``patience``
evaluations, or for ``patience_steps`` training steps, whichever is set and comes first. An evaluation that the
FID callback's KID screen turned away (FID NaN) counts as no improvement. The best-epoch rule still chooses among
every evaluation seen.

``max_minutes``: a wall-clock safety net for the training (resumed runs count the time of their earlier parts). A
run's result should depend on its steps and evaluations only (``trainer.max_epochs`` x the steps of an epoch, and
patience), not on how busy the machine is; the net is for a machine far slower than expected. It stops at an epoch's
end when the next epoch, FID pass included, would not fit (its estimate: the slowest epoch so far), so the run ends
inside it with an evaluated last epoch, and it says loudly that it cut the run short (the same command on a quieter
machine would train on and may choose another epoch). Lightning's ``trainer.max_time`` is a hard limit instead: it
stops mid-epoch, and the FID of that epoch still runs after it.

``wait_for_grey`` (default true): patience does not stop a run while no evaluated epoch has its particles and
background within the real patches' grey (the best-epoch rule's brightness range, drgan.callbacks.best_epoch):
such a run has nothing usable to choose yet, and on a small, unfamiliar set its FID can settle before the grey does.
It trains on to its budget (or max_epochs), and stops by patience as soon as an epoch in range exists.

``stop_reason(trainer)`` names what ended a run (``patience``, ``budget``, ``max_time``, ``max_epochs``,
``max_steps``, ``interrupted``); drgan.train logs it, writes it to metrics.json and tags the MLflow run with it.

The simulation of this rule on the recorded FID histories, which chose the defaults: experiments/early_stop/.
"""

from __future__ import annotations

import logging
import math
import time

from lightning.pytorch import Callback, LightningModule, Trainer
from lightning.pytorch.callbacks import Timer

from drgan.callbacks.best_epoch import BestEpochCallback, within_brightness
from drgan.callbacks.fid import FIDCallback
from drgan.core.errors import ConfigError

log = logging.getLogger(__name__)


def should_stop(
    history: list[dict], patience: int | None, patience_steps: int | None = None, min_delta: float = 0.0
) -> str | None:
    """The rule on a list of evaluations (dicts with ``fid`` and, for ``patience_steps``, ``step``), in order:
    a message when the run should stop after the last one, else None. Pure, so experiments can replay it."""
    best_index, best = None, math.inf
    for index, entry in enumerate(history):
        fid = entry.get("fid", math.nan)
        if math.isfinite(fid) and fid < best - min_delta:
            best_index, best = index, fid
    if best_index is None or not history:
        return None
    since = len(history) - 1 - best_index
    if patience is not None and since >= patience:
        return (
            f"FID has not improved on {best:.4g} (epoch {history[best_index]['epoch']}) by more than {min_delta:g} "
            f"for {since} evaluations (patience {patience})"
        )
    if patience_steps is not None:
        steps = int(history[-1]["step"]) - int(history[best_index]["step"])
        if steps >= patience_steps:
            return (
                f"FID has not improved on {best:.4g} (epoch {history[best_index]['epoch']}) by more than "
                f"{min_delta:g} for {steps} steps (patience_steps {patience_steps})"
            )
    return None


class FIDEarlyStopping(Callback):
    """patience: evaluations without improvement before the run stops (None: not by count); patience_steps:
    training steps since the lowest FID (None: not by steps); min_delta: FID points an evaluation must gain to
    count as an improvement (the score's own spread at ~130 images is ~2, experiments/tio2_sem/README.md);
    max_minutes: the wall-clock budget of the module docstring (None: none); wait_for_grey: no stop by patience
    while no evaluated epoch is within the real grey (module docstring)."""

    def __init__(
        self,
        patience: int | None = 2,
        patience_steps: int | None = None,
        min_delta: float = 0.0,
        max_minutes: float | None = None,
        wait_for_grey: bool = True,
    ):
        for name, value in (("patience", patience), ("patience_steps", patience_steps)):
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
                raise ConfigError(f"callbacks.early_stopping.{name}={value!r}: expected an integer >= 1 or null")
        if patience is None and patience_steps is None and max_minutes is None:
            raise ConfigError(
                "callbacks.early_stopping: patience, patience_steps and max_minutes are all null; set one, "
                "or drop the callback (~callbacks.early_stopping) to train for trainer.max_epochs"
            )
        if max_minutes is not None and not (isinstance(max_minutes, (int, float)) and 0 < max_minutes < math.inf):
            raise ConfigError(f"callbacks.early_stopping.max_minutes={max_minutes!r}: expected minutes > 0 or null")
        if not (isinstance(min_delta, (int, float)) and 0 <= min_delta < math.inf):
            raise ConfigError(f"callbacks.early_stopping.min_delta={min_delta!r}: expected a number >= 0 (FID points)")
        self.patience = patience
        self.patience_steps = patience_steps
        self.min_delta = float(min_delta)
        self.wait_for_grey = bool(wait_for_grey)
        self.max_seconds = None if max_minutes is None else 60.0 * float(max_minutes)
        self.reason: str | None = None
        self.kind: str | None = None
        self.elapsed = 0.0  # seconds of training in earlier parts of a resumed run
        self.slowest_epoch = 0.0  # seconds, FID pass included
        self._start: float | None = None
        self._last: float = 0.0

    def seconds(self) -> float:
        """Training seconds so far, earlier parts of a resumed run included."""
        return self.elapsed + (time.perf_counter() - self._start if self._start is not None else 0.0)

    def on_train_start(self, trainer: Trainer, pl_module: LightningModule) -> None:
        self._start = time.perf_counter()
        self._last = self.seconds()
        self.reason = self.kind = None  # a resumed run stops for reasons of its own

    @property
    def state_key(self) -> str:
        return type(self).__name__

    def on_train_epoch_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        fid_callback = next((c for c in trainer.callbacks if isinstance(c, FIDCallback)), None)
        if fid_callback is None:
            raise ConfigError("FIDEarlyStopping needs a FIDCallback (callbacks.fid) before it in the callback list")
        now = self.seconds()
        self.slowest_epoch, self._last = max(self.slowest_epoch, now - self._last), now
        kind, reason = None, None
        if fid_callback.latest(trainer.current_epoch) is not None:  # an evaluation this epoch
            kind, reason = (
                "patience",
                should_stop(fid_callback.history, self.patience, self.patience_steps, self.min_delta),
            )
            if reason is not None and self.wait_for_grey and not self._any_in_range(trainer):
                if trainer.is_global_zero:
                    log.warning(
                        "epoch %d: %s, but no evaluated epoch has its particle and background grey within the real "
                        "range yet (best_epoch.json): training on%s",
                        trainer.current_epoch,
                        reason,
                        f" until one does or the budget (max_minutes={self.max_seconds / 60:g}) ends"
                        if self.max_seconds is not None
                        else " until one does (or trainer.max_epochs)",
                    )
                kind, reason = None, None
        if reason is None and self.max_seconds is not None and now + self.slowest_epoch > self.max_seconds:
            kind, reason = (
                "budget",
                (
                    f"another epoch (up to {self.slowest_epoch:.0f} s) would not fit the budget "
                    f"max_minutes={self.max_seconds / 60:g} ({now:.0f} s spent)"
                ),
            )
        if reason is not None:
            self.kind, self.reason = kind, reason
            trainer.should_stop = True
            if trainer.is_global_zero and kind == "budget":
                log.warning(
                    "the wall-clock safety net cut this run short after epoch %d of trainer.max_epochs=%s: %s. Its "
                    "result now depends on this machine's speed (a quieter machine would train on and may choose "
                    "another epoch); raise callbacks.early_stopping.max_minutes to train the epochs it was set to",
                    trainer.current_epoch, trainer.max_epochs, reason,
                )  # fmt: skip
            elif trainer.is_global_zero:
                log.info("early stop after epoch %d: %s", trainer.current_epoch, reason)

    @staticmethod
    def _any_in_range(trainer: Trainer) -> bool:
        """Whether an evaluated epoch of the best-epoch rule's history is within its brightness range (True without
        that callback, or before its range is known: nothing to wait for)."""
        best = next((c for c in trainer.callbacks if isinstance(c, BestEpochCallback)), None)
        if best is None or best.brightness_range is None:
            return True
        return any(within_brightness(entry, best.brightness_range) for entry in best.history)

    def state_dict(self) -> dict:
        return {
            "reason": self.reason,
            "kind": self.kind,
            "elapsed": self.seconds(),
            "slowest_epoch": self.slowest_epoch,
        }

    def load_state_dict(self, state_dict: dict) -> None:
        self.reason, self.kind = state_dict.get("reason"), state_dict.get("kind")
        self.elapsed = float(state_dict.get("elapsed", 0.0))
        self.slowest_epoch = float(state_dict.get("slowest_epoch", 0.0))


def stop_reason(trainer: Trainer) -> tuple[str, str]:
    """(kind, message) of what ended ``trainer.fit``: patience, budget, max_time, interrupted, max_steps, max_epochs or
    other (e.g. ``trainer.should_stop`` set elsewhere)."""
    if trainer.interrupted:
        return "interrupted", "interrupted (signal or exception)"
    for callback in trainer.callbacks:
        if isinstance(callback, FIDEarlyStopping) and callback.reason:
            return callback.kind or "patience", callback.reason
    timer = next((c for c in trainer.callbacks if isinstance(c, Timer)), None)
    remaining = timer.time_remaining() if timer is not None else None  # None: no trainer.max_time
    if remaining is not None and remaining <= 0:
        return "max_time", f"wall-clock budget trainer.max_time ({timer.time_elapsed():.0f} s) spent"
    if trainer.max_steps not in (None, -1) and trainer.global_step >= trainer.max_steps:
        return "max_steps", f"trainer.max_steps={trainer.max_steps} reached"
    if trainer.max_epochs is not None and trainer.current_epoch >= trainer.max_epochs:
        return "max_epochs", f"trainer.max_epochs={trainer.max_epochs} reached"
    return "other", f"stopped at epoch {trainer.current_epoch}, step {trainer.global_step}"
