"""What one sample of a training render costs, step by step, and what the scene's representation changes.

    python benchmarks/render_parts.py                  # TiO2 SEM scene (40 potatoes), 256 px, spp 16
    python benchmarks/render_parts.py --repeats 8      # more alternating repeats of the passes

Two tables, CPU seconds (all threads of the process), median of --repeats:

1. Each step of ``direct_light_mis``'s sample run alone over the 1M samples of one render (its inputs
   evaluated beforehand): the camera ray (Embree's hit only, then with the surface interaction the BSDF
   reads), the emitter sample and its shadow ray, the BSDF sample and evaluation, and the BSDF-sampled ray
   traced for every sample or only where it hits the emitters' geometry (emitter culling). Steps run alone
   also write their outputs to memory, so their sum exceeds the fused render's time; the table says where
   the time goes, not what each step costs inside the fused kernel.
2. The primal render and the adjoint pass, alternating in one process, for the scene as drgan builds it
   (stage and top light as two triangles each, emitter culling on), with culling off, and with the stage and
   top light as Mitsuba ``rectangle`` shapes (as drgan built them before: the same surface, with the shape's own
   interaction and sampling code), with the image means (the same scene in expectation).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np
import torch

import drgan
from drgan.core.backend import dr, mi
from drgan.launch.configs import compose
from drgan.models.gan_module import GANModule
from drgan.scene import scene as scene_module

ROOT = Path(drgan.__file__).resolve().parents[2]


def cpu_seconds(fn, repeats: int) -> float:
    """Median CPU seconds of ``fn`` evaluated (Dr.Jit launches asynchronously: wait for it)."""
    times = []
    for _ in range(repeats):
        start = time.process_time()
        dr.eval(fn())
        dr.sync_thread()
        times.append(time.process_time() - start)
    return statistics.median(times)


def as_rectangle(name, to_world, props=None):
    """drgan's former stage and top light: Mitsuba rectangles (the old `_scene_dict`), for the comparison."""
    shape = {"type": "rectangle", "id": name, "to_world": to_world}
    for key in ("bsdf", "emitter"):
        if props is not None and key in props:
            shape[key] = props[key]
    return shape


def build(args, rectangles: bool = False) -> GANModule:
    cfg = compose(
        ["material=tio2_sem", f"renderer.spp={args.spp}", f"renderer.grad_spp={args.spp}"], config_name="train"
    )
    original = scene_module.rectangle_mesh
    if rectangles:
        scene_module.rectangle_mesh = as_rectangle
    try:
        return GANModule.from_config(cfg, m=8, base_dir=str(ROOT))
    finally:
        scene_module.rectangle_mesh = original


def steps_table(module: GANModule, phi, values, repeats: int) -> None:
    generator = module.generator
    with torch.no_grad():
        generator.render_one(phi[0], values)  # poses the layout and writes the values into the scene
    scene = generator.scene.scene
    integrator, sensor = scene.integrator(), scene.sensors()[0]
    rows = []
    with dr.suspend_grad():
        sampler, _ = integrator.prepare(sensor, 1, module.generator.scene.spec.render.spp, [])
        ray, _, _ = integrator.sample_rays(scene, sensor, sampler)
        n = dr.width(ray)
        u1, u2 = sampler.next_1d(), sampler.next_2d()
        u3 = sampler.next_2d()
        si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=True)
        valid = si.is_valid()
        ctx, bsdf = mi.BSDFContext(), si.bsdf(ray)
        ds, _ = scene.sample_emitter_direction(si, u2, False, valid)
        bs, _ = bsdf.sample(ctx, si, u1, u3, valid)
        ray_b = si.spawn_ray(si.to_world(bs.wo))
        active_b = valid & (bs.pdf > 0)
        shadow = si.spawn_ray_to(ds.p)
        emitters = integrator._emitter_geometry(scene)
        dr.eval(ray, u1, u2, u3, si, ds, bs, ray_b, active_b, shadow)
        dr.sync_thread()

        def culled():
            hit = emitters.ray_test(ray_b, False, active_b)
            return scene.ray_intersect(ray_b, ray_flags=mi.RayFlags.Minimal, coherent=False, active=active_b & hit)

        steps = [
            ("camera ray: Embree's hit only", lambda: scene.ray_intersect_preliminary(ray, coherent=True).t),
            ("camera ray: with the surface interaction", lambda: scene.ray_intersect(ray, mi.RayFlags.All, True)),
            ("emitter sample (no shadow ray)", lambda: scene.sample_emitter_direction(si, u2, False, valid)[1]),
            ("shadow ray", lambda: scene.ray_test(shadow, False, valid & (ds.pdf > 0))),
            ("BSDF sample", lambda: bsdf.sample(ctx, si, u1, u3, valid)[1]),
            ("BSDF evaluation and pdf (light direction)", lambda: bsdf.eval_pdf(ctx, si, si.to_local(ds.d), valid)),
            (
                "BSDF-sampled ray, every one",
                lambda: scene.ray_intersect(ray_b, ray_flags=mi.RayFlags.Minimal, coherent=False, active=active_b),
            ),
            ("BSDF-sampled ray, culled (emitter test + hits)", culled),
        ]
        for label, fn in steps:
            rows.append((label, cpu_seconds(fn, repeats)))
        hit = emitters.ray_test(ray_b, False, active_b)
        share = dr.count(hit & active_b)[0] / max(dr.count(active_b)[0], 1)
    print(f"Steps alone over {n} samples (CPU s, median of {repeats}):\n")
    print("| step | CPU s |\n|---|---|")
    for label, seconds in rows:
        print(f"| {label} | {seconds:.3f} |")
    print(f"\nBSDF-sampled rays that hit the emitters' geometry (traced on): {share:.2f}\n")


def passes_table(modules: dict[str, tuple[GANModule, bool]], phi, values, repeats: int) -> None:
    measured = {name: [] for name in modules}
    means = {name: [] for name in modules}
    for repeat in range(repeats + 1):  # the first round warms every kernel cache
        for name, (module, culling) in modules.items():
            generator = module.generator
            generator.scene.scene.integrator().emitter_culling = culling
            theta = values.clone().requires_grad_(True)
            start = time.process_time()
            image = generator.render_one(phi[0], theta, seed=1000 + repeat)
            primal = time.process_time() - start
            start = time.process_time()
            (image * torch.linspace(0.5, 1.5, image.shape[-1])).sum().backward()
            adjoint = time.process_time() - start
            if repeat:
                measured[name].append((primal, adjoint))
                means[name].append(float(image.detach().mean()))
    print(f"Primal and adjoint passes, alternating (CPU s, median of {repeats}):\n")
    print("| scene | primal | adjoint | both | against rectangles | image mean |\n|---|---|---|---|---|---|")
    base = None
    for name, rows in measured.items():
        primal = statistics.median(r[0] for r in rows)
        adjoint = statistics.median(r[1] for r in rows)
        base = base or primal + adjoint
        print(
            f"| {name} | {primal:.3f} | {adjoint:.3f} | {primal + adjoint:.3f} | "
            f"{(primal + adjoint) / base:.3f} | {np.mean(means[name]):.4f} |"
        )


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=4)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; drgan: {ROOT}")
    print(f"scene: TiO2 SEM, 256 px, spp {args.spp} (adjoint too), direct_light_mis\n")
    triangles = build(args)
    rectangles = build(args, rectangles=True)
    torch.manual_seed(0)
    phi = triangles.draw_phi(1)
    values = triangles.generator.learned_values(phi).detach()[0]
    steps_table(triangles, phi, values, args.repeats)
    modules = {
        "rectangles (before), no culling": (rectangles, False),
        "triangles, no culling": (triangles, False),
        "triangles, emitter culling (default)": (triangles, True),
    }
    passes_table(modules, phi, values, args.repeats)


if __name__ == "__main__":
    main()
