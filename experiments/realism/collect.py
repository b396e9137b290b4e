"""Tabulate drgan.realism results: `python experiments/realism/collect.py runs/realism` -> one markdown line per
run (sorted by source and input size, then seed) and, per source and input size, the mean accuracy over seeds."""

from __future__ import annotations

import json
import sys
from collections import defaultdict
from pathlib import Path


def main(root: str, prefix: str = "") -> None:
    rows = []
    for path in sorted(Path(root).glob(f"{prefix}*/results.json")):
        r = json.loads(path.read_text())
        label = f"{r['source']['label']} ({r['test']['settings']['input_size']} px input)"
        rows.append((label, r["test"]["settings"]["seed"], r["test"], path.parent.name))
    print("| source | seed | patches per class | accuracy [95 % CI] | p (vs 0.5) | AUC | FID | run |")
    print("|---|---|---|---|---|---|---|---|")
    by_source = defaultdict(list)
    for label, seed, t, run in sorted(rows, key=lambda row: (row[0], row[1])):
        low, high = t["interval"]
        print(
            f"| {label} | {seed} | {t['n_per_class']} | {t['accuracy']:.3f} [{low:.3f}, {high:.3f}] | "
            f"{t['p_value']:.2g} | {t['auc']:.3f} | {t['fid']:.1f} | {run} |"
            if "fid" in t
            else f"{t['p_value']:.2g} | {t['auc']:.3f} | - | {run} |"
        )
        by_source[label].append((t["accuracy"], t["auc"]))
    print("\n| source | seeds | accuracy: mean (min-max) | AUC: mean (min-max) |\n|---|---|---|---|")
    for label, values in by_source.items():
        acc, auc = [v[0] for v in values], [v[1] for v in values]
        print(
            f"| {label} | {len(values)} | {sum(acc) / len(acc):.3f} ({min(acc):.3f}-{max(acc):.3f}) | "
            f"{sum(auc) / len(auc):.3f} ({min(auc):.3f}-{max(auc):.3f}) |"
        )


if __name__ == "__main__":
    main(*(sys.argv[1:] or ["runs/realism"]))  # ROOT [PREFIX], e.g. runs/realism sem_
