"""The sizes an analyze run reports, the segmenter's and the classical ones, against the annotated masks of the same
images, and which of the two the run trusted.

analyze with ``profile=`` (the pipeline wires it) writes particles.csv (the segmenter's), particles_classical.csv (the
profile's classical segmentation at half contrast, every image segmented with the profile's settings) and
summary.json's ``trusted``. This compares each table's median diameter (particles not cut by the border) and count
with the annotated masks' on the images named (``--subset``: the split's train or test ids; all: every annotated
image), so the trusted sizes' error is read where the user's report gives them:

    python -m drgan.analyze model=RUN/segment/checkpoints/last.ckpt images=DATASET/images profile=RUN/profile out=OUT
    python experiments/statistics/trusted_sizes.py OUT DATASET [--subset test] [--name NAME]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from drgan.metrics.statistics import particles, read_particle_table
from drgan.segmenters.pairs import load_real_items


def table(path: Path, diameter: str) -> dict[str, tuple[int, np.ndarray]]:
    """Per image: (particles counted, diameters of those not cut by the border) from an analyze particle table."""
    return {k: (p.count, p.whole().diameter) for k, p in read_particle_table(path, diameter).items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("analyze", type=Path, help="an analyze run made with profile=")
    parser.add_argument("dataset", type=Path, help="the annotated set (images/, masks/, split.json)")
    parser.add_argument("--name", default=None, help="the row's name (default: the analyze folder's)")
    parser.add_argument("--subset", choices=("train", "test", "all"), default="test", help="which annotated ids")
    args = parser.parse_args()
    summary = json.loads((args.analyze / "summary.json").read_text())
    if not (args.analyze / "particles_classical.csv").is_file():
        raise SystemExit(f"{args.analyze}: no particles_classical.csv (run analyze with profile=PROFILE_RUN)")
    min_area = float(summary["min_area_px"])
    mine = table(args.analyze / "particles.csv", "equivalent_diameter_px")
    theirs = table(args.analyze / "particles_classical.csv", "half_contrast_diameter_px")
    split = json.loads((args.dataset / "split.json").read_text())
    ids = sorted(theirs) if args.subset == "all" else sorted(set(theirs) & set(map(str, split[args.subset])))
    truth = {}
    for item, labels in load_real_items(args.dataset, ids):
        found = particles(labels).at_least(min_area)
        truth[item.id] = (found.count, found.whole().diameter)

    def errors(found: dict) -> tuple[float, float]:
        median = np.median(np.concatenate([found.get(i, (0, np.zeros(0)))[1] for i in ids]))
        count = sum(found.get(i, (0, None))[0] for i in ids)
        masks_median = np.median(np.concatenate([truth[i][1] for i in ids]))
        masks_count = sum(truth[i][0] for i in ids)
        return median / masks_median - 1.0, count / masks_count - 1.0

    (seg_median, seg_count), (cls_median, cls_count) = errors(mine), errors(theirs)
    trusted = summary.get("trusted")
    reported = {"classical": (cls_median, cls_count)}.get(trusted, (seg_median, seg_count))
    head = [
        "run",
        f"{args.subset} images",
        "trusted",
        "segmenter median / count",
        "classical median / count",
        "reported median / count",
    ]
    print("| " + " | ".join(head) + " |\n|" + "---|" * len(head))
    cells = [(seg_median, seg_count), (cls_median, cls_count), reported]
    print(
        f"| {args.name or args.analyze.name} | {len(ids)} | {trusted} | "
        + " | ".join(f"{100 * m:+.1f} / {100 * c:+.1f} %" for m, c in cells)
        + " |"
    )


if __name__ == "__main__":
    main()
