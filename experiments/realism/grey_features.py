"""Grey levels alone, on the same real patches, dataset draw and folds as `drgan.realism` seed 0: a logistic
regression on each patch's mean and 5/50/95 % grey quantiles, and on its high-pass noise level.
Run from the repository root after experiments/realism/run_tsem.sh (reads runs/realism/tsem_patches)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import ndimage as ndi
from sklearn.linear_model import LogisticRegression
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler

from drgan.data.patches import PatchSet
from drgan.metrics.two_sample import group_folds
from drgan.realism import dataset_images

FOLDS = 5


def features(patches: np.ndarray) -> dict[str, np.ndarray]:
    highpass = patches - ndi.gaussian_filter(patches, (0, 2, 2))
    quantiles = np.quantile(patches.reshape(len(patches), -1), [0.05, 0.5, 0.95], axis=1).T
    return {
        "grey (mean, p5, p50, p95)": np.c_[patches.mean((1, 2)), quantiles],
        "noise (high-pass std)": highpass.std((1, 2))[:, None],
    }


def main() -> None:
    patches = PatchSet.load("runs/realism/tsem_patches")
    real, ids = patches.train, patches.train_ids
    synthetic, names = dataset_images(Path("runs/tio2_tsem/synthetic"), len(real), 0)
    f_real, f_syn = features(real), features(synthetic)
    y = np.r_[np.zeros(len(real)), np.ones(len(synthetic))]
    fold = group_folds(y, [f"A:{i}" for i in ids] + [f"B:{n}" for n in names], FOLDS, 0)
    for key in [*f_real, "both"]:
        if key == "both":
            x = np.r_[np.hstack(list(f_real.values())), np.hstack(list(f_syn.values()))]
        else:
            x = np.r_[f_real[key], f_syn[key]]
        predicted = np.zeros(len(y))
        for f in range(FOLDS):
            model = make_pipeline(StandardScaler(), LogisticRegression()).fit(x[fold != f], y[fold != f])
            predicted[fold == f] = model.predict(x[fold == f])
        print(f"{key}: held-out accuracy {np.mean(predicted == y):.3f}")
    print(
        f"mean grey: real {real.mean():.3f} +- {real.mean((1, 2)).std():.3f}, "
        f"synthetic {synthetic.mean():.3f} +- {synthetic.mean((1, 2)).std():.3f}"
    )


if __name__ == "__main__":
    main()
