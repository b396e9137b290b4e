"""The tables of experiments/pipeline/README.md from finished pipeline runs and their extra segmenters.

    python experiments/pipeline/collect.py runs/pipeline/bam_tio2_tsem runs/pipeline/cej ...

Per run folder: the stage times and choices (pipeline.json), and per scored group of segmenters (the pipeline's own
evaluate/, and extra/eval_<variant>/ of segmenters.sh) the mean +- sample std over its runs (seeds) of DSC, AP50 and
PQ, the median-diameter and count errors against the masks, and where the true particles went (merged with a
neighbour, missed) with the matched particles' median diameter offset (px). Prints markdown.
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import numpy as np


def _rows(path: Path) -> list[dict]:
    return list(csv.DictReader(path.open())) if path.is_file() else []


def _ms(values: list[float], scale: float = 1.0, digits: int = 3, sign: bool = False) -> str:
    v = np.asarray(values, float) * scale
    if not len(v):
        return ""
    fmt = f"{{:{'+' if sign else ''}.{digits}f}}"
    text = fmt.format(v.mean())
    return text + (f" +- {v.std(ddof=1):.{digits}f}" if len(v) > 1 else "")


def scored(folder: Path) -> dict | None:
    means = [r for r in _rows(folder / "results.csv") if r["image"] == "mean"]
    if not means:
        return None
    stats = {}
    for r in _rows(folder / "statistics.csv"):
        stats.setdefault(r["run"], {})[r["statistic"]] = float(r["value"]) if r["value"] else float("nan")
    runs = [r["run"] for r in means]

    def share(run, key):
        s = stats.get(run, {})
        return s.get(f"sources/{key}", np.nan) / s.get("sources/n_true", np.nan)

    return {
        "n": len(runs),
        "dsc": _ms([float(r["dsc"]) for r in means]),
        "ap50": _ms([float(r["ap50"]) for r in means]),
        "pq": _ms([float(r["pq"]) for r in means]),
        "median": _ms([stats[r]["median_error"] for r in runs], 100, 1, True),
        "count": _ms([stats[r]["count_error"] for r in runs], 100, 1, True),
        "merged": " / ".join(f"{100 * share(r, 'merged'):.0f}" for r in runs),
        "missed": " / ".join(f"{100 * share(r, 'missed'):.0f}" for r in runs),
        "offset": _ms([stats[r].get("sources/diameter_offset", np.nan) for r in runs], 1, 2, True),
    }


def main(folders: list[str]) -> None:
    head = "| set | segmenter | runs | DSC | AP50 | PQ | median error % | count error % | merged % | missed % | offset px |"
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    times = []
    for name in folders:
        run = Path(name)
        state = json.loads((run / "pipeline.json").read_text())
        groups = [("pipeline (default)", run / "evaluate")]
        groups += [(p.name.removeprefix("eval_"), p) for p in sorted((run / "extra").glob("eval_*")) if p.is_dir()]
        for label, folder in groups:
            s = scored(folder)
            if s:
                print(f"| {run.name} | {label} | {s['n']} | {s['dsc']} | {s['ap50']} | {s['pq']} | {s['median']} | "
                      f"{s['count']} | {s['merged']} | {s['missed']} | {s['offset']} |")  # fmt: skip
        stages = state.get("stages", {})
        line = " | ".join(f"{stages[k].get('seconds', 0) / 60:.1f}" if k in stages else "" for k in
                          ("profile", "train", "generate", "segment", "analyze", "evaluate"))  # fmt: skip
        train = (stages.get("train") or {}).get("summary") or {}
        times.append(f"| {run.name} | {line} | {train.get('line', '')} |")
    print("\n| set | profile | train | generate | segment | analyze | evaluate | GAN |")
    print("|---|---|---|---|---|---|---|---|")
    print("\n".join(times))


if __name__ == "__main__":
    main(sys.argv[1:])
