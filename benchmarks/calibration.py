"""The split calibration's cost (drgan.segmenters.calibrate.calibrate_split, what drgan.segment runs after training):
the same segmenter and pairs scored with the seeds and the instance matching as they are, and as they were before
they were computed cluster by cluster and counted by id (whole-image h-maxima, overlaps through np.unique).

    python benchmarks/calibration.py SEGMENT_RUN GENERATED_SET [--pairs 50] [--real DATASET --ids N]

Prints one markdown row per way: seconds, and the chosen split with its AP50 (equal by construction for the first two
ways: they give the same seeds and the same counts); the third, without the split's speck rule
(drgan.data.classical.watershed.merge_specks), is its cost, and may choose another split. With --real, N of DATASET's
train images (as a fine-tuning calibrates on a user's corrected images) join the pairs.
"""

from __future__ import annotations

import argparse
import time
from contextlib import contextmanager
from pathlib import Path
from unittest import mock

import numpy as np


@contextmanager
def as_before():
    """The calibration's two hot spots as they were: skimage's h_maxima of the whole image, overlaps via np.unique."""
    from skimage.morphology import h_maxima

    from drgan.data.classical import watershed
    from drgan.metrics import instance_scores

    def whole_image(distance, depth):
        return h_maxima(distance, depth).astype(bool)

    with (
        mock.patch.object(watershed, "cluster_h_maxima", whole_image),
        mock.patch.object(instance_scores, "DENSE_PAIRS", 0),
    ):
        yield


def without_speck_rule():
    """The U-Net's split as before the speck rule: every watershed region kept, however small."""
    from drgan.data.classical import watershed

    return mock.patch.object(watershed, "merge_specks", lambda labels, min_px: labels)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path)
    parser.add_argument("generated", type=Path)
    parser.add_argument("--pairs", type=int, default=50)
    parser.add_argument("--real", type=Path)
    parser.add_argument("--ids", type=int, default=1)
    args = parser.parse_args()

    import torch

    from drgan.scene.labels import class_mask
    from drgan.segmenters.calibrate import calibrate_split
    from drgan.segmenters.pairs import Pair, load_generated_pairs, load_real_items, real_ids
    from drgan.segmenters.registry import load_segmenter

    torch.set_num_threads(2)
    model = load_segmenter(args.run / "checkpoints" / "last.ckpt")
    pairs = [p for p in load_generated_pairs(args.generated) if p.labels is not None][: args.pairs]
    if args.real:
        ids = real_ids(args.real, None, "train")[: args.ids]
        pairs = [Pair(i.id, i.image, class_mask(lab, 1), lab) for i, lab in load_real_items(args.real, ids)] + pairs
    grid = {
        "cores": [None, 0.5, 0.7, 0.8, 0.9, 0.95, 0.98],
        "depths": [1.0, 2.0, 4.0, 8.0, 16.0],
        "seeds": ["hmaxima", "components"],
        "objective": "sizes",
    }  # fmt: skip  (segment.yaml's)
    print("| way | pairs | px | seconds | chosen | AP50 |\n|---|---|---|---|---|---|")
    ways = (
        ("before (whole-image h-maxima, np.unique)", as_before),
        ("now", None),
        ("now, no speck rule", without_speck_rule),
    )
    for name, context in ways:
        start = time.perf_counter()
        if context is None:
            result = calibrate_split(model, pairs, grid)
        else:
            with context():
                result = calibrate_split(model, pairs, grid)
        seconds = time.perf_counter() - start
        chosen = f"{result.get('split_seeds')} / {result['split_depth']} / {result['split_core']}"
        px = int(sum(np.asarray(p.image).size for p in pairs))
        print(f"| {name} | {len(pairs)} | {px:,} | {seconds:.1f} | {chosen} | {result['ap50']:.3f} |")


if __name__ == "__main__":
    main()
