"""The mean particle edge of each run's generated images against its real ones, from `drgan.generate`'s
edge_check.json (drgan.synthetic.edge_check), as one markdown table over the sets:

    python experiments/statistics/edge_table.py NAME=RUN [NAME=RUN ...]   # RUN: a pipeline run (RUN/generate) or
                                                                          # a generate folder

Columns: isolated particles measured (real / generated); where half contrast lies from the classical outline (px,
> 0 outside) on the real and the generated images, and from the exact mask edge on the generated ones (0: the masks
follow the half-contrast convention, ISO 13322-1); the 10-90 % ramp widths and their ratio (generated / real).
A blank: too few isolated particles on that side (the check needs whole particles apart from their neighbours)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def edge_check(run: Path) -> dict:
    for path in (run / "generate" / "edge_check.json", run / "edge_check.json"):
        if path.is_file():
            return json.loads(path.read_text())
    raise SystemExit(f"{run}: no generate/edge_check.json (runs of drgan.generate write it)")


def cell(side: dict | None, key: str, fmt: str = "{:+.2f}") -> str:
    value = (side or {}).get(key)
    return "" if value is None else fmt.format(value)


def row(name: str, check: dict) -> str:
    real, generated, mask = check.get("real"), check.get("generated"), check.get("generated_mask")
    ratio = check.get("width_ratio")
    return (
        f"| {name} | {cell(real, 'particles', '{}')} / {cell(generated, 'particles', '{}')} "
        f"| {cell(real, 'half_px')} | {cell(generated, 'half_px')} | {cell(mask, 'half_px')} "
        f"| {cell(real, 'width_px', '{:.2f}')} | {cell(generated, 'width_px', '{:.2f}')} "
        f"| {'' if ratio is None else f'{ratio:.2f}'} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", help="NAME=RUN")
    args = parser.parse_args()
    print(
        "| set | isolated particles real / generated | half contrast, real (px from the classical outline) "
        "| generated (same) | generated, from the exact mask edge | ramp 10-90 % real px | generated px "
        "| ramp ratio |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for item in args.runs:
        name, _, run = item.partition("=")
        if not run:
            raise SystemExit(f"{item}: expected NAME=RUN")
        print(row(name, edge_check(Path(run))))


if __name__ == "__main__":
    main()
