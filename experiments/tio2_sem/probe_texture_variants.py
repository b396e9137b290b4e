"""More stage-texture variants on the renders that probe_texture.py kept (sixth session).

    python experiments/tio2_sem/probe_texture_variants.py

v4: extra Gaussian noise of the real background's std on the stage (no texture); v5: 1.41 x sigma
everywhere; v1b: v1 with other patches; v6: the patch minus its 8 px Gaussian blur (what
material.background_texture does); v7: the texture on particles too.
"""

import os
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import gaussian_filter

from drgan.data.patches import PatchSet
from drgan.metrics.feature_distances import FeatureStats
from drgan.metrics.inception import InceptionFeatures
from drgan.models.generator import add_noise

ps = PatchSet.load(
    os.environ.get("PATCHES", Path(__file__).resolve().parents[2] / "runs/tio2_sem/r5_n20_decay/patches")
)
real, bgs = ps.train, ps.background.astype(np.float32)
ex = InceptionFeatures(batch_size=16)
rs = FeatureStats.from_features(ex.features(real))
d = np.load("/tmp/probe_bg_renders.npz")
clean, labels = d["clean"], d["labels"]
sig = 0.0392


def fid(imgs):
    return FeatureStats.from_features(ex.features(np.stack(imgs).astype(np.float32))).fid(rs)


def noisy(c, i, s):
    return add_noise(torch.from_numpy(c), torch.tensor(s), seed=1000 + i).numpy()


g = np.random.default_rng(11)


def hp(b):
    return b - gaussian_filter(b, 8)


print(
    "bg std",
    bgs.std(),
    "bg highpass(8) std",
    np.std([hp(b) for b in bgs[:50]]),
    "bg lowpass std",
    np.std([gaussian_filter(b, 8) - b.mean() for b in bgs[:50]]),
)
for name, fn in [
    (
        "v4 extra gaussian noise 0.035 on stage",
        lambda c, l, i: noisy(c, i, sig) + g.normal(0, 0.035, c.shape) * (l == 0),
    ),
    ("v5 sigma x1.41 everywhere", lambda c, l, i: noisy(c, i, sig * 1.414)),
    (
        "v1b raw bg texture, other picks",
        lambda c, l, i: noisy(c, i, sig) + (bgs[g.integers(len(bgs))] - bgs.mean()) * (l == 0),
    ),
    ("v6 highpass bg texture (sigma 8)", lambda c, l, i: noisy(c, i, sig) + hp(bgs[g.integers(len(bgs))]) * (l == 0)),
    (
        "v7 raw bg texture everywhere (particles too)",
        lambda c, l, i: noisy(c, i, sig) + (bgs[g.integers(len(bgs))] - bgs.mean()),
    ),
]:
    print(name, round(fid([np.clip(fn(c, l, i), 0, 1) for i, (c, l) in enumerate(zip(clean, labels))]), 1), flush=True)
