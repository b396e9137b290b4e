"""The edge-fringe measurement (drgan.data.particle_edge.edge_profile) on transmission renders of known fringe.

    python experiments/tio2_tsem/edge_fringe.py [--images 6] [--seed 1]

Renders `material=tio2_tsem` scenes (potato meshes, 12 particles placed `random_2d` so that enough stand alone,
256 px, spp 4) with `material.imaging.fringe` fixed at each amplitude and width below, for two particle kinds
(semi-transparent: background 0.8, absorption 0.05, floor 0.1; nearly opaque, the real TSEM look: 0.8, 0.15,
0.03), adds the detector noise the profile measured on the real images (sigma 0.018, grain 1 px), clamps to
[0, 1], segments as `drgan.profile` does and prints what the edge profile finds: the ring (kind, height, error,
distance) and the fitted fringe (amplitude, width, edge blur).
"""

from __future__ import annotations

import argparse

import torch

from drgan.data import particle_edge
from drgan.data.annotations import annotation_mask
from drgan.data.classical import resolve_params
from drgan.data.measurements import segment_image
from drgan.launch.configs import compose
from drgan.models import build
from drgan.models.generator import add_noise

CASES = [(0.0, 1.0), (0.1, 0.7), (0.15, 1.0), (0.3, 1.5), (0.5, 3.0), (-0.3, 2.0), (-0.5, 3.0)]
KINDS = {"semi-transparent": (0.8, 0.05, 0.1), "nearly opaque": (0.8, 0.15, 0.03)}


def measure(amplitude: float, width: float, values: tuple, images: int, seed: int) -> particle_edge.EdgeProfile | None:
    overrides = [
        "material=tio2_tsem",
        "renderer.resolution=256",
        "renderer.spp=4",
        "material.meshes.count=10",
        "placement=random_2d",
        "material.n_particles=12",
    ]
    if amplitude:
        overrides.append(f"material.imaging.fringe={{amplitude: {{value: {amplitude}}}, width_px: {width}}}")
    cfg = compose(overrides, config_name="train")
    scene = build.build_scene(cfg)
    rendered = []
    for i, phi in enumerate(build.sample_phi(cfg, images, seed=seed)):
        scene.set_layout(phi)
        image = scene.render(torch.tensor(values), seed=0)
        rendered.append(add_noise(image, torch.tensor(0.018), seed=1000 * seed + i, grain_px=1.0).numpy())
    params, _ = resolve_params(rendered, None, "dark")
    samples = []
    for image in rendered:
        labels, foreground = segment_image(image, params, "dark")[:2]
        samples.append(particle_edge.edge_samples(image, labels, foreground, annotation_mask(image)))
    return particle_edge.edge_profile(samples)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=6)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    print("| particles | fringe amplitude / width (px) | isolated particles | ring: kind, height +- error, distance "
          "(px) | fit: amplitude, width (px), edge blur (px) |")  # fmt: skip
    print("|---|---|---|---|---|")
    for kind, values in KINDS.items():
        for amplitude, width in CASES:
            edge = measure(amplitude, width, values, args.images, args.seed)
            given = f"{amplitude:+.2f} / {width:.1f}" if amplitude else "none"
            if edge is None:
                print(f"| {kind} | {given} | too few | - | - |")
                continue
            r, f = edge.ring, edge.fringe
            ring = f"{r.kind}, {r.height:+.3f} +- {r.height_se:.3f}, {r.distance_px:.2f}"
            fit = "-" if f is None else f"{f.amplitude:+.3f}, {f.width_px:.2f}, {f.edge_blur_px:.2f}"
            print(f"| {kind} | {given} | {edge.particles} | {ring} | {fit} |", flush=True)


if __name__ == "__main__":
    from drgan.launch.configs import setup

    setup()
    main()
