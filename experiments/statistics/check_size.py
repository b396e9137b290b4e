"""How much of a closed-loop check's spread is the check's own sampling: segmenters scored on their own held-out pairs
(the check stored in each checkpoint) and on a larger set of fresh pairs from the same generator (rendered with another
seed, so none was trained on), both as `drgan.segment` scores them (the calibrated split at the segmenter's working
scale, `drgan.segmenters.closed_loop`).

    python -m drgan.generate ckpt=RUN/train out=FRESH n=200 n_background=0 seed=1 renderer.spp=16 sampled_spp=64
    python experiments/statistics/check_size.py FRESH SEG_RUN_OR_CKPT [...] [--names a b c]
    python experiments/statistics/check_size.py FRESH SEG_RUN_OR_CKPT [...] --mirror   # also with test-time mirroring

``--mirror``: the fresh pairs are also scored with each tile's probabilities averaged over its four mirror images
(`inference.mirror`, as nnU-Net), split as calibrated (on unmirrored probabilities).

Prints one row per segmenter: its own check and the fresh one (median and count error with their 95 % intervals, the
whole particles each median is taken over, merged share, edge offset), then the mean +- std over the segmenters.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from drgan.segmenters.closed_loop import checkable, closed_loop
from drgan.segmenters.pairs import load_generated_pairs
from drgan.segmenters.registry import load_segmenter


def checkpoint(path: Path) -> Path:
    """A segment run folder's last checkpoint, or the file given."""
    return path if path.is_file() else path / "checkpoints" / "last.ckpt"


def run_name(path: Path) -> str:
    """A row's default name: the segment run folder's (a checkpoint's: its run folder's)."""
    return path.name if path.is_dir() else path.parent.parent.name


def cell(check: dict, key: str) -> str:
    c = check[key]
    return f"{100 * c['value']:+.1f} [{100 * c['low']:+.1f}, {100 * c['high']:+.1f}]"


def row(name: str, check: dict) -> str:
    return (
        f"| {name} | {check['n_pairs']} / {check['n_true']} | {cell(check, 'median_error')} | "
        f"{cell(check, 'count_error')} | {100 * check['merged']:.1f} % | {check['edge_offset_px']:+.2f} |"
    )


def fresh_parser(doc: str) -> argparse.ArgumentParser:
    """The arguments every script of this folder that scores segmenters on fresh pairs takes: the pairs' folder, the
    segment runs (or checkpoints) and their row names (`names`)."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("fresh", type=Path, help="fresh generated pairs of the same generator (drgan.generate)")
    parser.add_argument("runs", type=Path, nargs="+", help="segment run folders or checkpoints")
    parser.add_argument("--names", nargs="*", default=None, help="row names (default: the run folders' names)")
    return parser


def names(args: argparse.Namespace) -> list[str]:
    return args.names or [run_name(r) for r in args.runs]


def main() -> None:
    parser = fresh_parser(__doc__)
    parser.add_argument("--mirror", action="store_true", help="also the fresh pairs with test-time mirroring")
    args = parser.parse_args()
    rows = names(args)
    pairs = [p for p in load_generated_pairs(args.fresh) if checkable(p)]
    print("| segmenter | check | pairs / particles | median error [95 %] | count error [95 %] | merged | edge px |")
    print("|---|---|---|---|---|---|---|")
    kinds = ("own", "fresh", "fresh mirrored") if args.mirror else ("own", "fresh")
    medians: dict[str, list[float]] = {kind: [] for kind in kinds}
    counts: dict[str, list[float]] = {kind: [] for kind in kinds}
    for name, run in zip(rows, args.runs):
        model = load_segmenter(checkpoint(run)).eval()
        checks = {"own": model.closed_loop}
        checks["fresh"] = closed_loop(model, pairs, model.split_calibration, n_boot=1000, pixel_scale=model.pixel_scale)
        if args.mirror:
            checks["fresh mirrored"] = closed_loop(
                model, pairs, model.split_calibration, n_boot=1000, pixel_scale=model.pixel_scale, mirror=True
            )
        for kind, check in checks.items():
            print(row(f"{name} | {kind}", check))
            medians[kind].append(check["median_error"]["value"])
            counts[kind].append(check["count_error"]["value"])
    for kind in kinds:
        m, c = np.array(medians[kind]) * 100, np.array(counts[kind]) * 100
        sd = lambda v: f" +- {v.std(ddof=1):.1f}" if len(v) > 1 else ""  # noqa: E731
        print(f"| mean | {kind} | | {m.mean():+.1f}{sd(m)} | {c.mean():+.1f}{sd(c)} | | |")


if __name__ == "__main__":
    main()
