"""Figures and a summary for a recorded TiO2 SEM training run (synthetic images only: the real images are
licensed no-derivatives and stay out of the repository).

    python experiments/tio2_sem/make_figures.py runs/tio2_sem/tio2_sem_spp16 experiments/tio2_sem
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from drgan.models.gan_module import GANModule  # noqa: E402


def main(run: Path, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    best = json.loads((run / "checkpoints" / "best_epoch.json").read_text())
    history = best["history"]
    epochs = [h["epoch"] for h in history]
    fid = [h["fid"] for h in history]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(epochs, fid, marker="o")
    ax.axvline(best["epoch"], color="tab:red", ls="--", label=f"chosen epoch {best['epoch']}")
    ax.set_xlabel("epoch")
    ax.set_ylabel("FID (134 synthetic vs 134 real train patches)")
    bright = [h.get("brightness") for h in history]
    if all(b is not None for b in bright):  # runs since the brightness guard: mean grey synthetic / real
        twin = ax.twinx()
        twin.plot(epochs, bright, color="tab:grey", marker=".", ls=":", label="brightness (synthetic / real)")
        twin.set_ylabel("mean grey, synthetic / real", color="tab:grey")
        band = best.get("brightness_range")
        if isinstance(band, list):  # a fixed range; the derived one (a dict) is for particles and background apart
            twin.axhspan(*band, color="tab:grey", alpha=0.08)
    ax.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(out / "fid_curve.png", dpi=120)
    plt.close(fig)

    histogram = run / "plots" / f"params_epoch_{best['epoch']:03d}.png"
    if histogram.is_file():
        shutil.copyfile(histogram, out / "params_best_epoch.png")

    module = GANModule.load_from_checkpoint(run / "checkpoints" / "best.ckpt", map_location="cpu")
    module.eval()
    samples = [module.generator.sample(module.phi_bank[i], seed=1000 + i) for i in range(8)]
    fig, axes = plt.subplots(2, 8, figsize=(16, 4.4))
    for k, sample in enumerate(samples):
        axes[0, k].imshow(sample.image, cmap="gray", vmin=0, vmax=1)
        axes[1, k].imshow(sample.labels, cmap="nipy_spectral", interpolation="nearest")
        for row in (0, 1):
            axes[row, k].axis("off")
    axes[0, 0].set_title("synthetic image", loc="left")
    axes[1, 0].set_title("exact instance labels", loc="left")
    # The stage texture comes from the real images (licensed no-derivatives): these samples are rendered
    # without it (a module loaded from a checkpoint has none until use_background_texture), and say so.
    omitted = "; the stage texture of training (real background patches) is left out here" if module.textured else ""
    fig.suptitle(f"best epoch {best['epoch']} (FID {best['fid']:.1f}){omitted}")
    fig.tight_layout()
    fig.savefig(out / "samples_best_epoch.png", dpi=100)
    plt.close(fig)
    summary = {k: best[k] for k in ("epoch", "fid", "kid", "spread", "brightness", "brightness_range") if k in best}
    summary["fid_by_epoch"] = dict(zip(epochs, np.round(fid, 1).tolist()))
    if all(b is not None for b in bright):
        summary["brightness_by_epoch"] = dict(zip(epochs, np.round(bright, 3).tolist()))
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
