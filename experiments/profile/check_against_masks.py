"""Profile the 32 train images of tio2_sem and tio2_tsem without masks, then compute the same numbers from the
masks and print a table (the masks serve only this check; test ids are never read).

    python experiments/profile/check_against_masks.py [--out runs/profile/check]

Same definitions on both sides: equivalent diameters 2 sqrt(area / pi) of segments (masks: 4-connected
components) of plausible area (the profiler's min_area..max_area) not touching the image border; particles per
256 px patch: segments of plausible area whose centroid lies inside a window of the same stride-128 grid.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from drgan.data import measurements as est
from drgan.data.images import read_grey
from drgan.profile import ProfileSettings, profile

ROOT = Path("/work/shared/datasets")
SETS = {  # name: (mask file pattern, crop rows of the mask, expected polarity)
    "tio2_sem": ("{}_m.tif", (712, 768), "bright"),
    "tio2_tsem": ("{}.tif", None, "dark"),  # masks already 1024 x 712
}


def mask_values(name: str, ids: list[str], params: dict, patch: int) -> tuple[float, float, float]:
    pattern, crop, _ = SETS[name]
    diameters, counts = [], []
    for image_id in ids:
        mask = read_grey(ROOT / name / "masks" / pattern.format(image_id), crop) > 0.5
        table = est.component_table(mask, params["min_area"], params["max_area"])
        diameters.append(table["diameter_px"][~table["touches_border"]])
        counts.append(est.patch_counts(table["row"], table["col"], mask.shape, patch))
    d, c = np.concatenate(diameters), np.concatenate(counts)
    return float(np.median(d)), float(c.mean()), float(np.median(c))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", default="runs/profile/check")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as conf_dir:  # the check writes no material config into the project
        for name, (_, _, expected) in SETS.items():
            cfg = OmegaConf.create(
                {
                    "name": f"check_{name}",
                    "data": {
                        "dir": str(ROOT / name / "images"),
                        "crop_rows": [712, 768],
                        "split": "auto",
                        "polarity": "auto",
                    },
                    "patch_size": 256,
                    "max_images": None,
                    "overwrite": True,
                    "conf_dir": conf_dir,
                    "out": f"{args.out}/{name}",
                    "seed": 0,
                }
            )
            start = time.perf_counter()
            result = profile(ProfileSettings.from_config(cfg))
            seconds = time.perf_counter() - start
            params, patch = result["segmentation"]["params"], result["particles_per_patch"]["patch_size"]
            m_median, m_mean, m_med_count = mask_values(name, result["data"]["ids"], params, patch)
            rows.append((name, expected, result, m_median, m_mean, m_med_count, seconds))
    print(
        "| set | polarity (expected) | median diameter px: profile / masks (error) | particles per 256 px patch, "
        "mean: profile / masks (error) | median count: profile / masks | chosen fit | profile time |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, expected, r, m_median, m_mean, m_med_count, seconds in rows:
        p_median, c = r["sizes"]["median_diameter_px"], r["particles_per_patch"]
        print(
            f"| {name} | {r['polarity']['value']} ({expected}) | {p_median:.2f} / {m_median:.2f} "
            f"({100 * (p_median / m_median - 1):+.1f} %) | {c['mean']:.2f} / {m_mean:.2f} "
            f"({100 * (c['mean'] / m_mean - 1):+.1f} %) | {c['median']:g} / {m_med_count:g} | {r['sizes']['chosen']} "
            f"| {seconds:.0f} s |"
        )


if __name__ == "__main__":
    main()
