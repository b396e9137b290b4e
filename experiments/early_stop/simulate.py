"""Replay the early-stopping rule (drgan.callbacks.early_stop.should_stop) on the recorded FID histories.

    python experiments/early_stop/simulate.py [--patience 1 2 3] [--margin 0.2]

Every history below is copied from the tables of experiments/tio2_sem/README.md (its table "Every recorded training
run", by run number) and experiments/tio2_tsem/README.md (section 3). For each patience the rule runs evaluation by
evaluation, as in training, and the run "stops" at the first evaluation after which it says so. Printed per run and
patience: the evaluations the stopped run saw, its lowest FID against the whole run's lowest, and the epochs saved.
Where a run also recorded its KID, the KID screen (drgan.callbacks.fid, screen_margin) is replayed with the full KID
standing in for the screen's KID (the screen's own scatter is measured by screen_check.py): how many full FID passes
it would have saved.
"""

from __future__ import annotations

import argparse
import math

from drgan.callbacks.early_stop import should_stop

# name: (source, FIDs per evaluation, KIDs or None). Evaluations are epochs of the run as recorded.
HISTORIES = {
    "sem_s1_first (tio2_sem/README.md run 1)": ([465.1, 476.5, 479.2, 492.3, 489.8, 544.2], None),
    "sem_ring_default (tio2_sem/README.md run 7)": ([206.2, 289.3, 297.2, 262.7, 295.0, 286.9], None),
    "sem_ring45 (tio2_sem/README.md run 8)": ([309.4, 346.4, 328.2, 338.8, 339.0, 339.5], None),
    "sem_grazing_lr2e-4 (tio2_sem/README.md run 9)": ([171.2, 154.6, 169.2, 203.6], None),
    "sem_grazing_lr5e-5 + resume (run 10)": (
        [167.1, 162.5, 156.7, 152.2, 142.0, 140.0, 148.9, 158.5, 171.5],
        None,
    ),
    "sem_lr_decay (tio2_sem/README.md run 11)": ([124.6, 118.9, 111.2, 107.1, 117.0, 122.3, 124.4, 124.9], None),
    "sem_finetune (tio2_sem/README.md run 12)": ([102.2, 103.0, 105.0], None),
    "sem_r6_texture_counts, the default (run 13)": (
        [106.1, 106.2, 102.1, 90.4, 75.2, 65.2, 68.3, 69.3],
        [0.097, 0.097, 0.089, 0.073, 0.052, 0.036, 0.041, 0.044],
    ),
    "sem_r6 evaluated every 90 steps (every 2nd of the above)": (
        [106.2, 90.4, 65.2, 69.3],
        [0.097, 0.073, 0.036, 0.044],
    ),
    "tsem_transmission_v3 (tio2_tsem/README.md section 3)": (
        [252.4, 191.2, 179.9, 198.7],
        [0.304, 0.198, 0.179, 0.213],
    ),
}


def replay(fids: list[float], patience: int) -> int:
    """How many evaluations the run sees before the rule stops it (all of them if it never does)."""
    history = []
    for epoch, fid in enumerate(fids):
        history.append({"epoch": epoch, "fid": fid})
        if should_stop(history, patience) is not None:
            return len(history)
    return len(history)


def screened(kids: list[float], margin: float) -> list[bool]:
    """Per evaluation: goes on to the full FID (True) under the KID screen."""
    lowest, out = math.inf, []
    for value in kids:
        out.append(value <= lowest + abs(lowest) * margin)
        lowest = min(lowest, value)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--patience", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--margin", type=float, default=0.2)
    args = parser.parse_args()
    print(
        "| run | evaluations | lowest FID (epoch) | "
        + " | ".join(f"patience {p}: seen / lowest seen" for p in args.patience)
        + " | KID screen: full FIDs |"
    )
    print("|---|---|---|" + "---|" * len(args.patience) + "---|")
    for name, (fids, kids) in HISTORIES.items():
        best = min(range(len(fids)), key=fids.__getitem__)
        cells = []
        for patience in args.patience:
            seen = replay(fids, patience)
            low = min(range(seen), key=fids.__getitem__)
            mark = "same" if low == best else f"**worse by {fids[low] - fids[best]:.1f}**"
            cells.append(f"{seen} / {fids[low]:.1f} ({mark})")
        if kids is None:
            screen = "(no KID recorded)"
        else:
            seen = replay(fids, 2)
            kept = screened(kids[:seen], args.margin)
            lost = not kept[best] if best < seen else False
            screen = f"{sum(kept)} of {seen}" + (" **(drops the best)**" if lost else ", best kept")
        print(f"| {name} | {len(fids)} | {fids[best]:.1f} ({best}) | " + " | ".join(cells) + f" | {screen} |")


if __name__ == "__main__":
    main()
