"""Polarity detection on every EMPS image alone (one image = one user's folder), before and after, and the BAM sets.

    PYTHONPATH=src OMP_NUM_THREADS=1 python experiments/profile/polarity_check.py \\
        [--before 931a875] [--csv experiments/profile/polarity_check.csv]

For each of the 366 EMPS images (`/work/shared/datasets/emps_train`), read as `python -m drgan.profile` reads it
(`read_grey(path, "auto")`: an info bar along an edge dropped), `detect_polarity([image])` runs on that one image,
once with the code of commit --before (drgan/data/polarity.py of that commit, loaded from git) and once with the
working tree's. The truth comes from the instance map (read only here): particles are bright when the mean grey
inside the instances exceeds the mean grey of the pixels outside them. Scored on images with >= 5 instances; an
error (no contrast) counts as a miss. "dev" = ids starting 0-7 (looked at while developing), "held" = 8-f (not
looked at while choosing the settings); "dense" = instances cover more than 40 % of the image. The EMPS README does
not say which image is SEM and which TEM: the split "bright particles" / "dark particles" is by the true polarity
(mostly SEM / mostly TEM bright field).

Then the two BAM sets: the 32 train ids of each split.json, rows 712-767 (the info bar) cropped, each image alone and
all 32 together (tio2_sem: bright, tio2_tsem: dark).

Prints markdown tables and writes one CSV row per EMPS image (ids, numbers; no images).
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np
from PIL import Image

from drgan.core.errors import DataError
from drgan.data import polarity as after
from drgan.data.images import read_grey

EMPS = Path("/work/shared/datasets/emps_train")
BAM = {
    "tio2_sem": ("bright", Path("/work/shared/datasets/tio2_sem")),
    "tio2_tsem": ("dark", Path("/work/shared/datasets/tio2_tsem")),
}
BAM_CROP = (712, 768)
MIN_INSTANCES = 5
DENSE = 0.4
ROOT = Path(__file__).resolve().parents[2]


def module_at(rev: str) -> types.ModuleType:
    """drgan.data.polarity as it was at commit ``rev`` (loaded from git, not imported from the tree)."""
    source = subprocess.run(
        ["git", "show", f"{rev}:src/drgan/data/polarity.py"], cwd=ROOT, check=True, capture_output=True, text=True
    ).stdout
    module = types.ModuleType(f"polarity_{rev}")
    module.__file__ = f"{rev}:src/drgan/data/polarity.py"
    sys.modules[module.__name__] = module  # dataclasses look their module up
    exec(compile(source, module.__file__, "exec"), module.__dict__)
    return module


def truth(image_id: str) -> dict:
    grey = np.asarray(Image.open(EMPS / "images" / f"{image_id}.png").convert("L"), np.float64)
    inst = np.asarray(Image.open(EMPS / "instances" / f"{image_id}.png")).astype(np.int64)
    inside, outside = grey[inst > 0], grey[inst == 0]
    polarity = None
    if inside.size and outside.size:
        polarity = "bright" if inside.mean() > outside.mean() else "dark"
    return {
        "instances": int(np.unique(inst[inst > 0]).size),
        "area_fraction": float((inst > 0).mean()),
        "truth": polarity,
    }


def detect(module, images) -> tuple[str, float, object]:
    """(polarity or "error", seconds, the estimate or None)."""
    start = time.perf_counter()
    try:
        estimate = module.detect_polarity(images)
    except DataError:
        estimate = None
    return estimate.polarity if estimate else "error", time.perf_counter() - start, estimate


def emps_rows(before) -> list[dict]:
    rows = []
    for path in sorted((EMPS / "images").glob("*.png")):
        image = read_grey(path, "auto")
        row = {"id": path.stem, "half": "dev" if path.stem[0] in "01234567" else "held", **truth(path.stem)}
        row["before"], row["before_s"], _ = detect(before, [image])
        row["after"], row["after_s"], estimate = detect(after, [image])
        if estimate is not None:
            vote = estimate.votes[0]
            row.update(convexity=vote.convexity, mode_vote=vote.mode_vote, mode_margin=vote.mode_margin)
        rows.append(row)
    return rows


def pct(rows, key) -> str:
    if not rows:
        return "-"
    return f"{100 * np.mean([r[key] == r['truth'] for r in rows]):.1f} % ({sum(r[key] == r['truth'] for r in rows)}/{len(rows)})"


def emps_table(rows: list[dict], rev: str) -> str:
    scored = [r for r in rows if r["instances"] >= MIN_INSTANCES and r["truth"] is not None]
    groups = [
        ("dev (ids 0-7)", [r for r in scored if r["half"] == "dev"]),
        ("held-out (ids 8-f)", [r for r in scored if r["half"] == "held"]),
        ("all", scored),
        (f"dense (area > {DENSE:.0%}), all", [r for r in scored if r["area_fraction"] > DENSE]),
        ("dense, held-out", [r for r in scored if r["area_fraction"] > DENSE and r["half"] == "held"]),
        ("bright particles (SEM-like), all", [r for r in scored if r["truth"] == "bright"]),
        ("dark particles (TEM-like), all", [r for r in scored if r["truth"] == "dark"]),
    ]
    lines = [f"| EMPS, >= {MIN_INSTANCES} instances | images | before ({rev}) | after |", "|---|---|---|---|"]
    lines += [f"| {name} | {len(g)} | {pct(g, 'before')} | {pct(g, 'after')} |" for name, g in groups]
    seconds = [r["before_s"] + r["after_s"] for r in rows]
    lines.append(
        f"\ns / image (all {len(rows)}): before {np.mean([r['before_s'] for r in rows]):.3f}, after "
        f"{np.mean([r['after_s'] for r in rows]):.3f} (max {max(r['after_s'] for r in rows):.3f}); "
        f"{sum(seconds):.0f} s detecting in all"
    )
    return "\n".join(lines)


def bam_table(before) -> str:
    lines = ["| BAM set (32 train ids) | expected | images right before | after | all 32 together before | after |"]
    lines.append("|---|---|---|---|---|---|")
    for name, (expected, root) in BAM.items():
        ids = json.loads((root / "split.json").read_text())["train"]
        paths = [next((root / "images").glob(f"{i}.*")) for i in ids]
        images = [read_grey(p, BAM_CROP) for p in paths]
        cells, seconds = [], 0.0
        for module in (before, after):
            polarity, seconds, estimate = detect(module, images)
            right = sum(v.polarity == expected for v in estimate.votes)
            cells.append((f"{right}/{len(images)}", f"{polarity} ({estimate.confidence:.2f})"))
        convexity = [v.convexity for v in estimate.votes]
        lines.append(
            f"| {name} | {expected} | {cells[0][0]} | {cells[1][0]} | {cells[0][1]} | {cells[1][1]}, convexity "
            f"{min(convexity):+.2f} to {max(convexity):+.2f}, {seconds / len(images):.2f} s / image |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", default="931a875", help="commit whose polarity.py is the 'before'")
    parser.add_argument("--csv", default="experiments/profile/polarity_check.csv")
    parser.add_argument("--no-bam", action="store_true")
    args = parser.parse_args()
    before = module_at(args.before)
    rows = emps_rows(before)
    print(emps_table(rows, args.before))
    if args.csv:
        keys = ["id", "half", "instances", "area_fraction", "truth", "before", "after", "convexity", "mode_vote"]
        keys += ["mode_margin", "after_s"]
        with open(args.csv, "w", newline="") as f:
            writer = csv.DictWriter(f, keys, extrasaction="ignore")
            writer.writeheader()
            for row in rows:
                writer.writerow({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()})
        print(f"\nper image: {args.csv}")
    if not args.no_bam:
        print()
        print(bam_table(before))


if __name__ == "__main__":
    main()
