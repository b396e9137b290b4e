"""Where a training render's time goes inside Dr.Jit: the kernels of one primal render and one adjoint pass.

    python benchmarks/render_kernels.py                       # TiO2 SEM scene, 256 px, spp 16, direct_light_mis
    python benchmarks/render_kernels.py --spp 121 --integrator prb

Prints, per pass, the wall and process CPU seconds beside what Dr.Jit's kernel history reports: the number of
kernels launched, their summed execution time, their summed code generation time (near 0 once the kernel cache is
warm) and the largest kernel's share and operation count. If the largest kernel carries nearly all of the time, the
pass is one fused megakernel: what is left to gain is inside it (fewer operations per sample), not in tracing,
launches or Python.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import torch

import drgan
from drgan.core.backend import dr
from drgan.launch.configs import compose
from drgan.models.gan_module import GANModule

ROOT = Path(drgan.__file__).resolve().parents[2]


def kernels() -> list[dict]:
    return [k for k in dr.kernel_history() if k.get("type") != "Unknown"]


def summary(history: list[dict]) -> dict[str, float]:
    execution = [k.get("execution_time", 0.0) / 1000 for k in history]
    largest = max(history, key=lambda k: k.get("execution_time", 0.0)) if history else {}
    total = sum(execution)
    return {
        "kernels": len(history),
        "execution": total,
        "codegen": sum(k.get("codegen_time", 0.0) for k in history) / 1000,
        "largest_share": (largest.get("execution_time", 0.0) / 1000 / total) if total else 0.0,
        "largest_ops": largest.get("operation_count", 0),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--integrator", default="direct_light_mis")
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--torch-threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.torch_threads)
    cfg = compose(
        [
            "material=tio2_sem",
            f"renderer.spp={args.spp}",
            f"renderer.grad_spp={args.spp}",
            f"renderer.integrator={args.integrator}",
            f"renderer.resolution={args.resolution}",
        ],
        config_name="train",
    )
    module = GANModule.from_config(cfg, m=8, base_dir=str(ROOT))
    generator = module.generator
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; drgan: {ROOT}")
    print(f"scene: TiO2 SEM, {args.resolution} px, spp {args.spp} (adjoint too), {args.integrator}\n")
    print(
        "| pass | wall s | CPU s | kernels | kernel execution s | codegen s | largest kernel's share | its operations |"
    )
    print("|---|---|---|---|---|---|---|---|")
    rows: dict[str, list[dict]] = {"primal": [], "adjoint": []}
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    for repeat in range(args.repeats + 1):  # the first repeat warms the kernel cache
        phi = module.draw_phi(1)
        values = generator.learned_values(phi).detach()[0].requires_grad_(True)
        kernels()  # reading the history clears it
        wall, cpu = time.perf_counter(), time.process_time()
        image = generator.render_one(phi[0], values)
        primal = {"wall": time.perf_counter() - wall, "cpu": time.process_time() - cpu, **summary(kernels())}
        wall, cpu = time.perf_counter(), time.process_time()
        (image * torch.linspace(0.5, 1.5, image.shape[-1])).sum().backward()
        adjoint = {"wall": time.perf_counter() - wall, "cpu": time.process_time() - cpu, **summary(kernels())}
        if repeat:
            rows["primal"].append(primal)
            rows["adjoint"].append(adjoint)
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    for name, measured in rows.items():
        med = {key: statistics.median(m[key] for m in measured) for key in measured[0]}
        print(
            f"| {name} | {med['wall']:.3f} | {med['cpu']:.3f} | {med['kernels']:.0f} | {med['execution']:.3f} | "
            f"{med['codegen']:.3f} | {med['largest_share']:.2f} | {med['largest_ops']:.0f} |"
        )


if __name__ == "__main__":
    main()
