"""The touching-particle split a pipeline run's U-Net chooses on its own generated validation pairs, as
`drgan.segment` chooses it after training (drgan.segmenters.calibrate), with another grid of h-maxima depths.

    python experiments/pipeline/recalibrate.py runs/pipeline/NAME [--depths 1,2,4,8,16] [--store]

Prints the AP50 table (depth x core) and the choice; ``--store`` writes the choice into RUN/segment/checkpoints/
last.ckpt (the original kept as last.before_grid.ckpt), where evaluate and analyze read it (`split_core: auto`).
The validation pairs are those `drgan.segment` held out (val_fraction 0.1, seed 0). Never a real test image."""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from drgan.checkpoint_io import add_entry
from drgan.segmenters.calibrate import (
    CHECKPOINT_KEY,
    GRID_DEFAULTS,
    as_array_free,
    calibrate_split,
    check_grid,
    markdown_table,
)
from drgan.segmenters.pairs import load_generated_pairs, split_pairs
from drgan.segmenters.registry import load_segmenter


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path)
    parser.add_argument("--depths", default=",".join(str(d) for d in GRID_DEFAULTS["depths"]))
    parser.add_argument("--store", action="store_true")
    args = parser.parse_args()
    last = args.run / "segment" / "checkpoints" / "last.ckpt"
    before = last.with_name("last.before_grid.ckpt")
    model = load_segmenter(str(before if before.is_file() else last), "model")
    pairs = load_generated_pairs(str(args.run / "generate"), setting="data")
    validation = split_pairs(pairs, 0.1, 0)[1]
    grid = check_grid({**GRID_DEFAULTS, "depths": [float(d) for d in args.depths.split(",")]})
    calibration = as_array_free(calibrate_split(model.eval(), validation, grid, progress=False))
    print(markdown_table(calibration))
    print({k: v for k, v in calibration.items() if k != "table"})
    if args.store:
        if not before.is_file():
            shutil.copy2(last, before)
        add_entry(last, CHECKPOINT_KEY, calibration, "ckpt_path")
        print(f"stored in {last}")


if __name__ == "__main__":
    main()
