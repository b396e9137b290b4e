"""Which objective does each `renderer.grad_seed` estimator follow? Finite differences with a non-linear loss.

    python experiments/gradient_estimator/fd_check.py                 # 64 px, 8 spheres, prb, spp 4 and 16, MSE loss
    python experiments/gradient_estimator/fd_check.py --loss cauchy   # a loss that is not quadratic in the image

A linear loss cannot tell the estimators apart (both are unbiased for its gradient). With a loss L on the
image I that is not linear, two objectives differ:

  A  L(E[I])          the loss of the expected image (what inverse rendering asks for);
  B  E[L(I_s)]        the expected loss of the noisy image at s samples per pixel (Monte Carlo grain included).

For each spp s and each learned parameter this prints the mean over --seeds primal seeds of the gradient of
L(render(theta, seed, spp=s)) with grad_spp = s and `grad_seed` = same / independent, and the two objectives'
derivatives from central finite differences:

  dA  chain rule with the loss's derivative at a high-spp image R1 (seed a) and the central finite difference
      of a second high-spp image R2 (seed b != a; the same seed at theta +- h, common random numbers):
      <L'(R1), (R2(theta+h) - R2(theta-h)) / 2h>, averaged over --ref-pairs pairs (a, b). R1 and R2 are
      independent, so no Monte Carlo grain of the reference enters dA (a plain finite difference of L(R2)
      would carry the grain term at 1/ref_spp; it is printed too, as "dA plain", for comparison). Exact for a
      quadratic loss, whose L' is linear; for another loss L'(R1) is L' at a nearly noise-free image.
  dB  mean over the same primal seeds of (L(I_s(theta+h, seed)) - L(I_s(theta-h, seed))) / 2h (common random
      numbers: the realised noisy image's derivative, grain and sample directions moving with theta).

z = (estimator mean - objective) / standard error (paired per seed against dB; against dA the two standard
errors combined). |z| < ~3 means "consistent with unbiased for that objective" at this many seeds.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import torch

from drgan.scene import particle_meshes
from drgan.scene.config import SecondaryImaging
from drgan.scene.scene import ParticleScene, RenderSettings, SceneSpec, TopLight, TorusLight

# learned: stage base colour, particle base colour / roughness / sheen (the GAN's informative parameters)
PARTICLE = {
    "base_color": {"min": 0.01, "max": 5.0},
    "roughness": {"min": 0.01, "max": 5.0},
    "sheen": {"min": 0.01, "max": 5.0},
    "sheen_tint": {"value": 0.5},
    "spec_tint": {"value": 0.5},
}
STAGE = {"base_color": {"min": 0.01, "max": 0.4}}
THETA = {"stage.base_color": 0.2, "particle.base_color": 0.5, "particle.roughness": 0.5, "particle.sheen": 0.5}
TARGET = {"stage.base_color": 0.3, "particle.base_color": 0.7, "particle.roughness": 0.3, "particle.sheen": 0.8}
# eight spheres (x, y, z, diameter in px of a 64 px view), two pairs overlapping
PHI = np.array(
    [
        [-20, -18, 7, 14],
        [2, -20, 8, 16],
        [21, -16, 6, 12],
        [-18, 2, 7, 15],
        [-6, 4, 9, 17],
        [19, 5, 7, 14],
        [-8, 20, 6, 12],
        [12, 19, 8, 15],
    ],
    dtype=np.float32,
)


def make_scene(resolution: int, integrator: str, grad_seed: str) -> ParticleScene:
    """The TiO2 SEM lighting (grazing ring, radiance 4; top light 0.3) on a small view of spheres."""
    spec = SceneSpec(
        SecondaryImaging(particle_bsdf=PARTICLE, stage_bsdf=STAGE).material_parameters({"value": 0.0}),
        RenderSettings(resolution=resolution, spp=16, integrator=integrator, grad_seed=grad_seed),
        view_width=64.0,
        torus_light=TorusLight(radiance=4.0, major_radius=1.0, minor_radius=0.08, height=0.1),
        top_light=TopLight(radiance=0.3),
    )
    scene = ParticleScene([particle_meshes.sphere(3)], len(PHI), spec)
    scene.set_layout(PHI)
    return scene


def make_loss(kind: str, target: torch.Tensor):
    if kind == "mse":
        return lambda image: ((image.double() - target) ** 2).mean()
    # Cauchy / Lorentzian: log(1 + (r/c)^2), quadratic for small residuals, flat for large ones; c = 0.1
    return lambda image: torch.log1p(((image.double() - target) / 0.1) ** 2).mean()


def estimator_gradients(scene, loss, theta, spp, seeds) -> np.ndarray:
    rows = []
    for seed in seeds:
        x = theta.clone().requires_grad_(True)
        loss(scene.render(x, seed=seed, spp=spp, grad_spp=spp)).backward()
        rows.append(x.grad.double().numpy())
    return np.array(rows)


def render(scene, theta, seed, spp) -> torch.Tensor:
    with torch.no_grad():
        return scene.render(theta, seed=seed, spp=spp)


def noisy_loss_fd(scene, loss, theta, spp, seeds, h) -> np.ndarray:
    """Per seed, per parameter: central difference of L(I_s) with common random numbers (objective B)."""
    rows = np.zeros((len(seeds), len(theta)))
    for i, seed in enumerate(seeds):
        for j in range(len(theta)):
            step = torch.zeros_like(theta)
            step[j] = h
            rows[i, j] = (
                float(loss(render(scene, theta + step, seed, spp)))
                - float(loss(render(scene, theta - step, seed, spp)))
            ) / (2 * h)
    return rows


def expected_image_fd(scene, loss, theta, spp, pairs, h) -> tuple[np.ndarray, np.ndarray]:
    """Per reference pair: <L'(R1), dR2/dtheta> (objective A, decorrelated) and the plain FD of L(R2)."""
    chain, plain = np.zeros((len(pairs), len(theta))), np.zeros((len(pairs), len(theta)))
    for i, (a, b) in enumerate(pairs):
        r1 = render(scene, theta, a, spp).requires_grad_(True)
        (dloss,) = torch.autograd.grad(loss(r1), r1)
        for j in range(len(theta)):
            step = torch.zeros_like(theta)
            step[j] = h
            up, down = render(scene, theta + step, b, spp), render(scene, theta - step, b, spp)
            chain[i, j] = float((dloss.double() * (up.double() - down.double())).sum()) / (2 * h)
            plain[i, j] = (float(loss(up)) - float(loss(down))) / (2 * h)
    return chain, plain


def mean_se(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return rows.mean(0), rows.std(0, ddof=1) / np.sqrt(len(rows))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--spp", type=int, nargs="+", default=[4, 16])
    parser.add_argument("--seeds", type=int, default=64, help="primal seeds per spp")
    parser.add_argument("--ref-spp", type=int, default=1024)
    parser.add_argument("--ref-pairs", type=int, default=6, help="(a, b) seed pairs of the high-spp reference")
    parser.add_argument("--h", type=float, default=0.02, help="finite-difference step (parameter units)")
    parser.add_argument("--loss", choices=["mse", "cauchy"], default="mse")
    parser.add_argument("--integrator", default="prb")
    args = parser.parse_args()
    start = time.time()

    scenes = {mode: make_scene(args.resolution, args.integrator, mode) for mode in ("same", "independent")}
    ref = scenes["same"]
    names = [p.key for p in ref.learned]
    theta = torch.tensor([THETA[n] for n in names], dtype=torch.float32)
    target = render(ref, torch.tensor([TARGET[n] for n in names], dtype=torch.float32), 999_999, args.ref_spp).double()
    loss = make_loss(args.loss, target)
    pairs = [(1_000_000 + 2 * k, 1_000_001 + 2 * k) for k in range(args.ref_pairs)]
    d_a, d_a_plain = expected_image_fd(ref, loss, theta, args.ref_spp, pairs, args.h)
    a_mean, a_se = mean_se(d_a)
    a_plain = d_a_plain.mean(0)

    print(f"command: python {' '.join(sys.argv)}")
    print(
        f"{args.resolution} px, {len(PHI)} spheres, {args.integrator}, loss {args.loss}, h {args.h}, {args.seeds} primal seeds; "
        f"reference spp {args.ref_spp} x {args.ref_pairs} pairs; theta {dict(zip(names, theta.tolist()))}\n"
    )
    print(
        "| spp | parameter | dA = d L(E[I]) | dA plain | dB = d E[L(I_s)] | same: mean | same z vs A | same z vs B "
        "| independent: mean | indep. z vs A | indep. z vs B |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for spp in args.spp:
        seeds = list(range(spp * 100_000, spp * 100_000 + args.seeds))
        fd_b = noisy_loss_fd(ref, loss, theta, spp, seeds, args.h)
        b_mean, _ = mean_se(fd_b)
        grads = {mode: estimator_gradients(scene, loss, theta, spp, seeds) for mode, scene in scenes.items()}
        for j, name in enumerate(names):
            cells = [f"{a_mean[j]:.4g} +- {a_se[j]:.2g}", f"{a_plain[j]:.4g}", f"{b_mean[j]:.4g}"]
            for mode in ("same", "independent"):
                g_mean, g_se = mean_se(grads[mode][:, j : j + 1])
                z_a = (g_mean[0] - a_mean[j]) / np.hypot(g_se[0], a_se[j])
                _, paired_se = mean_se(grads[mode][:, j : j + 1] - fd_b[:, j : j + 1])
                z_b = (g_mean[0] - b_mean[j]) / max(paired_se[0], 1e-30)
                cells += [f"{g_mean[0]:.4g} +- {g_se[0]:.2g}", f"{z_a:+.1f}", f"{z_b:+.1f}"]
            print(f"| {spp} | {name} | " + " | ".join(cells) + " |", flush=True)
    print(f"\n{time.time() - start:.0f} s")


if __name__ == "__main__":
    main()
