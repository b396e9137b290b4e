"""The best epoch: among the ``top_k`` epochs of lowest FID whose particles and background are as bright as
real ones, of those whose FID no other beats by more than the FIDs' own spread, the one whose learned parameter
distribution is broadest.

A GAN's lowest FID is often reached by a generator that collapsed onto a narrow set of material
parameters; a broad distribution generalises better to downstream segmentation. So the selection is:
keep the epochs inside the brightness range, sort them by FID, keep the ``top_k`` lowest, drop those whose FID
another of them beats clearly (``fid_margin``), then pick the one with the largest *parameter spread* (spreads
within 5 % of the largest count as tied; the lower FID wins among them).

**When a lower FID wins outright** (``fid_margin: auto``, the default): each evaluation records ``fid_std``, the
FID's bootstrap standard error over its generated sample (drgan.callbacks.fid, 10 resamples). Epoch a beats
epoch b outright when fid_b - fid_a > 2 x sqrt(std_a^2 + std_b^2) (``FID_SIGMAS``; two standard errors of the
difference: two independent estimates of one FID differ by that much about 5 % of the time); an epoch beaten by
any other of the top_k does not compete, so spread decides only among FIDs statistically indistinguishable from
the lowest. The lowest FID is never beaten, so there is always a contender. The stds are a few FID points (the
real TiO2 patches half against half, ~65 images each: 2.1 SEM, 2.9 TSEM; ~130 images give less), so the rule is
tighter than a fixed 10 % where FIDs are above ~60-80: FIDs 123.1 and 132.6 with stds of ~2 differ by 9.5, over the
5.7 allowed, and the lower FID wins whatever the spreads, where a 10 % margin (12.3 points at that FID) would let the
spread choose the 132.6.
A pair where either entry has no ``fid_std`` (histories from before it, or written by hand) falls back to a
fixed margin: b is beaten when fid_b > (1 + 0.1) x fid_a (``FALLBACK_MARGIN``; with no stds at all, of the top_k
only FIDs at most 1.1 x the lowest compete). A number for ``fid_margin`` is that fixed
margin for every pair; null lets all top_k compete. The margin keeps the FID weighing in short runs: with 5
epochs or fewer every epoch is among the "5 lowest", and spread alone would pick an epoch of far higher FID.

Parameter spread (``parameter_spread``): for a fixed set of ``n_phi`` constellations (drawn once from the
configured size and placement distributions), the regressor's learned values are normalised by their
configured limits, u = (x - low) / (high - low) in [0, 1], and the spread is the mean over parameters of
the (population, ddof=0) standard deviation of u. 0: every constellation gets the same parameters; the
largest possible value is 0.5 (half at each limit).

Brightness guard: the FID hardly sees global brightness (see drgan.callbacks.fid), so epochs whose particles
or whose background are darker or brighter than the real ones (``val/particle_brightness`` or
``val/background_brightness`` outside ``brightness_range``), or whose contrast is inverted (``val/contrast``
<= 1: particles on the wrong side of the background), do not compete, unless no epoch passes (then all do, with
a warning). ``brightness_range: auto`` (default) takes the range from the real training patches
(``drgan.callbacks.fid.brightness_tolerance``): the 5th-95th percentile of each real patch's own particle grey and
background grey / the real grey, separately for particles and background, at least 1/1.1-1.1x; i.e. an epoch
is off when its mean grey (over ~130 images, far steadier than one patch) is where fewer than 5 % of the real
patches are. On the mined TiO2 patches that is particles 0.75-1.26x and background 0.57-1.35x for SEM, particles
0.91-1.10x (the floor) and background 0.70-1.60x for TSEM (negatives, dark particles): tighter than a fixed
0.5-2x, which lets through a background 0.62x real. The range is logged once and written to best_epoch.json. A
fixed ``[low, high]`` applies to particles and background alike; null switches the guard off. A generator can
reach its lowest FID with images several times too dark (4.6x in a TiO2 SEM run, experiments/tio2_sem/RESULTS.md),
and a segmenter trained on such images finds nothing in the real ones.

Each epoch's weights are saved to ``<checkpoints>/epochs/epoch_XXX.ckpt`` (weights only); those that fall
out of the top_k are deleted, since the best can only be among the top_k. After every evaluated epoch
(so a cut-off run has them) ``<checkpoints>/best.ckpt`` and ``best_epoch.json`` are rewritten atomically.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from lightning.pytorch import Callback, LightningModule, Trainer

from drgan.callbacks.fid import (
    BRIGHTNESS_FLOOR,
    BRIGHTNESS_PERCENTILES,
    FIDCallback,
    atomic_copy,
    checkpoint_dir,
    log_artifact,
    real_patches,
)
from drgan.core.errors import ConfigError
from drgan.core.io import write_json

log = logging.getLogger(__name__)

FID_SIGMAS = 2.0  # fid_margin auto: a lower FID wins outright past this many standard errors of the difference
FALLBACK_MARGIN = 0.1  # fid_margin auto, for a pair without fid_std: a fixed relative margin


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
    """True when the entry's particles and background (synthetic / real mean grey of each) are inside their
    range and its contrast is not inverted (``contrast`` > 1); True when there is no range or the entry has no
    such values (a history written by hand). brightness_range: (low, high) for both, or a mapping
    {"particle": (low, high), "background": (low, high)} (the derived ``auto`` range)."""
    if brightness_range is None:
        return True
    if isinstance(brightness_range, Mapping):
        ranges = [brightness_range["particle"], brightness_range["background"]]
    else:
        ranges = [brightness_range] * 2
    separate = [entry.get(k) for k in ("particle_brightness", "background_brightness")]
    if any(v is None for v in separate):
        return True
    if entry.get("contrast") is not None and not entry["contrast"] > 1.0:  # NaN (no particle pixel) fails too
        return False
    return all(low <= v <= high for v, (low, high) in zip(separate, ranges))


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value)


def beats(a: dict, b: dict, fid_margin="auto") -> bool:
    """Whether entry a's FID is lower than b's by more than chance: by more than ``FID_SIGMAS`` x
    sqrt(a.fid_std^2 + b.fid_std^2) (``fid_margin`` "auto" and both have a finite ``fid_std``), else by more
    than the relative margin (a number, or ``FALLBACK_MARGIN`` for auto) of a's FID."""
    if fid_margin == "auto":
        if _finite(a.get("fid_std")) and _finite(b.get("fid_std")):
            return b["fid"] - a["fid"] > FID_SIGMAS * math.hypot(a["fid_std"], b["fid_std"])
        fid_margin = FALLBACK_MARGIN
    return b["fid"] - a["fid"] > abs(a["fid"]) * float(fid_margin)


def select_best(
    history: list[dict],
    top_k: int,
    brightness_range=None,
    spread_tolerance: float = 0.05,
    fid_margin: float | str | None = "auto",
) -> tuple[dict | None, list[dict]]:
    """history: dicts with epoch, fid, spread (and fid_std, brightness) -> (best entry, the top_k table sorted by
    FID).

    Epochs with a non-finite FID are never chosen. Of the top_k lowest FIDs, only those that no other of them
    `beats` compete on spread (fid_margin "auto": by 2 combined standard errors where both have ``fid_std``,
    else by 10 %; a number: by that relative margin, i.e. only FIDs at most (1 + fid_margin) x the lowest
    compete; None: all top_k). Spreads within ``spread_tolerance`` (relative) of the
    largest count as tied, and ties go to the lower FID (spreads that close are noise: a spread larger by 0.0003
    would otherwise win with FID 148.9 over 140.0, experiments/tio2_sem/README.md). With a ``brightness_range`` (low, high), only epochs inside it
    (`within_brightness`) compete, unless none is (then all do)."""
    finite = [h for h in history if math.isfinite(h.get("fid", math.nan)) and math.isfinite(h.get("spread", math.nan))]
    eligible = [h for h in finite if within_brightness(h, brightness_range)]
    table = sorted(eligible or finite, key=lambda h: (h["fid"], h["epoch"]))[: int(top_k)]
    if not table:
        return None, []
    contenders = table
    if fid_margin is not None:  # the lowest FID is never beaten: contenders is never empty
        contenders = [b for b in table if not any(beats(a, b, fid_margin) for a in table)]
    broadest = max(h["spread"] for h in contenders)
    best = min(
        (h for h in contenders if h["spread"] >= (1.0 - spread_tolerance) * broadest),
        key=lambda h: (h["fid"], h["epoch"]),
    )
    return best, table


def check_brightness_range(value) -> str | tuple[float, float] | None:
    """The ``callbacks.best_epoch.brightness_range`` setting: "auto", None, or (low, high) with 0 < low < high."""
    if value is None or (isinstance(value, str) and value == "auto"):
        return value
    problem = None
    if isinstance(value, (str, bytes, Mapping)) or not hasattr(value, "__iter__"):
        problem = "not a pair"
    else:
        items = list(value)
        if len(items) != 2 or any(isinstance(v, (bool, str)) or not isinstance(v, (int, float)) for v in items):
            problem = "not a pair of numbers"
        elif not (0 < items[0] < items[1] < math.inf):
            problem = "not 0 < low < high"
    if problem:
        shown = list(value) if isinstance(value, (list, tuple)) else value
        raise ConfigError(
            f"callbacks.best_epoch.brightness_range={shown!r} ({problem}): expected auto (the range the real "
            "patches span, the default), [low, high] with 0 < low < high (synthetic / real mean grey of particles "
            "and of background), or null (no check)"
        )
    return float(items[0]), float(items[1])


def check_fid_margin(value) -> str | float | None:
    """The ``callbacks.best_epoch.fid_margin`` setting: "auto", None, or a number >= 0."""
    if value is None or (isinstance(value, str) and value == "auto"):
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value < math.inf:
        raise ConfigError(
            f"callbacks.best_epoch.fid_margin={value!r}: expected auto (an FID lower by more than 2 combined "
            "bootstrap standard errors wins outright, the default), a number >= 0 (0.1: epochs within 10 % of "
            "the lowest FID compete on spread) or null (all top_k compete)"
        )
    return float(value)


def _number(value) -> str:
    return f"{value:.3g}" if isinstance(value, (int, float)) else str(value)


def _range_text(brightness_range) -> str:
    if brightness_range is None:
        return "none"
    if isinstance(brightness_range, Mapping):
        return ", ".join(
            f"{k} {brightness_range[k][0]:.2f}-{brightness_range[k][1]:.2f} x" for k in ("particle", "background")
        )
    return f"{brightness_range[0]:.2f}-{brightness_range[1]:.2f} x"


class BestEpochCallback(Callback):
    """top_k: how many lowest-FID epochs compete on spread; n_phi: constellations for the spread; seed: of
    those constellations; brightness_range: "auto" (the range the real patches span, from the FIDCallback),
    (low, high) of synthetic / real mean grey for an epoch to compete, or None (no check); fid_margin: "auto"
    (the FIDs' bootstrap spread decides when a lower FID wins outright), a fixed relative margin, or None.
    Needs a FIDCallback before it in the callback list."""

    def __init__(
        self,
        top_k: int = 5,
        n_phi: int = 1000,
        seed: int = 0,
        brightness_range="auto",
        fid_margin: float | str | None = "auto",
    ):
        if int(top_k) < 1 or int(n_phi) < 2:
            raise ConfigError(f"BestEpochCallback: top_k={top_k}, n_phi={n_phi}; expected top_k >= 1 and n_phi >= 2")
        self.fid_margin = check_fid_margin(fid_margin)
        self.brightness_setting = check_brightness_range(brightness_range)
        # what within_brightness uses: the fixed pair or None now, the derived ranges once the real patches are known
        self.brightness_range = None if self.brightness_setting == "auto" else self.brightness_setting
        self.top_k, self.n_phi, self.seed = int(top_k), int(n_phi), int(seed)
        self.history: list[dict] = []  # epoch, fid, fid_std, kid, spread, brightness, checkpoint
        self._phi: np.ndarray | None = None

    def resolve_brightness(self, fid_callback: FIDCallback, trainer: Trainer):
        """For ``brightness_range: auto``: the ranges the real patches span (computed and logged once)."""
        if self.brightness_setting == "auto" and self.brightness_range is None:
            self.brightness_range = fid_callback.brightness_tolerance(trainer)
            if trainer.is_global_zero:
                log.info(
                    "best epoch: brightness range from the %d real patches (%gth-%gth percentile of their own grey / "
                    "the real grey, at least 1/%g-%g x): %s",
                    len(real_patches(trainer)),
                    *BRIGHTNESS_PERCENTILES,
                    BRIGHTNESS_FLOOR,
                    BRIGHTNESS_FLOOR,
                    _range_text(self.brightness_range),
                )
        return self.brightness_range

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
        self.resolve_brightness(fid_callback, trainer)
        folder = checkpoint_dir(trainer)
        ckpt = folder / "epochs" / f"epoch_{epoch:03d}.ckpt"
        trainer.save_checkpoint(ckpt, weights_only=True)  # collective under DDP: every rank calls it
        entry = {
            "epoch": epoch,
            "fid": scores["fid"],
            "fid_std": scores.get("fid_std"),
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

    def rule(self) -> dict:
        """The selection's settings and what they mean, as best_epoch.json records them."""
        if self.fid_margin == "auto":
            fid_rule = (
                f"an FID lower by more than {FID_SIGMAS:g} x sqrt(fid_std_a^2 + fid_std_b^2) wins outright (a pair "
                f"without fid_std: by more than {FALLBACK_MARGIN:g} x the lower FID); spread decides among the rest"
            )
        elif self.fid_margin is not None:
            fid_rule = f"FIDs at most {1 + self.fid_margin:g} x the lowest compete on spread"
        else:
            fid_rule = "all top_k compete on spread"
        if self.brightness_setting == "auto":
            low, high = BRIGHTNESS_PERCENTILES
            brightness_rule = (
                f"derived: {low:g}th-{high:g}th percentile of the real patches' own particle and background grey / "
                f"the real grey, at least 1/{BRIGHTNESS_FLOOR:g}-{BRIGHTNESS_FLOOR:g} x"
            )
            ranges = self.brightness_range
            brightness_range = None if ranges is None else {k: list(v) for k, v in ranges.items()}
        else:
            brightness_rule = "fixed, particles and background alike" if self.brightness_range else "none"
            brightness_range = None if self.brightness_range is None else list(self.brightness_range)
        setting = self.brightness_setting
        return {
            "fid_margin": self.fid_margin,
            "fid_rule": fid_rule,
            "brightness_range_setting": setting if setting in (None, "auto") else list(setting),
            "brightness_range": brightness_range,
            "brightness_rule": brightness_rule,
        }

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
            "epoch": best["epoch"], "fid": best["fid"], "fid_std": best.get("fid_std"), "kid": best["kid"],
            "spread": best["spread"],
            "brightness": best.get("brightness"), "particle_brightness": best.get("particle_brightness"),
            "background_brightness": best.get("background_brightness"), "contrast": best.get("contrast"),
            "top_k": self.top_k, "n_phi": self.n_phi, **self.rule(),
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
        fid_callback = next((c for c in trainer.callbacks if isinstance(c, FIDCallback)), None)
        if self.history and fid_callback is not None:  # a resumed run that evaluated nothing more: not resolved yet
            self.resolve_brightness(fid_callback, trainer)
        best, _ = select_best(self.history, self.top_k, self.brightness_range, fid_margin=self.fid_margin)
        if best is not None and trainer.is_global_zero:
            log.info(
                "best epoch %d: FID %.4g (bootstrap std %s), spread %.4g (of the %d lowest-FID epochs)",
                best["epoch"],
                best["fid"],
                _number(best["fid_std"]) if _finite(best.get("fid_std")) else "unknown",
                best["spread"],
                self.top_k,
            )
            if not within_brightness(best, self.brightness_range):
                log.warning(
                    "best epoch %d: no epoch had particles and background within the allowed range of the real "
                    "ones' grey (%s) with the real contrast direction (this one: particles %s x, background %s x, "
                    "contrast %s, whole image %s x); check the material (polarity, lights, limits) before "
                    "generating data from it",
                    best["epoch"],
                    _range_text(self.brightness_range),
                    *(_number(best.get(k)) for k in ("particle_brightness", "background_brightness", "contrast")),
                    _number(best.get("brightness")),
                )

    def state_dict(self) -> dict:
        return {"history": [dict(h) for h in self.history]}

    def load_state_dict(self, state_dict: dict) -> None:
        self.history = [dict(h) for h in state_dict.get("history", [])]
