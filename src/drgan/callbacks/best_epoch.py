"""The best epoch: among the ``top_k`` epochs of lowest FID that lie within ``fid_margin`` of the lowest, the
one whose learned parameter distribution is broadest.

A GAN's lowest FID is often reached by a generator that collapsed onto a narrow set of material
parameters; a broad distribution generalises better to downstream segmentation. So the selection is:
sort evaluated epochs by FID, keep the ``top_k`` lowest, and of those the ones whose FID is at most
(1 + fid_margin) x the lowest (default 10 %), then pick the one with the largest *parameter spread* (spreads
within 5 % of the largest count as tied; the lower FID wins among them). The margin keeps the FID weighing in
short runs: with 5 epochs or fewer every epoch is among the "5 lowest", and spread alone would pick an epoch of
far higher FID.

Parameter spread (``parameter_spread``): for a fixed set of ``n_phi`` constellations (drawn once from the
configured size and placement distributions), the regressor's learned values are normalised by their
configured limits, u = (x - low) / (high - low) in [0, 1], and the spread is the mean over parameters of
the (population, ddof=0) standard deviation of u. 0: every constellation gets the same parameters; the
largest possible value is 0.5 (half at each limit).

Brightness guard: the FID hardly sees global brightness (see drgan.callbacks.fid), so epochs whose particles
or whose background are far darker or brighter than the real ones (``val/particle_brightness`` or
``val/background_brightness`` outside ``brightness_range``, default 0.5-2x), or whose contrast is inverted
(``val/contrast`` <= 1: particles on the wrong side of the background), do not compete, unless no epoch
passes (then all do, with a warning). A generator can reach its lowest FID with images several times too dark
(4.6x in a TiO2 SEM run, experiments/tio2_sem/RESULTS.md), and a segmenter trained on such images finds nothing
in the real ones.

Each epoch's weights are saved to ``<checkpoints>/epochs/epoch_XXX.ckpt`` (weights only); those that fall
out of the top_k are deleted, since the best can only be among the top_k. After every evaluated epoch
(so a cut-off run has them) ``<checkpoints>/best.ckpt`` and ``best_epoch.json`` are rewritten atomically.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
from lightning.pytorch import Callback, LightningModule, Trainer

from drgan.callbacks.fid import FIDCallback, atomic_copy, checkpoint_dir, log_artifact
from drgan.errors import ConfigError
from drgan.io import write_json

log = logging.getLogger(__name__)


def parameter_spread(values: np.ndarray, low, high) -> float:
    """values (B, k) of k parameters with limits low/high (k,) -> mean over parameters of std((x - low) / (high - low))."""
    values = np.asarray(values, dtype=np.float64)
    low, high = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
    if values.ndim != 2 or values.shape[1] != low.shape[0] or high.shape != low.shape:
        raise ConfigError(f"parameter_spread: values {values.shape} do not match limits {low.shape}, {high.shape}")
    if values.shape[1] == 0:
        return 0.0
    unit = (values - low) / np.where(high > low, high - low, 1.0)
    return float(unit.std(axis=0).mean())


def within_brightness(entry: dict, brightness_range) -> bool:
    """True when the entry's particles and background (synthetic / real mean grey of each) are inside [low, high]
    and its contrast is not inverted (``contrast`` > 1); True when there is no range or the entry has no such
    values (a history written by hand)."""
    if brightness_range is None:
        return True
    low, high = brightness_range
    separate = [entry.get(k) for k in ("particle_brightness", "background_brightness")]
    if any(v is None for v in separate):
        return True
    if entry.get("contrast") is not None and not entry["contrast"] > 1.0:  # NaN (no particle pixel) fails too
        return False
    return all(low <= v <= high for v in separate)


def select_best(
    history: list[dict],
    top_k: int,
    brightness_range=None,
    spread_tolerance: float = 0.05,
    fid_margin: float | None = 0.1,
) -> tuple[dict | None, list[dict]]:
    """history: dicts with epoch, fid, spread (and brightness) -> (best entry, the top_k table sorted by FID).

    Epochs with a non-finite FID are never chosen. Of the top_k lowest FIDs, only those at most (1 + fid_margin)
    x the lowest compete on spread (None: all top_k). Spreads within ``spread_tolerance`` (relative) of the
    largest count as tied, and ties go to the lower FID (spreads that close are noise: a spread larger by 0.0003
    would otherwise win with FID 148.9 over 140.0, experiments/tio2_sem/README.md). With a ``brightness_range`` (low, high), only epochs inside it
    (`within_brightness`) compete, unless none is (then all do)."""
    finite = [h for h in history if math.isfinite(h.get("fid", math.nan)) and math.isfinite(h.get("spread", math.nan))]
    eligible = [h for h in finite if within_brightness(h, brightness_range)]
    table = sorted(eligible or finite, key=lambda h: (h["fid"], h["epoch"]))[: int(top_k)]
    if not table:
        return None, []
    contenders = table
    if fid_margin is not None:
        limit = table[0]["fid"] + abs(table[0]["fid"]) * float(fid_margin)
        contenders = [h for h in table if h["fid"] <= limit]
    broadest = max(h["spread"] for h in contenders)
    best = min(
        (h for h in contenders if h["spread"] >= (1.0 - spread_tolerance) * broadest),
        key=lambda h: (h["fid"], h["epoch"]),
    )
    return best, table


class BestEpochCallback(Callback):
    """top_k: how many lowest-FID epochs compete on spread; n_phi: constellations for the spread; seed: of
    those constellations; brightness_range: (low, high) of synthetic / real mean grey for an epoch to
    compete (None: no check). Needs a FIDCallback before it in the callback list."""

    def __init__(
        self,
        top_k: int = 5,
        n_phi: int = 1000,
        seed: int = 0,
        brightness_range=(0.5, 2.0),
        fid_margin: float | None = 0.1,
    ):
        if int(top_k) < 1 or int(n_phi) < 2:
            raise ConfigError(f"BestEpochCallback: top_k={top_k}, n_phi={n_phi}; expected top_k >= 1 and n_phi >= 2")
        if fid_margin is not None and not (isinstance(fid_margin, (int, float)) and 0 <= fid_margin < math.inf):
            raise ConfigError(
                f"callbacks.best_epoch.fid_margin={fid_margin!r}: expected a number >= 0 (0.1: epochs within "
                "10 % of the lowest FID compete on spread) or null"
            )
        self.fid_margin = None if fid_margin is None else float(fid_margin)
        if brightness_range is not None:
            brightness_range = tuple(float(v) for v in brightness_range)
            if len(brightness_range) != 2 or not 0 < brightness_range[0] < brightness_range[1]:
                raise ConfigError(
                    f"callbacks.best_epoch.brightness_range={list(brightness_range)}: expected [low, high] "
                    "with 0 < low < high (synthetic / real mean grey), or null"
                )
        self.top_k, self.n_phi, self.seed = int(top_k), int(n_phi), int(seed)
        self.brightness_range = brightness_range
        self.history: list[dict] = []  # epoch, fid, kid, spread, checkpoint
        self._phi: np.ndarray | None = None

    @property
    def state_key(self) -> str:
        return type(self).__name__

    def spread(self, pl_module: LightningModule) -> float:
        if self._phi is None:
            self._phi = pl_module.sample_phi(self.n_phi, seed=self.seed)
        learned = pl_module.generator.learned
        values = pl_module.parameter_samples(self._phi)
        return parameter_spread(values, [p.low for p in learned], [p.high for p in learned])

    def on_train_epoch_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        fid_callback = next((c for c in trainer.callbacks if isinstance(c, FIDCallback)), None)
        if fid_callback is None:
            raise ConfigError("BestEpochCallback needs a FIDCallback (callbacks.fid) in the callback list")
        epoch = trainer.current_epoch
        scores = fid_callback.latest(epoch)
        if scores is None or not math.isfinite(scores["fid"]):  # not evaluated (every_n_epochs > 1), or screened out
            return
        folder = checkpoint_dir(trainer)
        ckpt = folder / "epochs" / f"epoch_{epoch:03d}.ckpt"
        trainer.save_checkpoint(ckpt, weights_only=True)  # collective under DDP: every rank calls it
        entry = {
            "epoch": epoch,
            "fid": scores["fid"],
            "kid": scores["kid"],
            "spread": self.spread(pl_module),
            "checkpoint": str(ckpt),
            **{k: scores.get(k) for k in ("brightness", "particle_brightness", "background_brightness", "contrast")},
        }
        self.history = [h for h in self.history if h["epoch"] != epoch] + [entry]
        if trainer.is_global_zero:
            self._prune(folder)
        self.write(trainer, pl_module)

    def _prune(self, folder: Path) -> None:
        """Delete epoch checkpoints outside the top_k: the best is always among them."""
        _, table = select_best(self.history, self.top_k, self.brightness_range, fid_margin=self.fid_margin)
        keep = {Path(h["checkpoint"]).name for h in table}
        for path in (folder / "epochs").glob("epoch_*.ckpt"):
            if path.name not in keep:
                path.unlink(missing_ok=True)

    def write(self, trainer: Trainer, pl_module: LightningModule) -> dict | None:
        best, table = select_best(self.history, self.top_k, self.brightness_range, fid_margin=self.fid_margin)
        if best is None or not trainer.is_global_zero:
            return best
        folder = checkpoint_dir(trainer)
        src = Path(best["checkpoint"])
        if src.is_file():
            atomic_copy(src, folder / "best.ckpt")
        else:
            log.warning("best epoch %d: its checkpoint %s is gone; best.ckpt not updated", best["epoch"], src)
        summary = {
            "epoch": best["epoch"], "fid": best["fid"], "kid": best["kid"], "spread": best["spread"],
            "brightness": best.get("brightness"), "particle_brightness": best.get("particle_brightness"),
            "background_brightness": best.get("background_brightness"), "contrast": best.get("contrast"),
            "top_k": self.top_k, "fid_margin": self.fid_margin, "n_phi": self.n_phi,
            "brightness_range": None if self.brightness_range is None else list(self.brightness_range),
            "brightness_ok": within_brightness(best, self.brightness_range),
            "spread_definition": "mean over learned parameters of std((x - low) / (high - low)) over n_phi constellations",
            "table": table, "history": self.history,
        }  # fmt: skip
        path = folder / "best_epoch.json"
        write_json(path, summary)
        pl_module.log("best/epoch", float(best["epoch"]), on_step=False, on_epoch=True, rank_zero_only=True)
        pl_module.log("best/fid", float(best["fid"]), on_step=False, on_epoch=True, rank_zero_only=True)
        log_artifact(trainer, path)
        return best

    def on_train_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        best, _ = select_best(self.history, self.top_k, self.brightness_range, fid_margin=self.fid_margin)
        if best is not None and trainer.is_global_zero:
            log.info(
                "best epoch %d: FID %.4g, spread %.4g (of the %d lowest-FID epochs)",
                best["epoch"],
                best["fid"],
                best["spread"],
                self.top_k,
            )
            if not within_brightness(best, self.brightness_range):
                log.warning(
                    "best epoch %d: no epoch had particles and background within %s x the real ones' grey with "
                    "the real contrast direction (this one: particles %s x, background %s x, contrast %s, whole "
                    "image %s x); check the material (polarity, lights, limits) before generating data from it",
                    best["epoch"],
                    list(self.brightness_range),
                    best.get("particle_brightness"),
                    best.get("background_brightness"),
                    best.get("contrast"),
                    best.get("brightness"),
                )

    def state_dict(self) -> dict:
        return {"history": [dict(h) for h in self.history]}

    def load_state_dict(self, state_dict: dict) -> None:
        self.history = [dict(h) for h in state_dict.get("history", [])]
