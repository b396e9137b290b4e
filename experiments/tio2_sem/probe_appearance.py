"""FID of hand-set scene parameters (no GAN) against the real TiO2 SEM training patches.

    python experiments/tio2_sem/probe_appearance.py NAME [param=value ...] [-- hydra overrides ...]
    python experiments/tio2_sem/probe_appearance.py potato_band16 -- material.meshes.kind=potato renderer.spp=16

What a scene can reach before any training: the same phi bank (seed 7) and fixed BSDF values for every
image, as many images as real patches, TF-Inception FID. Used to find what separates our renders from the
real images (particle shape, Monte Carlo noise, light geometry; experiments/tio2_sem/README.md). Appends a
line to --results (default runs/probe_appearance.tsv). PATCHES (env) is a PatchSet folder written by a
training run (default runs/tio2_sem/tio2_sem_spp16_spheres/patches).
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir

import drgan  # noqa: F401  (registers the config resolvers)
from drgan.data.patches import PatchSet
from drgan.metrics.fid import FeatureStats, InceptionFeatures
from drgan.models.build import build_scene, sample_phi
from drgan.models.generator import add_noise

ROOT = Path(__file__).resolve().parents[2]
DEFAULTS = {
    "stage.base_color": 0.15,
    "particle.roughness": 0.5,
    "particle.base_color": 1.0,
    "particle.sheen": 0.5,
    "particle.sheen_tint": 0.5,
    "particle.spec_tint": 0.5,
    "sigma": 0.01,
}


def main(argv: list[str]) -> None:
    name, rest = argv[0], argv[1:]
    split = rest.index("--") if "--" in rest else len(rest)
    values = {**DEFAULTS, **{k: float(v) for k, v in (a.split("=", 1) for a in rest[:split])}}
    overrides = rest[split + 1 :]
    with initialize_config_dir(str(ROOT / "src" / "drgan" / "conf"), version_base="1.3"):
        cfg = compose("train", ["experiment=tio2_sem", *overrides])
    real = PatchSet.load(os.environ.get("PATCHES", ROOT / "runs/tio2_sem/tio2_sem_spp16_spheres/patches")).train
    extractor = InceptionFeatures(batch_size=16)
    real_stats = FeatureStats.from_features(extractor.features(real))
    scene = build_scene(cfg, base_dir=ROOT)
    bsdf = torch.tensor([values[f"{p.surface}.{p.name}"] for p in scene.learned_bsdf])
    start, images = time.perf_counter(), []
    for i, phi in enumerate(sample_phi(cfg, len(real), seed=7)):
        scene.set_layout(phi)
        with torch.no_grad():
            images.append(add_noise(scene.render(bsdf, seed=1000 + i), torch.tensor(values["sigma"])).numpy())
    images = np.stack(images)
    fid = FeatureStats.from_features(extractor.features(images)).fid(real_stats)
    changed = {k: v for k, v in values.items() if DEFAULTS.get(k) != v}
    line = f"{name}\tFID {fid:.1f}\trender {time.perf_counter() - start:.0f}s\t{json.dumps(changed)}\t{' '.join(overrides)}"
    print(line)
    results = ROOT / "runs" / "probe_appearance.tsv"
    results.parent.mkdir(parents=True, exist_ok=True)
    with open(results, "a") as handle:
        handle.write(line + "\n")


if __name__ == "__main__":
    main(sys.argv[1:])
