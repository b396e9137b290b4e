"""One DiffRenderGAN training iteration and one FID pass, timed part by part (TiO2 SEM config, 40 particles).

    python benchmarks/train_step.py                     # 256 px, batch 1, spp 16 and 121, FID pass over 124 images
    python benchmarks/train_step.py --spp 4 16 --fid-images 0
    python benchmarks/train_step.py --spp 16 121 --grad-spp 0 4 16 --fid-images 0   # 0: adjoint at the image's spp

An iteration: render (G forward), D step (forward on real and fake, backward, Adam), G step (D forward on the
fake, backward through D and the renderer's adjoint pass, Adam). Median of --steps after --warmup steps.
The FID pass renders --fid-images images without gradients and extracts their Inception features.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

from drgan.models.gan_module import GANModule

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from conftest import compose  # noqa: E402


def time_iteration(module: GANModule, steps: int, warmup: int) -> dict[str, float]:
    opt_g = torch.optim.Adam(module.generator.parameters(), lr=2e-4, betas=(0.5, 0.999))
    opt_d = torch.optim.Adam(module.discriminator.parameters(), lr=1e-4, betas=(0.5, 0.999))
    size = module.generator.scene.spec.render.resolution
    real = torch.rand(1, 1, size, size)
    parts: dict[str, list[float]] = {"render": [], "d_step": [], "g_step": [], "iteration": []}
    for step in range(warmup + steps):
        t0 = time.perf_counter()
        fake, _ = module.render(module.draw_phi(1))
        t1 = time.perf_counter()
        opt_d.zero_grad()
        d_loss = 0.5 * (module.adversarial_loss(module.discriminator(real), True) + module.adversarial_loss(module.discriminator(fake.detach()), False))
        d_loss.backward()
        opt_d.step()
        t2 = time.perf_counter()
        opt_g.zero_grad()
        module.adversarial_loss(module.discriminator(fake), True).backward()
        opt_g.step()
        t3 = time.perf_counter()
        if step >= warmup:
            for key, value in zip(parts, (t1 - t0, t2 - t1, t3 - t2, t3 - t0)):
                parts[key].append(value)
    return {key: statistics.median(values) for key, values in parts.items()}


def time_fid_pass(module: GANModule, n_images: int) -> tuple[float, float]:
    from drgan.metrics.fid import InceptionFeatures

    extractor = InceptionFeatures(batch_size=16)
    extractor.features(np.zeros((2, 64, 64), np.float32))  # load the network outside the timing
    start = time.perf_counter()
    images = np.stack([module.generator.sample(module.phi_bank[i % len(module.phi_bank)]).image for i in range(n_images)])
    rendered = time.perf_counter()
    extractor.features(images)
    return rendered - start, time.perf_counter() - rendered


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--spp", type=int, nargs="+", default=[16, 121])
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--fid-images", type=int, default=124)
    parser.add_argument("--grad-spp", type=int, nargs="+", default=[0],
                        help="spp of the adjoint pass (renderer.grad_spp); 0 = the image's spp; skipped when > spp")
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, torch threads {torch.get_num_threads()}")
    print(f"command: python {' '.join(sys.argv)}\n")
    print("| spp | grad_spp | resolution | render s | D step s | G step (incl. adjoint render) s | iteration s |")
    print("|---|---|---|---|---|---|---|")
    module = None
    for spp in args.spp:
        for grad_spp in args.grad_spp:
            if grad_spp > spp:
                continue
            grad = grad_spp or spp
            cfg = compose(["material=tio2_sem", f"renderer.spp={spp}", f"renderer.grad_spp={grad}",
                           f"renderer.resolution={args.resolution}"], config_name="train")
            module = GANModule(cfg, m=124, base_dir=str(ROOT))
            t = time_iteration(module, args.steps, args.warmup)
            print(f"| {spp} | {grad} | {args.resolution} | {t['render']:.3f} | {t['d_step']:.3f} | {t['g_step']:.3f} | "
                  f"{t['iteration']:.3f} |", flush=True)
    if args.fid_images and module is not None:
        render_s, inception_s = time_fid_pass(module, args.fid_images)
        print(f"\nFID pass, {args.fid_images} images at spp {args.spp[-1]}: render {render_s:.1f} s + Inception {inception_s:.1f} s "
              f"= {render_s + inception_s:.1f} s")


if __name__ == "__main__":
    main()
