"""Per-epoch pictures of a run, in ``<run>/plots/`` and as MLflow artifacts (``plots/``):

- ``params_epoch_XXX.png``: a histogram of each learned parameter over ``n_phi`` constellations, x axis
  spanning the parameter's configured limits; ``fid.png``: the FID curve so far (from the FIDCallback).
- ``samples_epoch_XXX.png``: ``n`` synthetic samples (top row) above ``n`` real patches (bottom row).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from lightning.pytorch import Callback, LightningModule, Trainer

from drgan.callbacks.fid import FIDCallback, log_artifact, real_patches, render_samples, run_dir
from drgan.core.errors import ConfigError
from drgan.core.io import write_with

# Sample-grid renders: seeds of their own (see drgan.callbacks.fid.FID_SEED_BASE).
GRID_SEED_BASE = 0x6A1D0000


def save_figure(fig, path: Path) -> None:
    """Save a matplotlib figure as PNG atomically and close it."""
    import matplotlib.pyplot as plt

    try:
        write_with(path, lambda handle: fig.savefig(handle, format="png", dpi=100))
    finally:
        plt.close(fig)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)  # no display on cluster nodes; a no-op when already chosen
    import matplotlib.pyplot as plt

    return plt


def plot_parameter_histograms(values: np.ndarray, learned, title: str):
    plt = _pyplot()
    k = len(learned)
    cols = min(k, 3) or 1
    rows = max(1, -(-k // cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 2.8 * rows), squeeze=False)
    for j, p in enumerate(learned):
        ax = axes[j // cols][j % cols]
        ax.hist(values[:, j], bins=40, range=(p.low, p.high), color="tab:blue")
        ax.set_xlim(p.low, p.high)
        ax.set_title(p.key, fontsize=9)
    for j in range(k, rows * cols):
        axes[j // cols][j % cols].axis("off")
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def plot_fid_curve(history: list[dict]):
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5, 3.2))
    full = [h for h in history if math.isfinite(h["fid"])]
    ax.plot([h["epoch"] for h in full], [h["fid"] for h in full], marker="o", label="FID")
    screened = [h["epoch"] for h in history if not math.isfinite(h["fid"])]
    if screened:  # the KID screen found them no better: no full FID (drgan.callbacks.fid)
        ax.plot(
            screened,
            [max((h["fid"] for h in full), default=0.0)] * len(screened),
            "x",
            color="grey",
            label="screened out (KID)",
        )
        ax.legend(fontsize=7)
    ax.set_xlabel("epoch")
    ax.set_ylabel("FID")
    fig.tight_layout()
    return fig


def plot_sample_grid(fake: np.ndarray, real: np.ndarray, title: str):
    plt = _pyplot()
    n = max(len(fake), len(real), 1)
    fig, axes = plt.subplots(2, n, figsize=(1.6 * n, 3.6), squeeze=False)
    for row, (images, label) in enumerate(((fake, "synthetic"), (real, "real"))):
        for i in range(n):
            ax = axes[row][i]
            ax.axis("off")
            if i < len(images):
                ax.imshow(images[i], cmap="gray", vmin=0.0, vmax=1.0)  # linear grey in [0, 1]
        axes[row][0].set_title(label, fontsize=9, loc="left")
    fig.suptitle(title)
    fig.tight_layout()
    return fig


class ParameterHistogramCallback(Callback):
    """n_phi: constellations (drawn once, fixed seed) whose learned parameters are histogrammed."""

    def __init__(self, n_phi: int = 1000, seed: int = 0):
        if int(n_phi) < 1:
            raise ConfigError(f"ParameterHistogramCallback.n_phi={n_phi}: expected >= 1")
        self.n_phi, self.seed = int(n_phi), int(seed)
        self._phi: np.ndarray | None = None

    def on_train_epoch_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        if not trainer.is_global_zero:
            return
        epoch = trainer.current_epoch
        if self._phi is None:
            self._phi = pl_module.sample_phi(self.n_phi, seed=self.seed)
        plots = run_dir(trainer) / "plots"
        learned = pl_module.generator.learned
        if learned:
            path = plots / f"params_epoch_{epoch:03d}.png"
            save_figure(
                plot_parameter_histograms(pl_module.parameter_samples(self._phi), learned, f"epoch {epoch}"), path
            )
            log_artifact(trainer, path, "plots")
        fid_callback = next((c for c in trainer.callbacks if isinstance(c, FIDCallback)), None)
        if fid_callback is not None and fid_callback.history:
            path = plots / "fid.png"
            save_figure(plot_fid_curve(fid_callback.history), path)
            log_artifact(trainer, path, "plots")


class SampleGridCallback(Callback):
    """n: synthetic samples (first n constellations of the phi bank, fixed seeds) and real patches shown."""

    def __init__(self, n: int = 8):
        if int(n) < 1:
            raise ConfigError(f"SampleGridCallback.n={n}: expected >= 1")
        self.n = int(n)

    def on_train_epoch_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        if not trainer.is_global_zero:
            return
        epoch = trainer.current_epoch
        fake = render_samples(pl_module, self.n, GRID_SEED_BASE)
        real = real_patches(trainer)
        real = real[np.linspace(0, len(real) - 1, min(self.n, len(real))).astype(int)]
        path = run_dir(trainer) / "plots" / f"samples_epoch_{epoch:03d}.png"
        save_figure(plot_sample_grid(fake, real, f"epoch {epoch}"), path)
        log_artifact(trainer, path, "plots")
