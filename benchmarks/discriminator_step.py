"""The discriminator's share of a training iteration, and what CPU tricks do to it.

    python benchmarks/discriminator_step.py                          # 256 px, fp32 / channels_last / compile / bf16
    python benchmarks/discriminator_step.py --variants fp32 bf16 --resolution 128

Times what an iteration spends in the 3-layer PatchGAN (batch 1): the D step (forward on a real and a fake
image, backward, Adam) and the D half of the G step (forward on the fake, backward to the image). No render:
the fake is a fixed random image that asks for a gradient. Each variant runs in its own process, so a variant
the CPU cannot execute (bf16 autocast on a machine whose hypervisor hides AMX dies with SIGILL) is reported
in its row instead of ending the table.

Variants: fp32 (what training uses), channels_last (NHWC weights and inputs), compile (torch.compile of D),
bf16 (torch.autocast on the CPU; losses in fp32).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import statistics
import subprocess
import sys
import time

VARIANTS = ("fp32", "channels_last", "compile", "bf16")


def measure(variant: str, resolution: int, steps: int, warmup: int) -> dict[str, float]:
    import torch

    from drgan.models.discriminator import PatchDiscriminator

    torch.manual_seed(0)
    disc = PatchDiscriminator()
    real = torch.rand(1, 1, resolution, resolution)
    fake = torch.rand(1, 1, resolution, resolution, requires_grad=True)
    if variant == "channels_last":
        disc = disc.to(memory_format=torch.channels_last)
        real = real.contiguous(memory_format=torch.channels_last)
    opt = torch.optim.Adam(disc.parameters(), lr=1e-4, betas=(0.5, 0.999))
    net = torch.compile(disc) if variant == "compile" else disc

    def forward(image):
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=variant == "bf16"):
            return net(image).float()

    d_times, g_times = [], []
    for step in range(warmup + steps):
        t0 = time.perf_counter()
        opt.zero_grad()
        d_loss = 0.5 * (((forward(real) - 1) ** 2).mean() + (forward(fake.detach()) ** 2).mean())
        d_loss.backward()
        opt.step()
        t1 = time.perf_counter()
        fake.grad = None
        ((forward(fake) - 1) ** 2).mean().backward()
        t2 = time.perf_counter()
        if step >= warmup:
            d_times.append(t1 - t0)
            g_times.append(t2 - t1)
    return {"d_step": statistics.median(d_times), "g_through_d": statistics.median(g_times)}


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--steps", type=int, default=8)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--child", choices=VARIANTS, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(measure(args.child, args.resolution, args.steps, args.warmup)))
        return

    import torch

    print(
        f"machine: {platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}, threads {torch.get_num_threads()}"
    )
    print(f"command: python {' '.join(sys.argv)}\n")
    print("| variant | resolution | D step s | G step, D part s | D total per iteration s |")
    print("|---|---|---|---|---|")
    for variant in args.variants:
        child = [
            sys.executable,
            __file__,
            "--child",
            variant,
            "--resolution",
            str(args.resolution),
            "--steps",
            str(args.steps),
            "--warmup",
            str(args.warmup),
        ]
        done = subprocess.run(child, capture_output=True, text=True)
        if done.returncode != 0:
            reason = (
                f"killed by {signal.Signals(-done.returncode).name}"
                if done.returncode < 0
                else (done.stderr.strip().splitlines() or [f"exit {done.returncode}"])[-1]
            )
            print(f"| {variant} | {args.resolution} | failed: {reason} | | |", flush=True)
            continue
        t = json.loads(done.stdout.strip().splitlines()[-1])
        print(
            f"| {variant} | {args.resolution} | {t['d_step']:.3f} | {t['g_through_d']:.3f} | "
            f"{t['d_step'] + t['g_through_d']:.3f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
