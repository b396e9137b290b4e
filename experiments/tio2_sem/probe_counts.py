"""FID of fixed scene values with a variable particle count per constellation (sixth session).

    python experiments/tio2_sem/probe_counts.py 20 20     # every scene 20 particles: 100.4
    python experiments/tio2_sem/probe_counts.py 8 32      # 8-32 per scene: 99.3

The fourth-session generator's median values, spp 121, 134 images (as many as real patches) against the
real training patches of PATCHES (a run's patches/ folder). Written before `material.n_particles_min`
existed: the scene holds HI particles and the last n - k of each constellation are moved 10^4 px off view
(the library now zeroes them instead; `n_particles_min` draws its counts in another order).
"""

import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir

from drgan.data.patches import PatchSet
from drgan.metrics.fid import FeatureStats, InceptionFeatures
from drgan.models.build import build_scene, sample_phi
from drgan.models.generator import add_noise

ROOT = Path(__file__).resolve().parents[2]
lo, hi = int(sys.argv[1]), int(sys.argv[2])
vals = {
    "stage.base_color": 0.2937,
    "particle.roughness": 2.1357,
    "particle.base_color": 0.8208,
    "particle.sheen": 2.7366,
    "particle.sheen_tint": 2.4281,
    "particle.spec_tint": 2.725,
    "sigma": 0.0392,
}
with initialize_config_dir(str(ROOT / "src" / "drgan" / "conf"), version_base="1.3"):
    cfg = compose("train", ["experiment=tio2_sem", f"material.n_particles={hi}", "renderer.spp=121"])
real = PatchSet.load(os.environ.get("PATCHES", ROOT / "runs/tio2_sem/r5_n20_decay/patches")).train
ex = InceptionFeatures(batch_size=16)
rs = FeatureStats.from_features(ex.features(real))
scene = build_scene(cfg, base_dir=ROOT)
bsdf = torch.tensor([vals[f"{p.surface}.{p.name}"] for p in scene.learned_bsdf])
rng = np.random.default_rng(3)
t = time.perf_counter()
imgs = []
for i, phi in enumerate(sample_phi(cfg, len(real), seed=7)):
    k = rng.integers(lo, hi + 1)
    phi = phi.copy()
    phi[k:, 0] += 1e4
    scene.set_layout(phi)
    with torch.no_grad():
        imgs.append(add_noise(scene.render(bsdf, seed=1000 + i), torch.tensor(vals["sigma"]), seed=1000 + i).numpy())
fid = FeatureStats.from_features(ex.features(np.stack(imgs))).fid(rs)
print(f"count U[{lo},{hi}] FID {fid:.1f} render {time.perf_counter() - t:.0f}s", flush=True)
