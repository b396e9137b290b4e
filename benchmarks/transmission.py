"""Render + backward per iteration: the SEM scene (tio2_sem) against the transmission scene (tio2_tsem).

    python benchmarks/transmission.py                       # 256 px, 32 particles, 3 timed iterations after 1 warmup
    python benchmarks/transmission.py --resolution 128 --repeats 5
    python benchmarks/transmission.py --torch-threads 1   # torch's own threads (default: torch's choice)

Each iteration is what a generator step asks of the scene: a new layout (set_layout), the image (render) and
the gradient of a linear loss w.r.t. the learned parameters (backward). SEM: the material's settings (spp 121,
grad_spp 16, prb integrator); transmission: tio2_tsem's (spp 16 sub-pixel rays; its path lengths are traced
once per layout, which a new layout per iteration always pays: the "trace" column). Every scene holds all
n particles (material.n_particles_min=null), placed by the material's size and placement settings.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

from drgan.launch.configs import compose
from drgan.models import build

ROOT = Path(__file__).resolve().parents[1]


def time_scene(material: str, resolution: int, n_particles: int, repeats: int, warmup: int, variant: str) -> dict:
    cfg = compose(
        [
            f"material={material}",
            f"renderer.resolution={resolution}",
            f"material.n_particles={n_particles}",
            "material.n_particles_min=null",
            f"renderer.variant={variant}",
        ],
        config_name="train",
    )
    scene = build.build_scene(cfg)
    phis = build.sample_phi(cfg, warmup + repeats, seed=0)
    learned = scene.learned
    values = torch.tensor([0.5 * (p.low + p.high) for p in learned], requires_grad=True)
    weights = torch.linspace(-1.0, 1.0, resolution).expand(resolution, resolution)
    times: dict[str, list[float]] = {"layout": [], "trace": [], "render+backward": [], "iteration": []}
    for step, phi in enumerate(phis):
        t0 = time.perf_counter()
        scene.set_layout(phi)
        t1 = time.perf_counter()
        if hasattr(scene, "thickness"):
            scene.thickness()  # the transmission scene's per-layout trace, timed on its own
        t2 = time.perf_counter()
        values.grad = None
        (scene.render(values, seed=step) * weights).sum().backward()
        t3 = time.perf_counter()
        if step >= warmup:
            for key, value in zip(times, (t1 - t0, t2 - t1, t3 - t2, t3 - t0)):
                times[key].append(value)
    spec = scene.spec.render
    return {
        "material": material,
        "scene": type(scene).__name__,
        "settings": f"spp {spec.spp}"
        + (f", grad_spp {spec.grad_spp}, {spec.integrator}" if material != "tio2_tsem" else ""),
        **{key: statistics.median(value) for key, value in times.items()},
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--particles", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--variant", default="llvm_ad_rgb")
    parser.add_argument("--torch-threads", type=int, default=0, help="torch.set_num_threads; 0 = torch's default")
    args = parser.parse_args()
    if args.torch_threads > 0:
        torch.set_num_threads(args.torch_threads)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, torch threads {torch.get_num_threads()}")
    print(f"command: python {' '.join(sys.argv)}")
    print(f"{args.resolution} px, {args.particles} particles, median of {args.repeats} after {args.warmup} warmup\n")
    rows = [
        time_scene(m, args.resolution, args.particles, args.repeats, args.warmup, args.variant)
        for m in ("tio2_sem", "tio2_tsem")
    ]
    print("| scene | settings | set_layout (s) | trace (s) | render + backward (s) | iteration (s) |")
    print("| --- | --- | ---: | ---: | ---: | ---: |")
    for r in rows:
        print(
            f"| {r['scene']} ({r['material']}) | {r['settings']} | {r['layout']:.3f} | {r['trace']:.3f} | "
            f"{r['render+backward']:.3f} | {r['iteration']:.3f} |"
        )
    print(f"\nratio SEM / transmission, per iteration: {rows[0]['iteration'] / rows[1]['iteration']:.1f}x")


if __name__ == "__main__":
    main()
