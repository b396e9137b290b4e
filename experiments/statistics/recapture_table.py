"""One row per segment run: its closed-loop check (metrics.json) beside drgan.evaluate's figures on real images.

    python experiments/statistics/recapture_table.py NAME=SEGMENT_RUN:EVALUATE_OUT ...

For issue 67's recapture comparison (experiments/statistics/README.md): U-Nets trained on the same generator's pairs
rendered with and without material.imaging.recapture, scored on their own held-out pairs and on tio2_sem's ids.
evaluate's CSVs are read with experiments/pipeline/pairs_table.py's reader (one reader of them for both tables).
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "pipeline"))
from pairs_table import scores  # noqa: E402


def shares(folder: Path) -> dict[str, float]:
    """run0's merged and missed shares of the true particles (statistics.csv's sources/ rows)."""
    rows = {r["statistic"]: float(r["value"]) for r in csv.DictReader((folder / "statistics.csv").open())
            if r["run"] == "run0" and r["statistic"].startswith("sources/")}  # fmt: skip
    n_true = rows["sources/n_true"]
    return {key: rows[f"sources/{key}"] / n_true for key in ("merged", "missed")}


def main() -> None:
    print(
        "| run | closed loop median / count / merged / AP50 | real DSC / AP50 | real median / count | real merged / missed |"
    )
    print("|---|---|---|---|---|")
    for arg in sys.argv[1:]:
        name, rest = arg.split("=", 1)
        run, evaluated = (Path(p) for p in rest.split(":"))
        check = json.loads((run / "metrics.json").read_text())["closed_loop"]
        loop = (f"{100 * check['median_error']['value']:+.1f} / {100 * check['count_error']['value']:+.1f} / "
                f"{100 * check['merged']:.1f} % / {check['ap50']:.3f}")  # fmt: skip
        real, lost = scores(evaluated), shares(evaluated)
        print(f"| {name} | {loop} | {real['dsc']:.3f} / {real['ap50']:.3f} | {100 * real['median_error']:+.1f} / "
              f"{100 * real['count_error']:+.1f} % | {100 * lost['merged']:.1f} / {100 * lost['missed']:.1f} % |")  # fmt: skip


if __name__ == "__main__":
    main()
