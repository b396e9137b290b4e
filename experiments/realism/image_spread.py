"""Issue 29's spread check: does a generated set span the real images' spread from image to image?

Per image, the background grey (median of the background pixels) and the particle contrast (Weber:
|mean particle grey - mean background grey| / mean background grey), over the generated pairs (images/ + masks/ of `drgan.generate`; partial and real background
items left out) and over real 256-px windows of the data set's **train** ids (the masks only check which pixels are
particles; windows on a stride of 256 px, info bar dropped as drgan reads it, windows with < 2 % particle pixels
left out of the contrast and < 20 % background out of the grey). Prints the 5th, 50th and 95th percentiles of each,
and the generated / real ratio of each percentile (the issue's target: within 10 %).

    python experiments/realism/image_spread.py runs/statistics/tio2_tsem/synthetic ../shared/datasets/tio2_tsem
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

WINDOW = 256
QUANTILES = (0.05, 0.5, 0.95)
MIN_PARTICLE, MIN_BACKGROUND = 0.02, 0.2


def measures(image: np.ndarray, particle: np.ndarray, known: np.ndarray) -> tuple[float, float]:
    """(background grey, particle contrast) of one image; nan where too little of either is shown."""
    background = known & ~particle
    grey = float(np.median(image[background])) if background.mean() >= MIN_BACKGROUND else float("nan")
    if particle.mean() < MIN_PARTICLE or not background.any():
        return grey, float("nan")
    # Weber contrast |particle - background| / background: for dark particles the plain ratio particle / background
    # sits near 0 (0.03-0.13 on tio2_tsem), where a few grey levels of noise floor or clipping change it by 2x
    b = max(float(image[background].mean()), 1e-6)
    return grey, abs(float(image[particle].mean()) - b) / b


def generated(folder: Path) -> list[tuple[float, float]]:
    from drgan.segmenters.pairs import load_generated_pairs

    pairs = [p for p in load_generated_pairs(folder) if p.id.startswith("syn_")]  # rendered items only
    return [measures(p.image, (p.mask == 1) | (p.mask == 2), p.mask != 255) for p in pairs]


def real(dataset: Path) -> list[tuple[float, float]]:
    from drgan.segmenters.pairs import load_real_pairs

    ids = json.loads((dataset / "split.json").read_text())["train"]  # test ids are never read
    out = []
    for pair in load_real_pairs(dataset, ids, contour_px=0):  # info bar dropped as drgan.segment reads it
        h, w = pair.image.shape
        for y in range(0, h - WINDOW + 1, WINDOW):
            for x in range(0, w - WINDOW + 1, WINDOW):
                window = (slice(y, y + WINDOW), slice(x, x + WINDOW))
                particle = pair.mask[window] > 0
                out.append(measures(pair.image[window], particle, np.ones(particle.shape, bool)))
    return out


def percentiles(values: list[tuple[float, float]]) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64)
    return np.array([np.nanquantile(arr[:, k], QUANTILES) for k in range(2)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("generated", type=Path)
    parser.add_argument("dataset", type=Path)
    args = parser.parse_args()
    gen, ref = generated(args.generated), real(args.dataset)
    g, r = percentiles(gen), percentiles(ref)
    print(
        f"generated: {len(gen)} images ({args.generated}); real: {len(ref)} train windows of {WINDOW} px ({args.dataset})"
    )
    print("\n| measure | percentile | real | generated | generated / real |\n|---|---|---|---|---|")
    for k, name in enumerate(("background grey", "particle contrast")):
        for j, q in enumerate(QUANTILES):
            print(f"| {name} | {q * 100:.0f}th | {r[k, j]:.3f} | {g[k, j]:.3f} | {g[k, j] / r[k, j]:.3f} |")


if __name__ == "__main__":
    main()
