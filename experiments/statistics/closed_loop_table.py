"""The closed-loop checks of segment runs as one table: `python experiments/statistics/closed_loop_table.py RUN/metrics.json ...`"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def percent(cell) -> str:
    value = cell.get("value") if isinstance(cell, dict) else cell
    return "n/a" if value is None else f"{100 * value:+.1f} %"


def main() -> None:
    print("| run | pairs | particles | median error [95 %] | mean error | count error | edge offset px | merged | split "
          "| missed | AP50 | val DSC |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for path in sys.argv[1:]:
        metrics = json.loads(Path(path).read_text())
        c = metrics.get("closed_loop")
        if not c:
            print(f"| {Path(path).parent.name} | no check |")
            continue
        m = c["median_error"]
        interval = f" [{percent(m['low'])}, {percent(m['high'])}]" if m.get("low") is not None else ""
        share = lambda k, c=c: "n/a" if c.get(k) is None else f"{100 * c[k]:.1f} %"  # noqa: E731
        print(
            f"| {Path(path).parent.name} | {c['n_pairs']} | {c['n_true']} | {percent(m)}{interval} | "
            f"{percent(c['mean_error'])} | {percent(c['count_error'])} | {c['edge_offset_px']:+.2f} | {share('merged')} "
            f"| {share('split')} | {share('missed')} | {c['ap50']:.3f} | {metrics.get('val/dsc', float('nan')):.3f} |"
        )


if __name__ == "__main__":
    main()
