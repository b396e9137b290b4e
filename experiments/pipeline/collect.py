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
        "ks": _ms([stats[r]["ks"] for r in runs]),
        "w1": _ms([stats[r]["w1"] for r in runs], 1, 2),
        "split": " / ".join(f"{100 * share(r, 'split'):.0f}" for r in runs),
        "merged": " / ".join(f"{100 * share(r, 'merged'):.0f}" for r in runs),
        "missed": " / ".join(f"{100 * share(r, 'missed'):.0f}" for r in runs),
        "offset": _ms([stats[r].get("sources/diameter_offset", np.nan) for r in runs], 1, 2, True),
    }


def main(folders: list[str]) -> None:
    head = (
        "| set | segmenter | runs | DSC | AP50 | PQ | median error % | count error % | KS | W1 px | merged % | split % | "
        "missed % | offset px |"
    )
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
                      f"{s['count']} | {s['ks']} | {s['w1']} | {s['merged']} | {s['split']} | {s['missed']} | {s['offset']} |")  # fmt: skip
        stages = state.get("stages", {})
        line = " | ".join(f"{stages[k].get('seconds', 0) / 60:.1f}" if k in stages else "" for k in
                          ("profile", "train", "generate", "segment", "analyze", "evaluate"))  # fmt: skip
        train = (stages.get("train") or {}).get("summary") or {}
        times.append(f"| {run.name} | {line} | {train.get('line', '')} |")
    print("\n| set | profile | train | generate | segment | analyze | evaluate | GAN |")
    print("|---|---|---|---|---|---|---|---|")
    print("\n".join(times))
    print(grey_table(folders))


def _grey(start: dict, key: str) -> str:
    if not start:
        return ""
    return f"{start['first'][key]:.3f} -> {start['last'][key]:.3f} ({start['real'][key]:.3f})"


def _ratio(best: dict, key: str) -> str:
    low, high = (best.get("brightness_range") or {}).get(key, (np.nan, np.nan))
    return f"{best[key + '_brightness']:.2f} ({low:.2f}-{high:.2f})"


def grey_table(folders: list[str]) -> str:
    """Where the GAN's grey started (the grey start: first render -> after it; real) and where the chosen epoch is."""
    lines = [
        "| set | particle grey: first -> start (real) | background grey: first -> start (real) | chosen epoch | "
        "particle x real (range) | background x real (range) | in range |",
        "|---|---|---|---|---|---|---|",
    ]
    for name in folders:
        run = Path(name)
        best_path = run / "train" / "checkpoints" / "best_epoch.json"
        start_path = run / "train" / "grey_start.json"
        if not best_path.is_file():
            continue
        best = json.loads(best_path.read_text())
        start = json.loads(start_path.read_text()) if start_path.is_file() else {}
        lines.append(
            f"| {run.name} | {_grey(start, 'particle')} | {_grey(start, 'background')} | {best['epoch']} "
            f"(FID {best['fid']:.1f}) | {_ratio(best, 'particle')} | {_ratio(best, 'background')} | "
            f"{'yes' if best.get('brightness_ok') else 'no'} |"
        )
    return "\n" + "\n".join(lines)


if __name__ == "__main__":
    main(sys.argv[1:])
