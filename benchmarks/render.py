"""Render cost: seconds per forward and per forward+backward of the differentiable scene.

    python benchmarks/render.py                         # the issue's grid: 256 px, spp 1..121, 2 integrators, 10/40 particles
    python benchmarks/render.py --spp 16 --resolution 64 128 256 512 --particles 40
    python benchmarks/render.py --elements              # cost of each optional scene element (lights, stage, filter)
    python benchmarks/render.py --noise                 # Monte Carlo noise of particle pixels: integrator x ring light x spp

Prints a markdown table (median of --repeats timed runs after one warm-up) and, with --out, writes it
with the machine description. New layouts are drawn for every timed run, as in training.
"""

from __future__ import annotations

import argparse
import itertools
import os
import platform
import statistics
import sys
import time

import numpy as np
import torch

from drgan.scene import layout, particle_meshes
from drgan.scene.config import SecondaryImaging
from drgan.scene.placements import PoissonAgglomerates
from drgan.scene.scene import (
    ParticleScene,
    RenderSettings,
    SceneSpec,
    TopLight,
    TorusLight,
)
from drgan.scene.sizes import LognormalSize

PARTICLE = {name: {"min": 0.01, "max": 5.0} for name in ("roughness", "base_color", "sheen", "sheen_tint", "spec_tint")}
STAGE = {"base_color": {"min": 0.01, "max": 0.4}}
SIGMA = {"min": 0.001, "max": 0.1}


def make_scene(n, resolution, spp, integrator, variant, cube_meshes, **elements):
    spec = SceneSpec(
        SecondaryImaging(
            particle_bsdf=PARTICLE, stage_bsdf=STAGE if elements.get("stage", True) else None
        ).material_parameters(SIGMA),
        RenderSettings(
            resolution=resolution, spp=spp, integrator=integrator, filter_stddev=elements.get("filter_stddev", 0.5)
        ),
        view_width=256.0,
        stage=elements.get("stage", True),
        torus_light=elements.get("torus_light", TorusLight()),
        top_light=elements.get("top_light", TopLight()),
    )
    return ParticleScene(cube_meshes, n, spec, variant=variant)


def time_scene(scene, n, repeats, seed=0):
    sizes, placement = LognormalSize(24.0, 0.25), PoissonAgglomerates()
    phis = layout.sample_layouts(2 * repeats + 2, n, sizes, placement, view_width=256.0, seed=seed)
    values = torch.tensor([0.2, 0.5, 0.8, 0.3, 0.4, 0.6][: len(scene.learned)])
    forward, both = [], []
    for i, phi in enumerate(phis):
        scene.set_layout(phi)
        start = time.perf_counter()
        if i % 2 == 0:
            with torch.no_grad():
                scene.render(values, seed=i)
            forward.append(time.perf_counter() - start)
        else:
            x = values.clone().requires_grad_(True)
            scene.render(x, seed=i).square().mean().backward()
            both.append(time.perf_counter() - start)
    # Drop the warm-up (first of each kind: kernel compilation).
    return statistics.median(forward[1:]), statistics.median(both[1:])


def grid(args, cube_meshes):
    rows = []
    for variant, integrator, n, resolution, spp in itertools.product(
        args.variant, args.integrator, args.particles, args.resolution, args.spp
    ):
        scene = make_scene(n, resolution, spp, integrator, variant, cube_meshes)
        fwd, fb = time_scene(scene, n, args.repeats)
        rows.append((variant, integrator, n, resolution, spp, fwd, fb))
        print(f"| {variant} | {integrator} | {n} | {resolution} | {spp} | {fwd:.3f} | {fb:.3f} |", flush=True)
    return rows


ELEMENTS = {
    "full scene (stage, ring light as band, top light, filter 0.5)": {},
    "ring light as the paper's torus": {"torus_light": TorusLight(shape="torus")},
    "no top light": {"top_light": None},
    "no torus light": {"torus_light": None},
    "no stage": {"stage": False},
    "filter stddev 3.0 (HIM)": {"filter_stddev": 3.0},
}


def elements(args, cube_meshes):
    n, resolution, spp = args.particles[0], args.resolution[0], args.spp[0]
    for name, change in ELEMENTS.items():
        scene = make_scene(n, resolution, spp, args.integrator[0], args.variant[0], cube_meshes, **change)
        fwd, fb = time_scene(scene, n, args.repeats)
        print(f"| {name} | {n} | {resolution} | {spp} | {fwd:.3f} | {fb:.3f} |", flush=True)


# The TiO2 SEM lighting (conf/gan/material/tio2_sem.yaml): a grazing band ring and a dimmer top light.
SEM_LIGHTS = {
    "torus_light": TorusLight(radiance=4.0, major_radius=1.0, minor_radius=0.08, height=0.1),
    "top_light": TopLight(radiance=0.3),
}


def noise(args, cube_meshes):
    """Noise of the image a discriminator sees: std of (render(seed 1) - render(seed 2)) / sqrt(2) over the
    particle pixels (and the stage pixels) of one 40-particle layout, and the forward time. --roughness picks
    the particles' roughness (the learned range's limits 0.01 and 5.0 are where light or BSDF sampling fail)."""
    sizes, placement = LognormalSize(30.0, 0.4), PoissonAgglomerates()
    phi = layout.sample_layouts(1, args.particles[-1], sizes, placement, view_width=256.0, seed=3)[0]
    lights = {
        "torus": {"torus_light": TorusLight(shape="torus")},
        "band": {"torus_light": TorusLight(shape="band")},
        "sem": SEM_LIGHTS,
    }
    for integrator, shape, roughness, spp in itertools.product(args.integrator, args.lights, args.roughness, args.spp):
        values = torch.tensor([0.15, roughness, 1.0, 0.5, 0.5, 0.5])
        scene = make_scene(len(phi), args.resolution[0], spp, integrator, args.variant[0], cube_meshes, **lights[shape])
        scene.set_layout(phi)
        particles = scene.instance_labels() > 0
        with torch.no_grad():
            scene.render(values, seed=0)  # warm-up (kernel compilation)
            start = time.perf_counter()
            a = scene.render(values, seed=1).numpy()
            seconds = time.perf_counter() - start
            b = scene.render(values, seed=2).numpy()
        diff = (a - b) / np.sqrt(2.0)
        print(
            f"| {integrator} | {shape} | {roughness} | {spp} | {a[particles].mean():.3f} | {diff[particles].std():.4f} | "
            f"{a[~particles].mean():.3f} | {diff[~particles].std():.4f} | {seconds:.3f} |",
            flush=True,
        )


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--spp", type=int, nargs="+", default=[1, 4, 16, 64, 121])
    parser.add_argument("--resolution", type=int, nargs="+", default=[256])
    parser.add_argument("--particles", type=int, nargs="+", default=[10, 40])
    parser.add_argument("--integrator", nargs="+", default=["prb", "direct_light", "prb_basic", "direct_projective"])
    parser.add_argument("--variant", nargs="+", default=["llvm_ad_rgb"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--elements", action="store_true", help="cost of each optional scene element")
    parser.add_argument("--noise", action="store_true", help="particle-pixel noise against integrator, ring light, spp")
    parser.add_argument(
        "--lights",
        nargs="+",
        default=["torus", "band"],
        choices=["torus", "band", "sem"],
        help="--noise: ring light shapes (sem: the TiO2 SEM grazing band ring and top light)",
    )
    parser.add_argument("--roughness", type=float, nargs="+", default=[0.5], help="--noise: particle roughness")
    args = parser.parse_args()

    cube_meshes = particle_meshes.generate_meshes("cube", 40, seed=0)
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch threads {torch.get_num_threads()}"
    )
    print(f"command: python {' '.join(sys.argv)}\n")
    if args.noise:
        print(
            "| integrator | lights | roughness | spp | particle mean | particle noise | stage mean | stage noise | forward s |"
        )
        print("|---|---|---|---|---|---|---|---|---|")
        noise(args, cube_meshes)
    elif args.elements:
        print("| scene | particles | resolution | spp | forward s | forward+backward s |")
        print("|---|---|---|---|---|---|")
        elements(args, cube_meshes)
    else:
        print("| variant | integrator | particles | resolution | spp | forward s | forward+backward s |")
        print("|---|---|---|---|---|---|---|")
        grid(args, cube_meshes)


if __name__ == "__main__":
    main()
