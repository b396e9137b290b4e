"""Does a weak U-Net seed show itself without annotations? Its agreement with the classical segmentation.

On tio2_sem's pipeline pairs one U-Net seed in four misses the agglomerates' inner particles (test DSC 0.730 against
0.93). The classical threshold finds the particles' area on these images (DSC 0.81-0.90) without training, so a
segmenter whose foreground leaves much of the classical foreground uncovered is suspect before any annotation is
consulted. This script compares ``drgan.evaluate`` outputs on the same images (their ``labels/<id>.tif``): each
segmenter against the classical run (no truth used), and each against the truth (the evaluate's own results.csv).

    python -m drgan.evaluate model=classical data=DATA subset=train out=CLASSICAL
    python -m drgan.evaluate model=CKPT data=DATA subset=train out=RUN      # per segmenter
    python experiments/statistics/seed_agreement.py CLASSICAL NAME=RUN [NAME=RUN ...]

Columns: ``covered`` (share of the classical foreground the segmenter's foreground covers, pooled over images),
``dice`` (the two foregrounds' Dice), ``median ratio`` (the segmenter's median equivalent diameter over the
classical one, both from statistics.csv), then the truth's DSC and AP50 (mean over images) and median error.
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import numpy as np
import tifffile


def _labels(folder: Path) -> dict[str, np.ndarray]:
    return {p.stem: tifffile.imread(p) for p in sorted((folder / "labels").glob("*.tif"))}


def _statistic(folder: Path, name: str) -> float:
    with open(folder / "statistics.csv", newline="") as f:
        return next(float(r["value"]) for r in csv.DictReader(f) if r["statistic"] == name)


def _truth(folder: Path) -> tuple[float, float]:
    with open(folder / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    return float(np.mean([float(r["dsc"]) for r in rows])), float(np.mean([float(r["ap50"]) for r in rows]))


def agreement(classical: dict[str, np.ndarray], found: dict[str, np.ndarray]) -> tuple[float, float]:
    """(covered, dice) of the pooled foregrounds over the images both hold."""
    both = sorted(set(classical) & set(found))
    if not both:
        raise SystemExit("no image in common between the classical run and the segmenter's")
    c = np.concatenate([(classical[k] > 0).ravel() for k in both])
    s = np.concatenate([(found[k] > 0).ravel() for k in both])
    overlap = float(np.logical_and(c, s).sum())
    return overlap / max(float(c.sum()), 1.0), 2 * overlap / max(float(c.sum() + s.sum()), 1.0)


def main(argv: list[str]) -> None:
    if len(argv) < 2 or any("=" not in a for a in argv[1:]):
        raise SystemExit(__doc__)
    classical_dir = Path(argv[0])
    classical = _labels(classical_dir)
    classical_median = _statistic(classical_dir, "median_diameter")
    cdsc, cap = _truth(classical_dir)
    print("| segmenter | covered | dice | median ratio | truth DSC | truth AP50 | median error |")
    print("|---|---|---|---|---|---|---|")
    true_median = _statistic(classical_dir, "median_diameter_true")
    print(f"| classical | 1 | 1 | 1 | {cdsc:.3f} | {cap:.3f} | {classical_median / true_median - 1:+.1%} |")
    for arg in argv[1:]:
        name, folder = arg.split("=", 1)
        folder = Path(folder)
        covered, dice = agreement(classical, _labels(folder))
        median = _statistic(folder, "median_diameter")
        dsc, ap50 = _truth(folder)
        error = median / _statistic(folder, "median_diameter_true") - 1
        print(
            f"| {name} | {covered:.3f} | {dice:.3f} | {median / classical_median:.3f} | {dsc:.3f} | {ap50:.3f} | {error:+.1%} |"
        )


if __name__ == "__main__":
    main(sys.argv[1:])
