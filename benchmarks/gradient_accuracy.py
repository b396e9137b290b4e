"""Gradient accuracy against spp: bias and spread of each learned parameter's gradient.

    python benchmarks/gradient_accuracy.py                      # 64 px, spp 1 4 16 64, reference spp 256 x 16 seeds
    python benchmarks/gradient_accuracy.py --resolution 128 --spp 1 4 16 64 121 --seeds 16
    python benchmarks/gradient_accuracy.py --integrator prb_basic --grad-seed same   # one estimator only

For each spp, the gradient of a fixed loss (a random linear functional of the image, the same for every
run) is estimated with --seeds independent seeds. The reference is the mean over --ref-seeds seeds at
--ref-spp. Reported per parameter, relative to the reference's magnitude:
bias = |mean - reference| / |reference|, spread = std over seeds / |reference|.
A GAN step sees one seed: ``spread`` is the relative noise of one step's gradient.
The loss is linear, so both ``renderer.grad_seed`` estimators are unbiased for it and the reference is the
same; they differ in spread (the "same" replay correlates the adjoint with the image it differentiates, which
a linear loss does not use). One table per --grad-seed value; grad_spp = spp.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

from drgan.scene import layout, particle_meshes
from drgan.scene.config import SecondaryImaging
from drgan.scene.placements import PoissonAgglomerates
from drgan.scene.scene import GRAD_SEEDS, INTEGRATORS, ParticleScene, RenderSettings, SceneSpec
from drgan.scene.sizes import LognormalSize

PARTICLE = {name: {"min": 0.01, "max": 5.0} for name in ("roughness", "base_color", "sheen", "sheen_tint", "spec_tint")}
STAGE = {"base_color": {"min": 0.01, "max": 0.4}}
VALUES = torch.tensor([0.2, 0.5, 0.8, 0.3, 0.4, 0.6])


def gradients(scene: ParticleScene, weight: torch.Tensor, spp: int, seeds) -> np.ndarray:
    rows = []
    for seed in seeds:
        x = VALUES.clone().requires_grad_(True)
        (scene.render(x, seed=seed, spp=spp) * weight).mean().backward()
        rows.append(x.grad.numpy().copy())
    return np.array(rows)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--spp", type=int, nargs="+", default=[1, 4, 16, 64])
    parser.add_argument("--seeds", type=int, default=12)
    parser.add_argument("--ref-spp", type=int, default=256)
    parser.add_argument("--ref-seeds", type=int, default=16)
    parser.add_argument("--particles", type=int, default=40)
    parser.add_argument("--integrator", choices=INTEGRATORS, default="prb")
    parser.add_argument(
        "--grad-seed",
        choices=GRAD_SEEDS,
        nargs="+",
        default=list(GRAD_SEEDS),
        help="renderer.grad_seed value(s): one table each",
    )
    args = parser.parse_args()

    meshes_ = particle_meshes.generate_meshes("cube", 40, seed=0)
    phi = layout.sample_layouts(1, args.particles, LognormalSize(24.0, 0.25), PoissonAgglomerates(), seed=1)[0]
    weight = torch.rand(args.resolution, args.resolution, generator=torch.Generator().manual_seed(0))
    print(f"command: python {' '.join(sys.argv)}")
    for grad_seed in args.grad_seed:
        spec = SceneSpec(
            SecondaryImaging(particle_bsdf=PARTICLE, stage_bsdf=STAGE).material_parameters({"min": 0.001, "max": 0.1}),
            RenderSettings(resolution=args.resolution, spp=16, integrator=args.integrator, grad_seed=grad_seed),
        )
        scene = ParticleScene(meshes_, args.particles, spec)
        scene.set_layout(phi)
        reference = gradients(scene, weight, args.ref_spp, range(10_000, 10_000 + args.ref_seeds)).mean(0)
        names = [p.key for p in scene.learned]
        print(
            f"\n{args.integrator}, grad_seed {grad_seed}; reference: spp {args.ref_spp} x {args.ref_seeds} seeds; "
            f"{args.resolution} px, {args.particles} particles\n"
        )
        print("| spp | " + " | ".join(f"{n} bias / spread" for n in names) + " |")
        print("|---|" + "---|" * len(names))
        for spp in args.spp:
            g = gradients(scene, weight, spp, range(args.seeds))
            scale = np.abs(reference) + 1e-12
            bias = np.abs(g.mean(0) - reference) / scale
            spread = g.std(0, ddof=1) / scale
            cells = [
                ("n/a (zero)" if abs(r) < 1e-9 else f"{b:.3f} / {s:.3f}") for b, s, r in zip(bias, spread, reference)
            ]
            print(f"| {spp} | " + " | ".join(cells) + " |", flush=True)
        print("\nreference gradients: " + ", ".join(f"{n}={r:.3g}" for n, r in zip(names, reference)))


if __name__ == "__main__":
    main()
