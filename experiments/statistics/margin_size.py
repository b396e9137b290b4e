"""How much validation AP50 the size-first split must give up to measure sizes and counts on exact truth: fresh generated
pairs (never trained on) cut in two halves; every split of the calibration grid scored on both (as `drgan.segment`
calibrates, `drgan.segmenters.calibrate.calibrate_split`); for each AP50 margin the setting `sizes_best` picks on the
first half, scored on the second; and the second half's best setting whatever its AP50 (what the network allows).

    python experiments/statistics/margin_size.py FRESH SEG_RUN_OR_CKPT [...] [--names a b c] [--margins 0.05 0.1 0.2]
    python experiments/statistics/margin_size.py ... --sources   # also what became of the second half's particles

``--sources``: each pick is also scored on the second half by the closed-loop check (`closed_loop`) with what became of
every true particle (matched, merged, split, missed) and the false share: whether a count nearer the truth is particles
separated, or merges and splits that cancel.
"""

from __future__ import annotations

import math

from check_size import checkpoint, fresh_parser, names  # this folder's script (a script's folder is on its path)

from drgan.segmenters import calibrate
from drgan.segmenters.calibrate import GRID_DEFAULTS, calibrate_split, check_grid, size_error
from drgan.segmenters.closed_loop import checkable, closed_loop
from drgan.segmenters.pairs import load_generated_pairs
from drgan.segmenters.registry import load_segmenter

SPLIT_KEYS = ("split_seeds", "split_depth", "split_core")


def key(row: dict) -> tuple:
    return tuple(row[k] for k in SPLIT_KEYS)


def percent(value) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{100 * value:+.1f}"


class Fates:
    """A split's matched / merged / split / missed / false shares on ``pairs`` (the closed-loop check), one check per
    split setting however often it is picked."""

    def __init__(self, model, pairs):
        self.model, self.pairs, self.done = model, pairs, {}

    def cell(self, row: dict) -> str:
        if key(row) not in self.done:
            check = closed_loop(self.model, self.pairs, dict(zip(SPLIT_KEYS, key(row))), n_boot=50)
            shares = " / ".join(f"{100 * check[k]:.1f}" for k in ("matched", "merged", "split", "missed", "false"))
            self.done[key(row)] = f" {shares} |"
        return self.done[key(row)]


def main() -> None:
    parser = fresh_parser(__doc__)
    parser.add_argument("--half", type=int, default=100, help="pairs of the first half (the rest score)")
    parser.add_argument("--pairs", type=int, default=None, help="the first this many pairs only (a quick look)")
    parser.add_argument("--margins", type=float, nargs="+", default=[0.0, 0.05, 0.1, 0.15, 0.2, 1.0])
    parser.add_argument("--sources", action="store_true", help="each pick's matched / merged / split / missed / false")
    args = parser.parse_args()
    pairs = [p for p in load_generated_pairs(args.fresh) if checkable(p)][: args.pairs]
    first, second = pairs[: args.half], pairs[args.half :]
    print(f"chosen on {len(first)} fresh pairs, scored on {len(second)}; AP50 pooled over the pairs, as calibrated")
    extra = " matched / merged / split / missed / false |" if args.sources else ""
    print(
        f"| segmenter | AP50 margin | split (seeds, depth, core) | AP50 (first / second) | median error | count error |{extra}"
    )
    print("|---|---|---|---|---|---|" + ("---|" if args.sources else ""))
    for name, run in zip(names(args), args.runs):
        model = load_segmenter(checkpoint(run)).eval()
        if float(getattr(model, "pixel_scale", 1.0) or 1.0) != 1.0:
            raise SystemExit(f"{run}: trained at another pixel scale; this script scores at the rendered one only")
        grid = check_grid({**GRID_DEFAULTS, "objective": "sizes", "max_pairs": max(len(first), len(second))})
        tables = [calibrate_split(model, half, grid)["table"] for half in (first, second)]
        scored = {key(row): row for row in tables[1]}
        rows = [row for row in tables[0] if not math.isnan(row["ap50"])]
        particle_px = 0.0  # ties in grid order, whatever the particles' size
        fates = Fates(model, second) if args.sources else None
        fate = (lambda row: "") if fates is None else fates.cell  # noqa: E731
        for margin in args.margins:
            calibrate.SIZES_AP50_MARGIN = margin
            pick = calibrate.sizes_best(rows, particle_px)
            out = scored[key(pick)]
            print(f"| {name} | {margin:g} | {', '.join(str(v) for v in key(pick))} | {pick['ap50']:.3f} / "
                  f"{out['ap50']:.3f} | {percent(out['median_error'])} | {percent(out['count_error'])} |{fate(out)}")  # fmt: skip
        best = min(tables[1], key=size_error)
        print(f"| {name} | any (second half's best) | {', '.join(str(v) for v in key(best))} | - / {best['ap50']:.3f} | "
              f"{percent(best['median_error'])} | {percent(best['count_error'])} |{fate(best)}")  # fmt: skip


if __name__ == "__main__":
    main()
