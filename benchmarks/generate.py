"""Generation throughput: image/mask pairs per minute, with render and label time apart.

    python benchmarks/generate.py                          # TiO2 SEM, 256 px, spp 121, 5 timed images
    python benchmarks/generate.py --spp 16 121 --images 10 --material tio2_him
    python benchmarks/generate.py --particles 40 20         # the material's paper count and experiment=tio2_sem's

Builds a freshly initialised GANModule from the material's training config (no checkpoint needed: the
FCN's weights do not change the cost), then does per image what drgan.generate does: draw a new phi,
render it without gradients (FCN + render + noise), label it (instance ids + 3-class mask), write the
three PNGs. One warm-up image per setting (kernel compilation) is not timed. No filter: every image counts.
Prints a markdown table (medians per image; pairs/minute from the mean total).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from drgan.core import io
from drgan.generate import index_seeds
from drgan.launch.configs import compose
from drgan.models import build
from drgan.models.gan_module import GANModule
from drgan.scene.labels import class_mask


def time_setting(
    material: str, spp: int, resolution: int, images: int, seed: int = 0, particles: int | None = None
) -> dict:
    overrides = [f"material={material}", f"renderer.spp={spp}", f"renderer.resolution={resolution}", f"seed={seed}"]
    if particles is not None:
        overrides.append(f"material.n_particles={particles}")
    cfg = compose(overrides, config_name="train")
    module = GANModule.from_config(cfg, m=1, base_dir=str(Path(__file__).resolve().parents[1])).eval()
    generator = module.generator
    contour_px = int(cfg.material.contour_px)
    layouts = build.layout_sampler(cfg)  # built once, as drgan.generate does
    times = {"phi": [], "render": [], "labels": [], "write": []}
    with tempfile.TemporaryDirectory() as out, torch.no_grad():
        for i in range(images + 1):
            seeds = index_seeds(seed, i)
            start = time.perf_counter()
            phi = torch.as_tensor(layouts(1, seed=seeds["phi"])[0], dtype=torch.float32)
            t_phi = time.perf_counter()
            values = generator.learned_values(phi.unsqueeze(0))[0]
            with torch.no_grad():
                image = generator.render_one(phi, values, seed=seeds["render"])[0].numpy()
            t_render = time.perf_counter()
            labels = generator.scene.instance_labels()
            mask = class_mask(labels, contour_px)
            t_labels = time.perf_counter()
            for kind, array in (("image", image), ("mask", mask), ("labels", labels)):
                io.write_png(Path(out) / f"{kind}_{i}.png", array)
            t_write = time.perf_counter()
            if i == 0:
                continue  # warm-up: kernel compilation
            times["phi"].append(t_phi - start)
            times["render"].append(t_render - t_phi)
            times["labels"].append(t_labels - t_render)
            times["write"].append(t_write - t_labels)
    total = np.sum([times[k] for k in times], axis=0)
    return {
        "material": material,
        "particles": int(cfg.material.n_particles),
        "resolution": resolution,
        "spp": spp,
        "images": images,
        **{f"{k}_s": statistics.median(v) for k, v in times.items()},
        "pairs_per_minute": 60.0 / float(np.mean(total)),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--material", default="tio2_sem")
    parser.add_argument("--spp", type=int, nargs="+", default=[121])
    parser.add_argument("--resolution", type=int, nargs="+", default=[256])
    parser.add_argument("--images", type=int, default=5, help="timed images per setting (after one warm-up)")
    parser.add_argument(
        "--particles", type=int, nargs="+", default=[None], help="particles per scene (default: the material's)"
    )
    args = parser.parse_args()
    if args.images < 1:
        parser.error("--images: expected >= 1")

    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch threads {torch.get_num_threads()}"
    )
    print(f"command: python {' '.join(sys.argv)}\n")
    print("| material | particles | resolution | spp | images | phi s | render s | labels s | write s | pairs/minute |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for resolution in args.resolution:
        for spp, particles in ((s, n) for s in args.spp for n in args.particles):
            r = time_setting(args.material, spp, resolution, args.images, particles=particles)
            print(
                f"| {r['material']} | {r['particles']} | {r['resolution']} | {r['spp']} | {r['images']} | {r['phi_s']:.3f} "
                f"| {r['render_s']:.3f} | {r['labels_s']:.3f} | {r['write_s']:.3f} | {r['pairs_per_minute']:.1f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
