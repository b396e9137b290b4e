"""The touching-particle split a pipeline run's U-Net chooses on its own generated validation pairs, as
`drgan.segment` chooses it after training (drgan.segmenters.calibrate), with another grid of h-maxima depths.

    python experiments/pipeline/recalibrate.py runs/pipeline/NAME [--depths 1,2,4,8,16] [--store] [--check]
    python experiments/pipeline/recalibrate.py SEGMENT_RUN --generated GENERATED ...     # any segment run folder
    python experiments/pipeline/recalibrate.py SEGMENT_RUN --generated GENERATED --seed 2 \
        --guard USER_IMAGES PROFILE_LABELS --store --check   # as drgan.segment seed=2 with its agreement settings
    python experiments/pipeline/recalibrate.py ... --texture 0.1   # on pairs as textured as the training crops

Prints the AP50 table (seeds, depth x core) and the choice; ``--store`` writes the choice into the run's
checkpoints/last.ckpt (the original kept as last.before_grid.ckpt), where evaluate and analyze read it (`split_core:
auto`); ``--check`` then scores the closed-loop check again with it (drgan.segmenters.closed_loop) and stores it too.
The validation pairs are those `drgan.segment` held out (its closed-loop pairs set aside first, then val_fraction 0.1,
both drawn with the run's seed: ``--seed``, default 0). ``--guard``: the user's images and the profile's classical
labels, with which `drgan.segment` checks the split's real count (drgan.segmenters.calibrate.real_count_guard; the
pipeline passes its agreement folders). Never a real test image."""

from __future__ import annotations

import argparse
import logging
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np

from drgan.core.checkpoint_io import add_entry
from drgan.segment import calibrate
from drgan.segmenters.agreement import AgreementSettings, read_reference
from drgan.segmenters.calibrate import GRID_DEFAULTS, check_grid
from drgan.segmenters.closed_loop import CLOSED_LOOP_KEY, closed_loop, hold_out, log_summary, trust_line
from drgan.segmenters.pairs import load_generated_pairs, split_pairs, with_texture
from drgan.segmenters.registry import load_segmenter


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path)
    parser.add_argument("--depths", default=",".join(str(d) for d in GRID_DEFAULTS["depths"]))
    parser.add_argument("--store", action="store_true")
    parser.add_argument("--check", action="store_true")
    parser.add_argument("--objective", default=GRID_DEFAULTS["objective"], choices=("ap50", "sizes"))
    parser.add_argument("--generated", type=Path, default=None, help="the pairs of a segment run folder given as run")
    parser.add_argument("--check-fraction", type=float, default=0.05)
    parser.add_argument("--seed", type=int, default=0, help="the segment run's seed (its validation split's)")
    parser.add_argument(
        "--texture",
        type=float,
        default=0.0,
        help="calibrate on validation pairs with the training crops' surface texture added (its std drawn from [0, "
        "this], drgan.segmenters.pairs.with_texture; loader.texture's default 0.1): a diagnosis, never stored",
    )
    parser.add_argument(
        "--guard",
        type=Path,
        nargs=2,
        default=None,
        metavar=("IMAGES", "LABELS"),
        help="the real-count guard's user images and classical labels (drgan.segment's agreement.*)",
    )
    args = parser.parse_args()
    folder = args.run if args.generated else args.run / "segment"
    last = folder / "checkpoints" / "last.ckpt"
    before = last.with_name("last.before_grid.ckpt")
    model = load_segmenter(str(before if before.is_file() else last), "model")
    pairs = load_generated_pairs(str(args.generated or args.run / "generate"), setting="data")
    ids = set((model.closed_loop or {}).get("ids") or [])
    if ids:
        rest, check = [p for p in pairs if p.id not in ids], [p for p in pairs if p.id in ids]
    else:
        rest, check = hold_out(pairs, args.check_fraction, args.seed)
    validation = split_pairs(rest, 0.1, args.seed)[1]
    if args.texture > 0:
        if args.store:
            raise SystemExit("--texture is a diagnosis: not with --store")
        rng = np.random.default_rng(args.seed)
        validation = [replace(p, image=with_texture(p.image, args.texture, rng).astype(np.float32)) for p in validation]
    grid = check_grid(
        {**GRID_DEFAULTS, "depths": [float(d) for d in args.depths.split(",")], "objective": args.objective}
    )
    real_items = None
    if args.guard:
        real_items = read_reference(AgreementSettings(images=args.guard[0], reference=args.guard[1]))
    if args.store and not before.is_file():
        shutil.copy2(last, before)
    # as drgan.segment calibrates after training: the split, the real-count guard, then (--store) the checkpoint entry
    calibration = calibrate(model, validation, grid, last, progress=False, real_items=real_items, store=args.store)
    if calibration is None:
        raise SystemExit(f"no split calibrated for {last}")
    print({k: v for k, v in calibration.items() if k != "table"})
    if args.check and check:
        result = closed_loop(model.eval(), check, calibration)
        log_summary(result)
        print(trust_line(result))
        if args.store:
            add_entry(last, CLOSED_LOOP_KEY, result, "ckpt_path")


if __name__ == "__main__":
    main()
