"""The splits within a pipeline segmenter's calibration margin (validation AP50 within 0.05 of the best, read from
its segment.log), ranked by how near their particle count on the user's own images (up to 8 the profile segmented,
as the agreement check reads them) comes to the classical segmentation's count. No annotation is read: a lead for
breaking the size-first calibration's ties on real images (experiments/statistics/chain.md, "The closed loop over
the sets, three seeds").

    python experiments/statistics/split_by_real_count.py runs/benchmarks/pipeline/tsem4_0 /work/data/emps/tsem4/images
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np

from drgan.data.imagej import read_label_tiff
from drgan.data.images import list_images
from drgan.metrics.instance_scores import binarize_and_label
from drgan.segmenters.agreement import spread
from drgan.segmenters.inference import (
    check_noise_match,
    filled_holes,
    probs_at_scale,
    split_touching,
    without_annotations,
)
from drgan.segmenters.pairs import read_image_item
from drgan.segmenters.registry import load_segmenter

CORES = [None, 0.5, 0.7, 0.8, 0.9, 0.95, 0.98]  # the calibration table's columns
MARGIN = 0.05  # the size-first objective's AP50 margin
MIN_AREA = 8  # px: specks, as drgan.evaluate


def calibration_table(log: str) -> tuple[dict, tuple[str, ...]]:
    """{(seeds, depth, core): validation AP50} of the split calibration segment.log printed, and its choice."""
    block = log[log.index("split chosen") :]
    table = {}
    for seeds, depth, cells in re.findall(r"^\| (hmaxima|components), (\d+) \| (.*) \|$", block, re.M)[:10]:
        for core, cell in zip(CORES, cells.split(" | ")):
            table[(seeds, float(depth), core)] = float(cell.strip("*"))
    chosen = re.search(r"split_seeds (\w+), split_depth ([\d.]+), split_core ([\w.]+)", block).groups()
    return table, chosen


def counted(labels: np.ndarray) -> int:
    return int((np.bincount(labels.ravel())[1:] >= MIN_AREA).sum())


def main() -> None:
    run, images = Path(sys.argv[1]), Path(sys.argv[2])
    table, chosen = calibration_table((run / "segment" / "segment.log").read_text())
    best = max(table.values())
    candidates = {k: v for k, v in table.items() if v >= best - MARGIN}
    model = load_segmenter(run / "segment" / "checkpoints" / "last.ckpt")
    scale = float(getattr(model, "pixel_scale", 1.0))
    level = check_noise_match(getattr(model, "train_noise", None))
    labels_dir = run / "profile" / "labels"
    ids = spread(sorted(p.stem for p in labels_dir.glob("*.tif")), 8)
    predicted, n_classical = [], 0
    for path, image_id in zip(list_images(images, ids), ids):
        item = read_image_item(path, image_id, "auto")
        predicted.append((item.image, probs_at_scale(model, item.image, scale, level)[:3]))
        n_classical += counted(read_label_tiff(labels_dir / f"{image_id}.tif")[0])
    ranked = []
    for (seeds, depth, core), ap50 in candidates.items():
        n = 0
        for image, probs in predicted:
            classes = filled_holes(split_touching(probs, depth / scale, 1.0 / scale, core, seeds))
            n += counted(binarize_and_label(without_annotations(classes, image).astype(np.int64), particle_class=1))
        ranked.append((abs(n / n_classical - 1), seeds, depth, core, ap50, n))
    print(f"{run.name}: classical count {n_classical} on {len(ids)} images; the size-first choice {chosen}")
    for _, seeds, depth, core, ap50, n in sorted(ranked, key=lambda r: r[0]):
        print(
            f"  {seeds:10s} depth {depth:4.1f} core {core!s:5s} validation AP50 {ap50:.3f}: {n} particles "
            f"({100 * (n / n_classical - 1):+.1f} % from the classical count)"
        )


if __name__ == "__main__":
    main()
