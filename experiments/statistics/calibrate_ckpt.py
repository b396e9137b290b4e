"""Choose and store the touching-particle split of segmenter checkpoints on held-out generated pairs, as
`drgan.segment` does after training on its own validation pairs (drgan.segmenters.calibrate).

For U-Nets trained where the calibration did not finish (issue 27's synthetic-trained U-Nets on the lent GPU,
experiments/statistics/README.md): the pairs come from the same generator with another seed than the training set,
so none of them was trained on (rendered pairs only: no real background patches, which the U-Nets trained on).
Never real test images.

    python experiments/statistics/calibrate_ckpt.py --data runs/statistics/tio2_sem/heldout A.ckpt B.ckpt ...
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from omegaconf import OmegaConf

import drgan
from drgan.core.checkpoint_io import add_entry
from drgan.segmenters.calibrate import CHECKPOINT_KEY, as_array_free, calibrate_split, markdown_table
from drgan.segmenters.pairs import load_generated_pairs
from drgan.segmenters.registry import load_segmenter

# drgan.segment's own grid (segment.yaml's split_calibration), so both choose among the same splits
SEGMENT_YAML = Path(drgan.__file__).parent / "conf" / "segmentation" / "segment.yaml"
GRID = OmegaConf.to_container(OmegaConf.load(SEGMENT_YAML).split_calibration)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", nargs="+")
    parser.add_argument("--data", required=True, help="a drgan.generate folder (held out from every checkpoint)")
    parser.add_argument("--max-pairs", type=int, default=GRID["max_pairs"])
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    pairs = load_generated_pairs(args.data, setting="--data")
    for path in args.checkpoints:
        model = load_segmenter(path, "checkpoint")
        calibration = as_array_free(calibrate_split(model, pairs, {**GRID, "max_pairs": args.max_pairs}))
        add_entry(path, CHECKPOINT_KEY, calibration, "checkpoint")
        print(
            f"{path}: split_depth {calibration['split_depth']}, split_core {calibration['split_core']}, "
            f"AP50 {calibration['ap50']:.3f} on {calibration['n_pairs']} pairs"
        )
        print(markdown_table(calibration))


if __name__ == "__main__":
    main()
