"""Segmenter speed on this machine: training throughput and sliding-window inference time.

    python benchmarks/segment.py [--depth 4] [--base 16] [--crop 128] [--batch 8] [--steps 10] [--epochs 10]
                                 [--schedule poly|constant]

Training: forward + backward + Adam step of the U-Net on random crops (pairs/s = crops per second, one
crop per pair and epoch; the learning rate's schedule, `model.lr_schedule`, stepped after each step as Lightning
steps it), projected to minutes for 1,200 pairs x epochs. Inference: seconds for one
1024 x 712 image with predict() (default tile 384, overlap 0.125, batch 8), and what noise matching adds before the
network (drgan.segmenters.noise_match: the image's level, then noise up to twice it). Prints a markdown table.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from drgan.data.images import read_grey
from drgan.segmenters.inference import predict, predict_probs, split_touching
from drgan.segmenters.module import LR_SCHEDULES, SegmenterModule, load_segmenter, poly_schedule
from drgan.segmenters.noise_match import match_noise, noise_level, white_gain


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--depth", type=int, default=4)
    ap.add_argument("--base", type=int, default=16)
    ap.add_argument("--crop", type=int, default=128)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--epochs", type=int, default=10)
    ap.add_argument("--pairs", type=int, default=1200)
    ap.add_argument("--schedule", choices=LR_SCHEDULES, default="poly", help="model.lr_schedule (default: the YAML's)")
    ap.add_argument("--tile", type=int, default=384)
    ap.add_argument("--overlap", type=float, default=0.125)
    ap.add_argument("--threads", type=int, default=torch.get_num_threads())
    ap.add_argument("--ckpt", help="time inference with this trained segmenter (default: the untrained network)")
    ap.add_argument("--image", help="time inference on this image (default: uniform noise, 1024 x 712)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    model = SegmenterModule(depth=args.depth, base=args.base, lr_schedule=args.schedule)
    opt = model.configure_optimizers()  # no trainer here: Adam alone; the schedule as configure_optimizers builds it
    schedule = poly_schedule(opt, args.steps + 2) if args.schedule == "poly" else None
    image = torch.rand(args.batch, 1, args.crop, args.crop)
    mask = torch.randint(0, 3, (args.batch, args.crop, args.crop))
    model.train()
    for step in range(args.steps + 2):  # two warm-up steps
        if step == 2:
            start = time.perf_counter()
        opt.zero_grad()
        model._losses((image, mask))[3].backward()
        opt.step()
        if schedule is not None:
            schedule.step()
    per_step = (time.perf_counter() - start) / args.steps
    pairs_s = args.batch / per_step
    minutes = args.pairs * args.epochs / pairs_s / 60

    net = model.net if args.ckpt is None else load_segmenter(args.ckpt)
    net.eval()
    full = (
        np.random.default_rng(0).random((712, 1024)).astype(np.float32)
        if args.image is None
        else read_grey(args.image, (712, 768))
    )
    predict(net, full[:256, :256])
    start = time.perf_counter()
    probs = predict_probs(net, full, tile=args.tile, overlap=args.overlap)
    network_s = time.perf_counter() - start
    split_touching(probs)
    infer_s = time.perf_counter() - start
    white_gain()  # measured once per process
    start = time.perf_counter()
    match_noise(full, 2 * noise_level(full))
    match_s = time.perf_counter() - start

    n_params = sum(p.numel() for p in model.parameters())
    print(
        f"| depth | base | params | crop | batch | threads | schedule | s/step | pairs/s | min for {args.pairs} pairs x {args.epochs} epochs | tile / overlap | s per 1024x712 image (network + split) | noise matching s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    print(
        f"| {args.depth} | {args.base} | {n_params / 1e6:.2f} M | {args.crop} | {args.batch} | {args.threads} | {args.schedule} | {per_step:.3f} | "
        f"{pairs_s:.1f} | {minutes:.1f} | {args.tile} / {args.overlap} | {infer_s:.2f} ({network_s:.2f} + {infer_s - network_s:.2f}) | {match_s:.3f} |"
    )


if __name__ == "__main__":
    main()
