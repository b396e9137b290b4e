"""One row per segment run: its closed-loop check (metrics.json) beside drgan.evaluate's figures on real images.

    python experiments/statistics/recapture_table.py NAME=SEGMENT_RUN:EVALUATE_OUT ...

For issue 67's recapture comparison (experiments/statistics/README.md): U-Nets trained on the same generator's pairs
rendered with and without material.imaging.recapture, scored on their own held-out pairs and on tio2_sem's ids.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path


def _run0(path: Path, header: str) -> list[str]:
    """The cells of the run0 row of the table whose header starts with ``header`` in a Markdown file."""
    lines = path.read_text().splitlines()
    for i, line in enumerate(lines):
        if line.startswith(header):
            for row in lines[i + 2 :]:
                if row.startswith("| run0"):
                    return [c.strip() for c in row.strip("|").split("|")]
    raise SystemExit(f"{path}: no run0 row under {header!r}")


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
        scores = _run0(evaluated / "results.md", "| | DSC")
        sizes = _run0(evaluated / "statistics.md", "| run | median diameter")
        sources = _run0(evaluated / "statistics.md", "| run | true particles")
        first = [re.sub(r" \[.*", "", c) for c in sizes]
        print(
            f"| {name} | {loop} | {scores[1]} / {scores[2]} | {first[2]} / {first[4]} | {sources[3]} / {sources[5]} |"
        )


if __name__ == "__main__":
    main()
