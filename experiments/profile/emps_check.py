"""Profile every EMPS image alone (one image = one user's folder) and compare with its instance map.

    python experiments/profile/emps_check.py [--out runs/profile/emps] [--jobs 2] [--every 1] [--half all|dev|held]

Each image goes through `drgan.profile.profile` (the code path of `python -m drgan.profile`, in-process) in a folder
of its own; the instance maps (`instances/ID.png`) are read only here, after the profile, to check it:

- polarity: particles darker or brighter than the rest (mean grey inside vs outside the instances);
- median equivalent diameter 2 sqrt(area / pi) of the instances that do not touch the image border, against the
  profile's `sizes.median_diameter_px` (segments not touching the border): right within 20 %;
- count: instances against the profile's `segmentation.particles` (segments of plausible area): right within 30 %.

Scored on the images with >= 5 instances; an error counts as a miss on every score (and is listed). Writes
`emps.csv` (one row per image) and `worst.png` (the profile's outlines next to the instance outlines of the worst
cases: real images, keep them out of the repository) in --out, and prints a per-image table and the summary.
--half dev / held: the images whose id starts with 0-7 / 8-f (a development half and a held-out half).
"""

from __future__ import annotations

import argparse
import csv
import logging
import math
import tempfile
import time
import traceback
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf
from PIL import Image

ROOT = Path("/work/shared/datasets/emps_train")
MIN_INSTANCES = 5
DIAMETER_TOL, COUNT_TOL = 0.20, 0.30


def reference(image_id: str, images: Path) -> dict:
    """The numbers the instance map gives (the check's side; nothing in drgan reads these maps)."""
    grey = np.asarray(Image.open(images / "images" / f"{image_id}.png").convert("L"), np.float64)
    inst = np.asarray(Image.open(images / "instances" / f"{image_id}.png")).astype(np.int64)
    areas = np.bincount(inst.ravel())
    present = np.flatnonzero(areas)
    present = present[present > 0]
    border = np.unique(np.concatenate([inst[0], inst[-1], inst[:, 0], inst[:, -1]]))
    inner = [a for i, a in enumerate(areas) if i > 0 and a > 0 and i not in border]
    inside, outside = grey[inst > 0], grey[inst == 0]
    polarity = None
    if inside.size and outside.size:
        polarity = "bright" if inside.mean() > outside.mean() else "dark"
    return {
        "ref_count": int(present.size),
        "ref_median_px": float(np.median(2 * np.sqrt(np.asarray(inner) / np.pi))) if inner else math.nan,
        "ref_polarity": polarity,
    }


def profile_one(args: tuple[str, str, str]) -> dict:
    """Profile one image alone through drgan.profile.profile; the row of the table (errors caught and recorded)."""
    image_id, images, out = args
    logging.disable(logging.WARNING)
    from drgan.profile import ProfileSettings, profile

    row = {"id": image_id, **reference(image_id, Path(images))}
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / image_id
        folder.mkdir()
        (folder / f"{image_id}.png").symlink_to(Path(images) / "images" / f"{image_id}.png")
        cfg = OmegaConf.create({
            "name": f"emps_{image_id}",
            "data": {"dir": str(folder), "crop_rows": "auto", "split": "auto", "polarity": "auto"},
            "patch_size": 256,
            "max_images": None,
            "overwrite": True,
            "conf_dir": str(Path(tmp) / "conf"),
            "out": f"{out}/profiles/{image_id}",
            "seed": 0,
        })  # fmt: skip
        try:
            result = profile(ProfileSettings.from_config(cfg))
            row.update(
                polarity=result["polarity"]["value"],
                median_px=result["sizes"]["median_diameter_px"],
                count=result["segmentation"]["particles"],
                scale_px=result["segmentation"].get("scale_px", math.nan),
                error="",
            )
        except Exception as exc:  # an error is a result here: the table lists it
            message = f"{type(exc).__name__}: {exc}".replace("\n", " ")
            if not isinstance(exc, (ValueError, RuntimeError)) or "drgan" not in type(exc).__module__:
                message += " @ " + traceback.format_exc().strip().splitlines()[-3].strip()
            row.update(polarity="", median_px=math.nan, count=math.nan, scale_px=math.nan, error=message[:400])
    row["seconds"] = round(time.perf_counter() - start, 2)
    return row


def score(row: dict) -> dict:
    ok = not row["error"]
    d_ratio = row["median_px"] / row["ref_median_px"] if ok and row["ref_median_px"] > 0 else math.nan
    c_ratio = row["count"] / row["ref_count"] if ok and row["ref_count"] else math.nan
    return {
        "polarity_ok": ok and row["polarity"] == row["ref_polarity"],
        "median_ratio": d_ratio,
        "median_ok": bool(abs(d_ratio - 1) <= DIAMETER_TOL) if np.isfinite(d_ratio) else False,
        "count_ratio": c_ratio,
        "count_ok": bool(abs(c_ratio - 1) <= COUNT_TOL) if np.isfinite(c_ratio) else False,
    }


def summary(rows: list[dict]) -> dict:
    scored = [r for r in rows if r["ref_count"] >= MIN_INSTANCES]
    with_median = [r for r in scored if np.isfinite(r["ref_median_px"])]
    n = len(scored)
    return {
        "images": len(rows),
        "scored (>= 5 instances)": n,
        "polarity right": f"{sum(r['polarity_ok'] for r in scored)} / {n} "
        f"({100 * np.mean([r['polarity_ok'] for r in scored]):.1f} %)",
        "median diameter within 20 %": f"{sum(r['median_ok'] for r in with_median)} / {len(with_median)} "
        f"({100 * np.mean([r['median_ok'] for r in with_median]):.1f} %)",
        "count within 30 %": f"{sum(r['count_ok'] for r in scored)} / {n} "
        f"({100 * np.mean([r['count_ok'] for r in scored]):.1f} %)",
        "errors (all images)": sum(bool(r["error"]) for r in rows),
        "errors (scored images)": sum(bool(r["error"]) for r in scored),
        "median |log ratio| diameter": round(
            float(
                np.nanmedian(
                    [abs(math.log(r["median_ratio"])) for r in with_median if r["median_ratio"] > 0] or [math.nan]
                )
            ),
            3,
        ),  # fmt: skip
        "seconds per image (median)": float(np.median([r["seconds"] for r in rows])),
    }


def worst_figure(rows: list[dict], images: Path, out: Path, n: int = 12) -> Path | None:
    """The profile's particles.png next to the instance outlines, for the n scored images furthest off in diameter."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from skimage.segmentation import find_boundaries

    scored = [r for r in rows if r["ref_count"] >= MIN_INSTANCES]
    bad = sorted(
        scored,
        key=lambda r: -(abs(math.log(r["median_ratio"])) if r["median_ratio"] > 0 else 10.0),
    )[:n]
    if not bad:
        return None
    fig, axes = plt.subplots(len(bad), 2, figsize=(10, 4.2 * len(bad)), squeeze=False)
    for (left, right), r in zip(axes, bad):
        ours = out / "profiles" / r["id"] / "particles.png"
        if ours.is_file():
            left.imshow(np.asarray(Image.open(ours)))
        left.set_title(f"{r['id']}: profile {r['polarity'] or 'error'} d={r['median_px']:.1f} n={r['count']}")
        grey = np.asarray(Image.open(images / "images" / f"{r['id']}.png").convert("L"), np.float64) / 255
        inst = np.asarray(Image.open(images / "instances" / f"{r['id']}.png")).astype(np.int64)
        rgb = np.repeat(grey[..., None], 3, axis=2)
        rgb[find_boundaries(inst, mode="outer")] = (0.1, 0.9, 0.2)
        right.imshow(rgb)
        right.set_title(f"instances {r['ref_polarity']} d={r['ref_median_px']:.1f} n={r['ref_count']}")
        for ax in (left, right):
            ax.axis("off")
    fig.tight_layout()
    path = out / "worst.png"
    fig.savefig(path, dpi=60)
    plt.close(fig)
    return path


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--images", default=str(ROOT))
    parser.add_argument("--out", default="runs/profile/emps")
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--every", type=int, default=1, help="profile every k-th image (a quicker subset)")
    parser.add_argument("--half", choices=("all", "dev", "held"), default="all")
    parser.add_argument("--ids", nargs="*", help="only these ids")
    parser.add_argument("--csv", default=None, help="also write the CSV here (e.g. into experiments/profile/)")
    args = parser.parse_args()
    images, out = Path(args.images), Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    ids = sorted(p.stem for p in (images / "images").glob("*.png"))
    if args.half != "all":
        ids = [i for i in ids if (int(i[0], 16) < 8) == (args.half == "dev")]
    ids = args.ids or ids[:: args.every]
    start = time.perf_counter()
    tasks = [(i, str(images), str(out)) for i in ids]
    if args.jobs > 1:
        with ProcessPoolExecutor(args.jobs) as pool:
            rows = list(pool.map(profile_one, tasks))
    else:
        rows = [profile_one(t) for t in tasks]
    rows = [{**r, **score(r)} for r in rows]
    columns = list(rows[0])
    for path in [out / "emps.csv"] + ([Path(args.csv)] if args.csv else []):
        with open(path, "w", newline="") as f:
            writer = csv.DictWriter(f, columns)
            writer.writeheader()
            for r in rows:
                writer.writerow({k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()})
    print("| id | polarity (ref) | median px (ref) | count (ref) | ok p/d/n | s | error |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        flags = "".join("x" if r[k] else "." for k in ("polarity_ok", "median_ok", "count_ok"))
        print(
            f"| {r['id']} | {r['polarity'] or '-'} ({r['ref_polarity']}) | {r['median_px']:.1f} "
            f"({r['ref_median_px']:.1f}) | {r['count']} ({r['ref_count']}) | {flags} | {r['seconds']:.1f} | "
            f"{r['error'][:120]} |"
        )
    print()
    for key, value in summary(rows).items():
        print(f"{key}: {value}")
    print(f"wall time: {time.perf_counter() - start:.0f} s ({args.jobs} job(s)); csv: {out / 'emps.csv'}")
    figure = worst_figure(rows, images, out)
    if figure:
        print(f"worst cases: {figure}")


if __name__ == "__main__":
    main()
