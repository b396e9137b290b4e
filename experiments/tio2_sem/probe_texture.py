"""FID of fixed scene values with and without real background texture on the stage (sixth session).

    python experiments/tio2_sem/probe_texture.py
    python experiments/tio2_sem/probe_texture_variants.py    # more variants on the same renders

The fourth-session generator's median values, 8-32 particles per scene, spp 121, 134 images against the
real training patches of PATCHES (a run's patches/). Renders once (kept in /tmp/probe_bg_renders.npz with
their instance labels), then scores: no texture; a real background patch minus its mean on the stage
pixels (v1); the same blurred (v2); v1 without synthetic noise on the stage (v3).
"""

import os
import time
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import gaussian_filter

from drgan.configs import compose
from drgan.data.patches import PatchSet
from drgan.metrics.feature_distances import FeatureStats
from drgan.metrics.inception import InceptionFeatures
from drgan.models.build import build_scene, sample_phi
from drgan.models.generator import add_noise

ROOT = Path(__file__).resolve().parents[2]
vals = {
    "stage.base_color": 0.2937,
    "particle.roughness": 2.1357,
    "particle.base_color": 0.8208,
    "particle.sheen": 2.7366,
    "particle.sheen_tint": 2.4281,
    "particle.spec_tint": 2.725,
    "sigma": 0.0392,
}
cfg = compose(
    ["experiment=tio2_sem", "material.n_particles=32", "material.n_particles_min=8", "renderer.spp=121"],
    config_name="train",
)
ps = PatchSet.load(os.environ.get("PATCHES", ROOT / "runs/tio2_sem/r5_n20_decay/patches"))
real, bgs = ps.train, ps.background
ex = InceptionFeatures(batch_size=16)
rs = FeatureStats.from_features(ex.features(real))
scene = build_scene(cfg, base_dir=ROOT)
bsdf = torch.tensor([vals[f"{p.surface}.{p.name}"] for p in scene.learned])
rng = np.random.default_rng(3)
t = time.perf_counter()
clean, labels = [], []
for i, phi in enumerate(sample_phi(cfg, len(real), seed=7)):
    scene.set_layout(phi)
    with torch.no_grad():
        clean.append(scene.render(bsdf, seed=1000 + i).numpy())
    labels.append(scene.instance_labels())
print(
    f"render {time.perf_counter() - t:.0f}s; real bg mean {bgs.mean():.3f} std {bgs.std():.3f}; synth stage mean {np.mean([c[l == 0].mean() for c, l in zip(clean, labels)]):.3f}",
    flush=True,
)
np.savez("/tmp/probe_bg_renders.npz", clean=np.stack(clean), labels=np.stack(labels))


def fid(imgs):
    return FeatureStats.from_features(ex.features(np.stack(imgs).astype(np.float32))).fid(rs)


pick = rng.integers(0, len(bgs), len(clean))


def noisy(c, i, s):
    return add_noise(torch.from_numpy(c), torch.tensor(s), seed=1000 + i).numpy()


base = [noisy(c, i, vals["sigma"]) for i, c in enumerate(clean)]
print("baseline", round(fid(base), 1), flush=True)
for name, tex_fn, sigma in [
    ("v1 raw bg texture + noise", lambda b: b - b.mean(), vals["sigma"]),
    ("v2 blurred bg texture + noise", lambda b: gaussian_filter(b, 1.5) - b.mean(), vals["sigma"]),
    ("v3 raw bg texture, no synth noise on stage", lambda b: b - b.mean(), None),
]:
    out = []
    for i, (c, l) in enumerate(zip(clean, labels)):
        tex = tex_fn(bgs[pick[i]].astype(np.float32)) * (l == 0)
        if sigma is None:
            n = noisy(c, i, vals["sigma"])
            img = np.where(l == 0, c + tex, n)
        else:
            img = noisy(c, i, sigma) + tex
        out.append(np.clip(img, 0, 1))
    print(name, round(fid(out), 1), flush=True)
