"""A set's segmenter seeds as one table: the closed-loop check on held-out generated pairs beside the annotated test
ids' scores, per seed and as mean +- std (issue 67's "3 seeds" rows).

    python experiments/statistics/seed_table.py NAME SEGMENT_RUN:EVALUATE_RUN ...

e.g. for a pipeline run (seed 0) and two more U-Nets on its pairs (experiments/statistics/chain.md, "The closed loop
over the sets, three seeds"):

    R=runs/benchmarks/pipeline/cej_0 S=runs/seeds/cej
    python experiments/statistics/seed_table.py cej $R/segment:$R/evaluate $S/seg_1:$S/ev_1 $S/seg_2:$S/ev_2
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import numpy as np


def _rows(path: Path) -> list[dict]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


def evaluate_runs(folder: Path) -> list[dict]:
    """Each run of one drgan.evaluate folder (``models=[...]``: one per model), in its order: the mean DSC / AP50 / SQ
    over the test images and the median and count errors (%). A pipeline's evaluate also scores run "reported" in
    statistics.csv only: it has no row in results.csv, so it is not one of them."""
    means = [r for r in _rows(folder / "results.csv") if r["image"] == "mean"]
    stats: dict[str, dict[str, float]] = {}
    for r in _rows(folder / "statistics.csv"):
        stats.setdefault(r["run"], {})[r["statistic"]] = float(r["value"])
    return [
        {
            "dsc": float(m["dsc"]),
            "ap50": float(m["ap50"]),
            "sq": float(m["sq"]),
            "median": 100 * stats[m["run"]]["median_error"],
            "count": 100 * stats[m["run"]]["count_error"],
        }
        for m in means
    ]


def seed_row(segment: Path, evaluate: Path) -> dict:
    """One seed: the segment run's closed-loop check beside its (first) network's scores on the test ids."""
    check = json.loads((segment / "metrics.json").read_text())["closed_loop"]
    return {
        "cl_median": 100 * check["median_error"]["value"],
        "cl_count": 100 * check["count_error"]["value"],
        "cl_merged": 100 * check["merged"],
        "cl_edge": check["edge_offset_px"],
        **evaluate_runs(evaluate)[0],
    }


FORMATS = {"cl_median": "+.1f", "cl_count": "+.1f", "cl_merged": ".1f", "cl_edge": "+.2f", "dsc": ".3f", "ap50": ".3f",
           "sq": ".3f", "median": "+.1f", "count": "+.1f"}  # fmt: skip


def formatted(key: str, value: float, spread: float | None = None) -> str:
    text = format(value, FORMATS[key])
    return text if spread is None else f"{text} +- {format(spread, FORMATS[key].lstrip('+'))}"


def main() -> None:
    name, runs = sys.argv[1], sys.argv[2:]
    rows = []
    for spec in runs:
        segment, evaluate = (Path(p) for p in spec.split(":"))
        rows.append(seed_row(segment, evaluate))
    header = (
        "| set | seed | closed loop median | count | merged | edge px | test DSC | AP50 | SQ | median | count |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|"
    )
    print(header)
    for k, row in enumerate(rows):
        print(f"| {name} | {k} | " + " | ".join(formatted(c, row[c]) for c in FORMATS) + " |")
    if len(rows) > 1:
        values = {c: np.array([r[c] for r in rows]) for c in FORMATS}
        cells = [formatted(c, float(values[c].mean()), float(values[c].std(ddof=1))) for c in FORMATS]
        print(f"| **{name}** | **{len(rows)} seeds** | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
