"""Whether a segmenter's size bias on exact truth is its network or its split's calibration: fresh generated pairs of
the same generator (never trained on) cut in two halves; the split calibrated again on the first half (as
`drgan.segment` calibrates it on its validation pairs, the stored grid and objective) and both calibrations, the
stored one and the new one, scored on the second half as the closed-loop check scores (`drgan.segmenters.closed_loop`).

    python -m drgan.generate ckpt=RUN/train out=FRESH n=200 n_background=0 seed=1 renderer.spp=16 sampled_spp=64
    python experiments/statistics/calibration_size.py FRESH SEG_RUN_OR_CKPT [...] [--names a b c] [--calibrate 100]

A split that the network allows but the validation pairs chose badly moves to the truth with the larger calibration;
a network that merges whatever the split stays off.
"""

from __future__ import annotations

import numpy as np
from check_size import cell, checkpoint, fresh_parser, names  # this folder's script (a script's folder is on its path)

from drgan.segmenters.calibrate import GRID_DEFAULTS, as_array_free, calibrate_split, check_grid
from drgan.segmenters.closed_loop import checkable, closed_loop
from drgan.segmenters.pairs import load_generated_pairs
from drgan.segmenters.registry import load_segmenter

SPLIT_KEYS = ("split_seeds", "split_depth", "split_core")


def main() -> None:
    parser = fresh_parser(__doc__)
    parser.add_argument("--calibrate", type=int, default=100, help="pairs of the first half (the rest score)")
    args = parser.parse_args()
    pairs = [p for p in load_generated_pairs(args.fresh) if checkable(p)]
    first, second = pairs[: args.calibrate], pairs[args.calibrate :]
    print(f"calibrated on {len(first)} fresh pairs, scored on {len(second)}")
    print(
        "| segmenter | split (seeds, depth, core) | calibrated on | median error [95 %] | count error [95 %] | merged |"
    )
    print("|---|---|---|---|---|---|")
    errors: dict[str, list[tuple[float, float]]] = {"stored": [], "fresh": []}
    for name, run in zip(names(args), args.runs):
        model = load_segmenter(checkpoint(run)).eval()
        stored = model.split_calibration
        grid = check_grid({**GRID_DEFAULTS, "max_pairs": len(first), "objective": stored.get("objective", "sizes")})
        fresh = as_array_free(calibrate_split(model, first, grid))
        for kind, calibration, where in (
            ("stored", stored, f"its {stored.get('n_pairs', '?')} validation pairs"),
            ("fresh", fresh, f"{len(first)} fresh pairs"),
        ):
            check = closed_loop(model, second, calibration, n_boot=1000, pixel_scale=model.pixel_scale)
            split = ", ".join(str(calibration.get(k)) for k in SPLIT_KEYS)
            print(
                f"| {name} | {split} | {where} | {cell(check, 'median_error')} | {cell(check, 'count_error')} | "
                f"{100 * check['merged']:.1f} % |"
            )
            errors[kind].append((100 * check["median_error"]["value"], 100 * check["count_error"]["value"]))
    for kind, rows in errors.items():
        values = np.array(rows)
        sd = values.std(axis=0, ddof=1) if len(values) > 1 else np.zeros(2)
        mean = values.mean(axis=0)
        print(f"| mean | | {kind} | {mean[0]:+.1f} +- {sd[0]:.1f} | {mean[1]:+.1f} +- {sd[1]:.1f} | |")


if __name__ == "__main__":
    main()
