"""What the FID of a trained TiO2 SEM generator owes to content (particle shape, count) rather than the GAN.

    python experiments/tio2_sem/ablate_content.py runs/tio2_sem/tio2_sem_spp16/checkpoints/last.ckpt

Keeps the checkpoint's FCN (learned parameters) and phi bank, swaps the particle meshes or hides half of the
particles, renders as many images as real training patches (spp 4: FID hardly depends on spp, see
benchmarks/fid_vs_spp.py) and scores them against the real training patches.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from drgan.data.patches import PatchSet
from drgan.metrics.feature_distances import FeatureStats
from drgan.metrics.inception import InceptionFeatures
from drgan.models.gan_module import GANModule
from drgan.scene import particle_meshes
from drgan.scene.scene import ParticleScene


def main(ckpt: Path) -> None:
    real = PatchSet.load(ckpt.resolve().parents[1] / "patches").train
    extractor = InceptionFeatures(batch_size=16)
    real_stats = FeatureStats.from_features(extractor.features(real))
    module = GANModule.load_from_checkpoint(ckpt, map_location="cpu")
    module.eval()
    generator, n = module.generator, module.generator.scene.n_particles
    spec = replace(generator.scene.spec, render=replace(generator.scene.spec.render, spp=4))

    def fid(unit_meshes, phis) -> float:
        generator.scene = ParticleScene(unit_meshes, n, spec)
        images = np.stack([generator.sample(phis[i], seed=10_000 + i).image for i in range(len(real))])
        return FeatureStats.from_features(extractor.features(images)).fid(real_stats)

    cubes = particle_meshes.generate_meshes("cube", n, 0)
    sparse = module.phi_bank.clone()
    sparse[:, n // 2 :, :2] += 10_000  # half of the particles far outside the view
    rows = {
        "deformed cubes (as trained)": fid(cubes, module.phi_bank),
        "rounder cubes (displacement 0.2, 60 smoothing passes)": fid(
            particle_meshes.generate_meshes("cube", n, 0, displacement=0.2, smoothing_iterations=60), module.phi_bank
        ),
        "spheres": fid(particle_meshes.generate_meshes("sphere", n, 0), module.phi_bank),
        f"deformed cubes, {n - n // 2} of {n} particles in view": fid(cubes, sparse),
    }
    print("| content | FID |\n|---|---|")
    for name, value in rows.items():
        print(f"| {name} | {value:.1f} |")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
