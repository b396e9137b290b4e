"""Which touching-particle split would the real annotated *train* images choose for a segmenter? An upper bound on
what calibrating the split (drgan.segmenters.calibrate, done on generated validation pairs) can gain; never run on
test ids. Prints the AP50 table (h-maxima depth x core) on the first N train images, noise-matched as evaluate does.

    python experiments/statistics/split_oracle.py runs/pipeline/bam_tio2_sem/segment/checkpoints/last.ckpt \
        ../shared/datasets/tio2_sem --level 0.0225 --n 8
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from drgan.segmenters.calibrate import as_array_free, calibrate_split, check_grid, markdown_table
from drgan.segmenters.noise_match import match_noise
from drgan.segmenters.pairs import load_real_pairs, real_ids
from drgan.segmenters.registry import load_segmenter


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("ckpt")
    parser.add_argument("data")
    parser.add_argument("--level", type=float, default=0.0, help="noise-matching level (the segmenter's own)")
    parser.add_argument("--n", type=int, default=8)
    args = parser.parse_args()
    model = load_segmenter(args.ckpt, "model").eval()
    ids = real_ids(args.data, None, "train")[: args.n]
    pairs = [
        replace(p, image=match_noise(p.image, args.level).astype(np.float32))
        for p in load_real_pairs(args.data, ids, 1)
    ]
    grid = check_grid({"cores": [None, 0.5, 0.7, 0.9, 0.98], "depths": [0.5, 1.0, 2.0, 4.0], "max_pairs": 100})
    calibration = as_array_free(calibrate_split(model, pairs, grid))
    print(markdown_table(calibration))
    print({k: v for k, v in calibration.items() if k != "table"})


if __name__ == "__main__":
    main()
