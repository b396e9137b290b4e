"""Synthetic sweep of the scale-adaptive segmentation: discs of known size, both polarities, grainy noise, a scale
bar and its text drawn in; the median equivalent diameter found against the drawn one.

    python experiments/profile/synthetic_sweep.py [--size 512] [--csv PATH]

Per image: discs of one diameter (lognormal spread 0.1) placed without overlap on ~20 % of a size x size field,
contrast 0.35 on a background of 0.3 (bright) or 0.7 (dark), Gaussian noise of std `noise` blurred by `grain` px
(scaled back to that std), a white or black scale bar (6 px x 20 % of the width) with its label ("200 nm") in the
bottom-right corner and a panel letter "(a)" top-left. The image goes through drgan.data.classical as the profile
uses it (resolve_params on the image, then segment_particles); the measured median is that of the segments not
touching the border, the truth that of the drawn discs not touching it. Target: within 10 % everywhere.
"""

from __future__ import annotations

import argparse
import csv
import itertools
import math
import time

import numpy as np
from PIL import Image, ImageDraw, ImageFont
from scipy import ndimage as ndi

from drgan.data.classical import resolve_params, segment_diameters, segment_particles

BACKGROUND = {"bright": 0.3, "dark": 0.7}
CONTRAST = {"bright": 0.35, "dark": -0.35}


def draw(polarity: str, diameter: float, noise: float, grain: float, size: int, seed: int):
    """(image float32 in [0, 1], true median diameter of the discs not touching the border)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    image = np.full((size, size), BACKGROUND[polarity], np.float64)
    covered, drawn, centres = 0.0, [], []
    for _ in range(4000):
        if covered > 0.2 * size * size:
            break
        d = diameter * math.exp(rng.normal(0, 0.1))
        r = d / 2
        c = rng.uniform(-r / 2, size + r / 2, 2)
        if any(np.hypot(*(c - c2)) < r + r2 + 2 for c2, r2 in centres):
            continue
        if size - 0.3 * size < c[0] and c[1] > size - 0.35 * size:  # keep the scale bar's corner free
            continue
        disc = (yy - c[0]) ** 2 + (xx - c[1]) ** 2 <= r * r
        image[disc] += CONTRAST[polarity]
        centres.append((c, r))
        covered += disc.sum()
        if r <= c[0] < size - r and r <= c[1] < size - r:
            drawn.append(2 * math.sqrt(disc.sum() / math.pi))
    if noise > 0:
        field = rng.standard_normal((size, size))
        field = ndi.gaussian_filter(field, grain) if grain > 0 else field
        image += noise * field / field.std()
    ink = 1.0 if polarity == "bright" else 0.0
    canvas = Image.fromarray((np.clip(image, 0, 1) * 255).astype(np.uint8))
    pen = ImageDraw.Draw(canvas)
    bar = int(0.2 * size)
    x1, y1 = size - 20, size - 20
    pen.rectangle((x1 - bar, y1 - 6, x1, y1), fill=int(255 * ink))
    font = ImageFont.load_default(size=max(12, size // 24))
    pen.text((x1 - bar, y1 - 12 - size // 24), "200 nm", fill=int(255 * ink), font=font)
    pen.text((8, 8), "(a)", fill=int(255 * ink), font=ImageFont.load_default(size=max(14, size // 16)))
    return np.asarray(canvas, np.float32) / 255, float(np.median(drawn)) if drawn else math.nan


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--csv", default=None)
    args = parser.parse_args()
    rows = []
    grid = itertools.product(("bright", "dark"), (10, 20, 40, 80, 120), (0.0, 0.04, 0.08), (1.0, 3.0))
    start = time.perf_counter()
    for seed, (polarity, diameter, noise, grain) in enumerate(grid):
        if noise == 0 and grain == 3.0:
            continue
        image, truth = draw(polarity, diameter, noise, grain, args.size, seed)
        try:
            params, _ = resolve_params([image], None, polarity)
            found = segment_diameters(segment_particles(image, params, polarity)[0], params)
            median, scale, error = float(np.median(found)) if found.size else math.nan, params.scale, ""
        except Exception as exc:  # a failure is a result of the sweep
            median, scale, error = math.nan, math.nan, f"{type(exc).__name__}: {exc}"[:100]
        ratio = median / truth
        rows.append({
            "polarity": polarity, "diameter": diameter, "noise": noise, "grain": grain, "truth_px": round(truth, 2),
            "median_px": round(median, 2), "scale_px": scale, "ratio": round(ratio, 3),
            "ok": bool(abs(ratio - 1) <= 0.1), "error": error,
        })  # fmt: skip
        r = rows[-1]
        print(
            f"| {polarity} | {diameter} | {noise} | {grain} | {r['truth_px']} | {r['median_px']} | {r['ratio']} | "
            f"{'ok' if r['ok'] else 'OFF'} | {error} |",
            flush=True,
        )
    ok = sum(r["ok"] for r in rows)
    print(f"within 10 %: {ok} / {len(rows)}; {time.perf_counter() - start:.0f} s")
    if args.csv:
        with open(args.csv, "w", newline="") as f:
            writer = csv.DictWriter(f, list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)


if __name__ == "__main__":
    main()
