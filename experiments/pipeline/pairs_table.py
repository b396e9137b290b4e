"""The pairs curve's table (experiments/pipeline/pairs_curve.sh): per setting, the segment stage's wall time and the
test scores of its seeds (mean +- sample std; DSC and AP50 the mean over test images, as drgan.evaluate reports them).

    python experiments/pipeline/pairs_table.py runs/pairs/cej [BASELINE_EVALUATE_DIR ...]
"""

from __future__ import annotations

import csv
import re
import statistics
import sys
from collections import defaultdict
from pathlib import Path


def scores(folder: Path) -> dict[str, float]:
    rows = [r for r in csv.DictReader((folder / "results.csv").open()) if r["image"] != "mean"]
    out = {k: statistics.mean(float(r[k]) for r in rows) for k in ("dsc", "ap50", "sq")}
    stats = {r["statistic"]: float(r["value"]) for r in csv.DictReader((folder / "statistics.csv").open())}
    for key in ("median_error", "count_error"):
        if key in stats:
            out[key] = stats[key]
    return out


def spread(values: list[float], form: str) -> str:
    import math

    missing = sum(1 for v in values if not math.isfinite(v))  # e.g. a median of a run that found no particle
    values = [v for v in values if math.isfinite(v)]
    if not values:
        return "n/a"
    if missing:
        return spread(values, form) + f" ({missing} n/a)"
    mean = statistics.mean(values)
    return form.format(mean) + (
        f" +- {form.replace('+', '').format(statistics.stdev(values))}" if len(values) > 1 else ""
    )


def main() -> None:
    root = Path(sys.argv[1])
    times = {}
    if (root / "times.txt").is_file():
        for line in (root / "times.txt").read_text().splitlines():
            tag, _, seconds = line.split()
            times[tag] = float(seconds)
    groups: dict[str, list[tuple[str, dict]]] = defaultdict(list)
    for folder in sorted(root.glob("ev_*")):
        if (folder / "results.csv").is_file():
            tag = folder.name[3:]
            groups[re.sub(r"_s\d+", "", tag, count=1)].append((tag, scores(folder)))
    print("| setting | seeds | segment min (each) | DSC | AP50 | SQ | median error | count error |")
    print("|---|---|---|---|---|---|---|---|")
    for setting, runs in groups.items():
        minutes = " / ".join(f"{times[t] / 60:.1f}" for t, _ in runs if t in times) or "n/a"

        def col(key: str, form: str, runs=runs) -> str:
            return spread([s[key] for _, s in runs if key in s], form)

        print(f"| {setting} | {len(runs)} | {minutes} | {col('dsc', '{:.3f}')} | {col('ap50', '{:.3f}')} | "
              f"{col('sq', '{:.3f}')} | {col('median_error', '{:+.3f}')} | {col('count_error', '{:+.3f}')} |")  # fmt: skip


if __name__ == "__main__":
    main()
