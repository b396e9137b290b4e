"""Which light strengths make the grazing ring both realistic (FID) and as bright as the real images?

    python experiments/tio2_sem/probe_lights.py NAME [-- hydra overrides ...]
    python experiments/tio2_sem/probe_lights.py ring01 -- renderer.spp=16 \
        material.imaging.torus_light.height=0.1 material.imaging.torus_light.minor_radius=0.08

Light transport is linear in each emitter's radiance, so the scene is rendered once per light (ring alone at
radiance 1, top light alone at radiance 1; hand-set BSDF values of probe_appearance.py, phi bank seed 7) and
every (ring, top) radiance pair on a grid is the weighted sum of the two renders, then noise and clamp as in
training. Prints, per pair, the FID against the real training patches and the median particle and stage
grey (labels of the renders; real patches through the classical segmentation of the patch selection). The
FID hardly sees global brightness (the real patches x 0.25 score 57.7 against themselves), so it cannot
choose the radiance alone. Renders are cached in runs/probe_lights/NAME.npz.
"""

from __future__ import annotations

import itertools
import os
import sys
from pathlib import Path

import numpy as np
import torch

from drgan.configs import compose
from drgan.data.classical import segment_particles
from drgan.data.patches import PatchSet
from drgan.metrics.feature_distances import FeatureStats
from drgan.metrics.inception import InceptionFeatures
from drgan.models.build import build_scene, sample_phi
from drgan.models.generator import add_noise

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(Path(__file__).parent))
from probe_appearance import DEFAULTS  # noqa: E402

RINGS = (1.0, 2.0, 4.0, 6.0, 8.0)
TOPS = (0.0, 0.1, 0.3, 0.6)


def render_components(overrides: list[str], n: int) -> dict[str, np.ndarray]:
    out = {}
    for name, lights in (
        ("ring", ["material.imaging.top_light.radiance=0.0"]),
        ("top", ["material.imaging.torus_light.radiance=0.0", "material.imaging.top_light.radiance=1.0"]),
    ):
        cfg = compose(["experiment=tio2_sem", *overrides, *lights], config_name="train")
        scene = build_scene(cfg, base_dir=ROOT)
        bsdf = torch.tensor([DEFAULTS[f"{p.surface}.{p.name}"] for p in scene.learned])
        images, labels = [], []
        for i, phi in enumerate(sample_phi(cfg, n, seed=7)):
            scene.set_layout(phi)
            with torch.no_grad():
                images.append(scene.render(bsdf, seed=1000 + i).numpy())
            labels.append(scene.instance_labels())
            print(f"\r{name} {i + 1}/{n}", end="", flush=True)
        print()
        out[name], out["labels"] = np.stack(images), np.stack(labels)
    return out


def grey(images: np.ndarray, labels: np.ndarray) -> tuple[float, float]:
    particle = np.median([im[lab > 0].mean() for im, lab in zip(images, labels) if (lab > 0).any()])
    stage = np.median([im[lab == 0].mean() for im, lab in zip(images, labels)])
    return float(particle), float(stage)


def main(argv: list[str]) -> None:
    name, rest = argv[0], argv[1:]
    overrides = rest[rest.index("--") + 1 :] if "--" in rest else []
    real = PatchSet.load(os.environ.get("PATCHES", ROOT / "multirun/tio2_sem/spp_sweep/0/patches")).train
    cache = ROOT / "runs" / "probe_lights" / f"{name}.npz"
    if cache.exists():
        parts = dict(np.load(cache))
    else:
        parts = render_components(overrides, len(real))
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(cache.with_suffix(".tmp.npz"), **parts)
        os.replace(cache.with_suffix(".tmp.npz"), cache)
    extractor = InceptionFeatures(batch_size=16)
    real_stats = FeatureStats.from_features(extractor.features(real))
    p, s = grey(real, np.stack([segment_particles(x)[0] for x in real]))
    print(f"{name}: {' '.join(overrides)}\n\n| ring | top | FID | particle grey | stage grey |\n|---|---|---|---|---|")
    print(f"| real | | | {p:.3f} | {s:.3f} |")
    torch.manual_seed(0)
    for ring, top in itertools.product(RINGS, TOPS):
        image = torch.from_numpy(ring * parts["ring"] + top * parts["top"])
        noisy = add_noise(image, torch.tensor(DEFAULTS["sigma"])).numpy()
        fid = FeatureStats.from_features(extractor.features(noisy)).fid(real_stats)
        p, s = grey(noisy, parts["labels"])
        print(f"| {ring:g} | {top:g} | {fid:.1f} | {p:.3f} | {s:.3f} |", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
