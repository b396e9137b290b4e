"""The scale search's map, on a grid: for every EMPS image, what segmenting at each scale gives.

    PYTHONPATH=src OMP_NUM_THREADS=1 python experiments/profile/scale_map.py --csv F [--jobs 2] [--half all|dev|held]

The particle scale is searched as a fixed point of s -> median diameter of the segments made with the settings of s
(`drgan.data.classical.search_scale`). Following that map from a few starts lands in one of several basins on
textured images, and a small change anywhere moves which. This script segments each image at every scale of a
quarter-octave grid (6 px to half the image's shorter side), with both neck depths, and writes what the search's
choice could rest on (one row per image, depth and scale): the segments' median and area-weighted median, how many
there are, their size spread, their mean solidity, the threshold's separability. The instance maps' numbers are
added for the analysis (read only after segmenting, as in `emps_check.py`).
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi
from skimage.measure import regionprops
from skimage.segmentation import find_boundaries

from drgan.data.classical import (
    CALIBRATION,
    SegmentParams,
    cut_foreground,
    estimate_scale,
    prepare,
    retry_separability,
    size_spread,
    split_touching,
)
from drgan.data.images import read_grey
from drgan.data.polarity import resolve_polarity

ROOT = Path("/work/shared/datasets/emps_train")


def grid(shape: tuple[int, int]) -> np.ndarray:
    """CALIBRATION.min_scale to half the shorter side, CALIBRATION.scale_step apart."""
    top, low, step = 0.5 * min(shape), CALIBRATION.min_scale, CALIBRATION.scale_step
    n = int(math.floor(math.log(top / low) / math.log(step) + 1e-9)) + 1
    return low * step ** np.arange(n)


def segment_rows(labels: np.ndarray, params: SegmentParams, bright: np.ndarray, gradient: np.ndarray) -> dict:
    areas = np.bincount(labels.ravel())
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    plausible = (areas >= params.min_area) & (areas <= params.max_area)
    plausible[0] = False
    inner = plausible.copy()
    inner[border] = False
    d = 2.0 * np.sqrt(areas[inner] / np.pi)
    solidity = [r.solidity for r in regionprops(labels) if inner[r.label]] if inner.any() else []
    weighted = math.nan
    if d.size:
        ds = np.sort(d)
        c = np.cumsum(ds * ds)
        weighted = float(ds[np.searchsorted(c, 0.5 * c[-1])])
    kept = np.isin(labels, np.flatnonzero(inner))
    edge = contrast = math.nan
    if kept.any():
        rim = find_boundaries(np.where(kept, labels, 0), mode="inner") & kept
        edge = float(gradient[rim].mean() / max(np.median(gradient), 1e-9))
        outside = bright[labels == 0]
        if outside.size > 10:
            contrast = float((bright[kept].mean() - outside.mean()) / max(outside.std(), 1e-9))
    return {
        "edge": edge,
        "contrast": contrast,
        "median": float(np.median(d)) if d.size else math.nan,
        "wmedian": weighted,
        "inner": int(inner.sum()),
        "plausible": int(plausible.sum()),
        "segments": int(labels.max()),
        "spread": size_spread(d),
        "solidity": float(np.mean(solidity)) if solidity else math.nan,
        "covered": float(np.isin(labels, np.flatnonzero(plausible)).mean()) if plausible.any() else 0.0,
    }


def map_one(job: tuple[str, Path]) -> list[dict]:
    image_id, root = job
    image = read_grey(root / "images" / f"{image_id}.png", "auto")
    polarity, _ = resolve_polarity("auto", [image])
    prepared = prepare(image, polarity)
    log = estimate_scale([prepared.bright], [prepared.annotations]).diameter_px
    base = SegmentParams()
    rows = []
    start = time.perf_counter()
    for scale in grid(prepared.bright.shape):
        resolved = replace(base, min_separability=0.0).resolved(float(scale))
        cut = cut_foreground(prepared, resolved, retry_below=retry_separability(base))
        gradient = ndi.gaussian_gradient_magnitude(prepared.bright, max(1.0, resolved.sigma))
        for depth in (0.0, CALIBRATION.neck_depth):
            labels = split_touching(cut.foreground, replace(resolved, neck_depth=depth))
            rows.append({
                "id": image_id, "polarity": polarity, "log_px": log, "depth": depth, "scale": round(float(scale), 3),
                "separability": cut.separability,
                **segment_rows(labels, resolved, prepared.bright, gradient),
            })  # fmt: skip
    for r in rows:
        r["seconds"] = round(time.perf_counter() - start, 1)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--csv", type=Path, required=True)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--half", choices=("all", "dev", "held"), default="all")
    parser.add_argument("--images", type=Path, default=ROOT)
    args = parser.parse_args()
    ids = sorted(p.stem for p in (args.images / "images").glob("*.png"))
    if args.half != "all":
        ids = [i for i in ids if (i[0] in "01234567") == (args.half == "dev")]
    rows = []
    with ProcessPoolExecutor(args.jobs) as pool:
        for k, part in enumerate(pool.map(map_one, [(i, args.images) for i in ids], chunksize=1)):
            rows += part
            if k % 20 == 0:
                print(f"{k + 1} / {len(ids)}", flush=True)
    args.csv.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.csv.with_suffix(".part")
    with tmp.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    tmp.replace(args.csv)
    print(f"{len(rows)} rows, {len(ids)} images -> {args.csv}")


if __name__ == "__main__":
    main()
