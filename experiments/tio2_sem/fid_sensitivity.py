"""What the FID against the real TiO2 SEM training patches sees, and what it hardly sees.

    python experiments/tio2_sem/fid_sensitivity.py [PATCHSET_DIR]

Transforms the real patches (or replaces them) and prints the FID (TF-Inception, as in training) of each
result against the unchanged real patches. PATCHSET_DIR: the patches folder of a training run (default
multirun/tio2_sem/spp_sweep/0/patches).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from drgan.data.patches import PatchSet
from drgan.metrics.feature_distances import FeatureStats
from drgan.metrics.inception import InceptionFeatures


def main(patchset: Path) -> None:
    patches = PatchSet.load(patchset)
    real = patches.train.astype(np.float32)
    rng = np.random.default_rng(0)
    extractor = InceptionFeatures(batch_size=16)
    reference = FeatureStats.from_features(extractor.features(real))
    n = len(real)
    variants = {
        "real x 0.5 (2x darker)": real * 0.5,
        "real x 0.25 (4x darker)": real * 0.25,
        "real squared (gamma 2)": real**2,
        "real background patches (no particles)": patches.background[:n],
        "real pixels shuffled within each patch": rng.permuted(real.reshape(n, -1), axis=1).reshape(real.shape),
        "uniform grey 0.187 + N(0, 0.03)": 0.187 + rng.normal(0, 0.03, real.shape),
        "black 0.02 + N(0, 0.01)": 0.02 + rng.normal(0, 0.01, real.shape),
    }
    print(f"{n} real patches, mean grey {real.mean():.3f}\n\n| set | FID against the real patches |\n|---|---|")
    for name, images in variants.items():
        fid = FeatureStats.from_features(extractor.features(np.clip(images, 0, 1).astype(np.float32))).fid(reference)
        print(f"| {name} | {fid:.1f} |", flush=True)


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("multirun/tio2_sem/spp_sweep/0/patches"))
