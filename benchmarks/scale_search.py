"""The particle scale search's time on this machine: averaged-down large scales against every scale at full resolution.

    python benchmarks/scale_search.py [--size 768 1024] [--diameters 16 40 100 200] [--repeat 1] [--images DIR ...]

For each image (drawn discs of each diameter on a grainy film, and any real images given: each one user's folder of
one image), `drgan.data.particles.resolve_params` runs twice, as the profile and patch mining run it: with the search's
large scales segmented on copies averaged down (the default, WORK_DIAMETER) and with every scale at full resolution
(WORK_DIAMETER = inf). Prints a markdown table: seconds each way (best of --repeat), their ratio, and the scale and
neck depth each way chose (they should agree: the averaged-down copies only measure). One process; the machine's
load moves the seconds, not much their ratio.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

from drgan.data import particles as P
from drgan.data.images import read_grey


def disc_field(shape: tuple[int, int], diameter: float, seed: int = 0) -> np.ndarray:
    """Bright discs of ``diameter`` px covering ~30 % of a grey film with 2 px grain (noise std 0.04)."""
    rng = np.random.default_rng(seed)
    h, w = shape
    image = np.full(shape, 0.35)
    yy, xx = np.mgrid[:h, :w]
    r, centres = diameter / 2, []
    for _ in range(int(0.3 * h * w / (math.pi * r * r)) * 20):
        c = rng.uniform(r, (h - r, w - r))
        if all(math.dist(c, o) > 2 * r + 2 for o in centres):
            centres.append(c)
            image[(yy - c[0]) ** 2 + (xx - c[1]) ** 2 <= r * r] = 0.7
        if len(centres) * math.pi * r * r >= 0.3 * h * w:
            break
    grain = ndi.gaussian_filter(rng.standard_normal(shape), 2.0)
    return np.clip(image + 0.04 * grain / grain.std(), 0, 1).astype(np.float32)


def timed(image: np.ndarray, polarity: str, work: float, repeat: int) -> tuple[float, P.SegmentParams]:
    P.WORK_DIAMETER = work
    best, params = math.inf, None
    for _ in range(repeat):
        start = time.perf_counter()
        params, _ = P.resolve_params([image], None, polarity)
        best = min(best, time.perf_counter() - start)
    return best, params


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, nargs=2, default=(768, 1024), metavar=("H", "W"))
    ap.add_argument("--diameters", type=float, nargs="*", default=(16, 40, 100, 200))
    ap.add_argument("--images", nargs="*", default=(), help="real images too (grey, any format read_grey reads)")
    ap.add_argument("--polarity", default="bright", help="of the real images (bright or dark)")
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args()
    default = P.WORK_DIAMETER
    cases = [(f"discs {d:g} px, {args.size[0]} x {args.size[1]}", disc_field(tuple(args.size), d), "bright")
             for d in args.diameters]  # fmt: skip
    cases += [(Path(p).name, read_grey(p), args.polarity) for p in args.images]
    print("| image | averaged down (s) | full resolution (s) | ratio | scale px, depth: averaged down / full |")
    print("|---|---|---|---|---|")
    for name, image, polarity in cases:
        fast, a = timed(image, polarity, default, args.repeat)
        slow, b = timed(image, polarity, math.inf, args.repeat)
        print(
            f"| {name} | {fast:.1f} | {slow:.1f} | {slow / fast:.2f}x | {a.scale}, {a.neck_depth} / "
            f"{b.scale}, {b.neck_depth} |",
            flush=True,
        )
    P.WORK_DIAMETER = default


if __name__ == "__main__":
    main()
