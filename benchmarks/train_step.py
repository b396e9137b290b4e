"""One DiffRenderGAN training iteration beside its parts timed alone, and one FID pass (TiO2 SEM config, 40 particles).

    python benchmarks/train_step.py                     # 256 px, batch 1, spp 16 and 121, FID pass over 124 images
    python benchmarks/train_step.py --spp 4 16 --fid-images 0
    python benchmarks/train_step.py --spp 16 121 --grad-spp 0 4 16 --fid-images 0   # 0: adjoint at the image's spp
    python benchmarks/train_step.py --integrator prb direct_light --fid-images 0      # renderer.integrator

An iteration: render (G forward), D step (forward on real and fake, backward, Adam), G step (D forward on the
fake, backward through D and the renderer's adjoint pass, Adam). Its parts, each timed alone in a loop of its own:
FCN (parameter regressor forward + backward), primal render (layout, render, noise; no gradient), adjoint render
(the renderer's backward pass for one image), D (the D step plus the G step's D forward/backward on a detached
fake). iteration / sum of parts above 1 is what the iteration spends on neither rendering nor the networks.
Medians of --steps after --warmup steps; wall seconds, and the process's CPU seconds (all its threads) of the
iteration and of the parts: CPU time is far less sensitive to other work on a shared machine.

Runs against another checkout too (`PYTHONPATH=/path/to/checkout/src python benchmarks/train_step.py ...`):
configs are composed from the imported drgan's conf/ folder.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

import drgan
from drgan.models.gan_module import GANModule

try:
    from drgan.launch.configs import compose
except ImportError:  # a checkout from before drgan.launch.configs (comparisons against an older main)

    def compose(overrides=(), config_name="render"):
        from hydra import compose as hydra_compose
        from hydra import initialize_config_dir

        # the ${mul:} resolver: registered by drgan.core.resolvers (newer) or drgan.build (older checkouts)
        for name in ("drgan.core.resolvers", "drgan.build"):
            try:
                importlib.import_module(name)
                break
            except ModuleNotFoundError:
                continue

        conf = Path(drgan.__file__).resolve().parent / "conf"
        if not conf.is_dir():  # checkouts from before conf/ moved into the package
            conf = Path(drgan.__file__).resolve().parents[2] / "conf"
        with initialize_config_dir(version_base="1.3", config_dir=str(conf)):
            return hydra_compose(config_name=config_name, overrides=list(overrides))


ROOT = Path(drgan.__file__).resolve().parents[2]


class Clock:
    """Wall and process CPU seconds of a block."""

    def __enter__(self):
        self.wall, self.cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall, self.cpu = time.perf_counter() - self.wall, time.process_time() - self.cpu


# --d-weight-grads: the G step also computes D's weight gradients, as GANModule did before commit d68288a (to time
# an older checkout's iteration as it trained).
D_WEIGHT_GRADS_IN_G_STEP = False


@contextlib.contextmanager
def frozen(network: torch.nn.Module):
    """``network``'s weights need no gradient inside (GANModule's G step: Lightning's optimizer toggle)."""
    if D_WEIGHT_GRADS_IN_G_STEP:
        yield
        return
    flags = [p.requires_grad for p in network.parameters()]
    for p in network.parameters():
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p, flag in zip(network.parameters(), flags):
            p.requires_grad_(flag)


def time_iteration(module: GANModule, steps: int, warmup: int) -> dict[str, float]:
    opt_g = torch.optim.Adam(module.generator.parameters(), lr=2e-4, betas=(0.5, 0.999))
    opt_d = torch.optim.Adam(module.discriminator.parameters(), lr=1e-4, betas=(0.5, 0.999))
    size = module.generator.scene.spec.render.resolution
    real = torch.rand(1, 1, size, size)
    parts: dict[str, list[float]] = {"render": [], "d_step": [], "g_step": [], "iteration": [], "iteration_cpu": []}
    for step in range(warmup + steps):
        cpu0 = time.process_time()
        t0 = time.perf_counter()
        fake, _ = module.render(module.draw_phi(1))
        t1 = time.perf_counter()
        opt_d.zero_grad()
        d_loss = 0.5 * (
            module.adversarial_loss(module.discriminator(real), True)
            + module.adversarial_loss(module.discriminator(fake.detach()), False)
        )
        d_loss.backward()
        opt_d.step()
        t2 = time.perf_counter()
        opt_g.zero_grad()
        with frozen(module.discriminator):  # as GANModule's G step: D's input gradient only
            module.adversarial_loss(module.discriminator(fake), True).backward()
        opt_g.step()
        t3 = time.perf_counter()
        if step >= warmup:
            for key, value in zip(parts, (t1 - t0, t2 - t1, t3 - t2, t3 - t0, time.process_time() - cpu0)):
                parts[key].append(value)
    return {key: statistics.median(values) for key, values in parts.items()}


def time_parts(module: GANModule, steps: int, warmup: int) -> dict[str, float]:
    """Each part of an iteration alone: FCN forward/backward, primal render, adjoint render, D forward/backward."""
    generator, scene = module.generator, module.generator.scene
    opt_d = torch.optim.Adam(module.discriminator.parameters(), lr=1e-4, betas=(0.5, 0.999))
    size = scene.spec.render.resolution
    real = torch.rand(1, 1, size, size)
    parts: dict[str, list[float]] = {"fcn": [], "primal": [], "adjoint": [], "d": [], "cpu": []}
    for step in range(warmup + steps):
        phi = module.draw_phi(1)
        with Clock() as fcn:
            values = generator.learned_values(phi)
            (values * torch.linspace(0.5, 1.5, values.shape[1])).sum().backward()
        values = values.detach()[0]
        with Clock() as primal, torch.no_grad():
            fake = generator.render_one(phi[0], values).unsqueeze(0)
        bsdf_values = values[: len(scene.learned)].clone().requires_grad_(True)
        image = scene.render(bsdf_values, seed=generator.next_seed())
        grad = torch.randn_like(image)
        with Clock() as adjoint:
            image.backward(grad)
        with Clock() as d:
            opt_d.zero_grad()
            d_loss = 0.5 * (
                module.adversarial_loss(module.discriminator(real), True)
                + module.adversarial_loss(module.discriminator(fake), False)
            )
            d_loss.backward()
            opt_d.step()
            leaf = fake.clone().requires_grad_(True)
            with frozen(module.discriminator):
                module.adversarial_loss(module.discriminator(leaf), True).backward()
        if step >= warmup:
            for key, clock in zip(parts, (fcn, primal, adjoint, d)):
                parts[key].append(clock.wall)
            parts["cpu"].append(fcn.cpu + primal.cpu + adjoint.cpu + d.cpu)
    return {key: statistics.median(values) for key, values in parts.items()}


def time_fid_pass(module: GANModule, n_images: int) -> tuple[float, float]:
    from drgan.metrics.inception import InceptionFeatures

    extractor = InceptionFeatures(batch_size=16)
    extractor.features(np.zeros((2, 64, 64), np.float32))  # load the network outside the timing
    start = time.perf_counter()
    images = np.stack(
        [module.generator.sample(module.phi_bank[i % len(module.phi_bank)]).image for i in range(n_images)]
    )
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
    parser.add_argument(
        "--grad-spp",
        type=int,
        nargs="+",
        default=[0],
        help="spp of the adjoint pass (renderer.grad_spp); 0 = the image's spp; skipped when > spp",
    )
    parser.add_argument(
        "--integrator", nargs="+", default=[None], help="renderer.integrator values to time (default: the config's)"
    )
    parser.add_argument("--no-parts", action="store_true", help="time the iteration only")
    parser.add_argument(
        "--torch-threads",
        type=int,
        default=None,
        help="torch.set_num_threads (default: torch's). On a loaded machine 2 torch threads wait on "
        "each other: a 256 px D forward/backward took 0.4 s with 1 thread and 0.6-2.4 s with 2",
    )
    parser.add_argument(
        "--d-weight-grads",
        action="store_true",
        help="the G step also computes D's weight gradients (GANModule before commit d68288a; for older checkouts)",
    )
    args = parser.parse_args()
    global D_WEIGHT_GRADS_IN_G_STEP
    D_WEIGHT_GRADS_IN_G_STEP = args.d_weight_grads
    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, torch threads {torch.get_num_threads()}")
    print(f"drgan: {ROOT}")
    print(f"command: python {' '.join(sys.argv)}\n")
    print(
        "| spp | grad_spp | integrator | render s | D step s | G step (incl. adjoint) s | iteration s | iteration CPU s "
        "| FCN s | primal s | adjoint s | D s | sum of parts s | iteration / sum | parts CPU s | iteration / sum, CPU |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    module = None
    for integrator in args.integrator:
        for spp in args.spp:
            for grad_spp in args.grad_spp:
                if grad_spp > spp:
                    continue
                grad = grad_spp or spp
                overrides = [
                    "material=tio2_sem",
                    f"renderer.spp={spp}",
                    f"renderer.grad_spp={grad}",
                    f"renderer.resolution={args.resolution}",
                ]
                if integrator is not None:
                    overrides.append(f"renderer.integrator={integrator}")
                cfg = compose(overrides, config_name="train")
                # GANModule.from_config since the module takes built parts; older checkouts: GANModule(cfg, ...)
                build_module = getattr(GANModule, "from_config", GANModule)
                module = build_module(cfg, m=124, base_dir=str(ROOT))
                t = time_iteration(module, args.steps, args.warmup)
                row = (
                    f"| {spp} | {grad} | {cfg.renderer.integrator} | {t['render']:.3f} | {t['d_step']:.3f} | "
                    f"{t['g_step']:.3f} | {t['iteration']:.3f} | {t['iteration_cpu']:.3f} |"
                )
                if args.no_parts:
                    print(row + " | | | | | | | |", flush=True)
                    continue
                p = time_parts(module, args.steps, args.warmup)
                total = p["fcn"] + p["primal"] + p["adjoint"] + p["d"]
                print(
                    row + f" {p['fcn']:.3f} | {p['primal']:.3f} | {p['adjoint']:.3f} | {p['d']:.3f} | {total:.3f} | "
                    f"{t['iteration'] / total:.2f} | {p['cpu']:.3f} | {t['iteration_cpu'] / p['cpu']:.2f} |",
                    flush=True,
                )
    if args.fid_images and module is not None:
        render_s, inception_s = time_fid_pass(module, args.fid_images)
        print(
            f"\nFID pass, {args.fid_images} images at spp {args.spp[-1]}: render {render_s:.1f} s + Inception {inception_s:.1f} s "
            f"= {render_s + inception_s:.1f} s"
        )


if __name__ == "__main__":
    main()
