"""The sizes a pipeline's GAN draws its particles from against the annotated sizes of the same images.

The profile measures the particle sizes of the unannotated train images with the classical segmentation
(`profile/labels/ID.tif`) and writes them into the material's size distribution; if that segmentation merged
particles, the rendered scenes would hold oversized single particles and teach the segmenter to keep merged blobs.
This prints the equivalent diameters (px, particles not cut by the border) of both, all particles and isolated
ones (touching no other), on the train ids only, and the profile's at half contrast where it measured there:

    python experiments/statistics/profile_sizes.py PIPELINE_RUN DATASET
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from drgan.data.imagej import read_label_tiff
from drgan.data.necks import contact_pairs
from drgan.metrics.statistics import particles
from drgan.segmenters.pairs import load_real_items

QUANTILES = (10, 25, 50, 75, 90)


def sizes(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(diameters of the particles not cut by the border, the same of those touching no other particle)."""
    found = particles(labels)
    ids = np.unique(labels[labels > 0])
    ridge, low, high = contact_pairs(labels)
    touching = np.union1d(low[ridge], high[ridge])
    isolated = ~np.isin(ids, touching)
    inside = ~found.border
    return found.diameter[inside], found.diameter[inside & isolated]


def row(name: str, labels: list[np.ndarray], shift: float = 0.0, smallest: float = 0.0) -> list[str]:
    """A table row; ``shift`` px moves every outline (diameters + 2 x shift), as the profile's half contrast does;
    particles below ``smallest`` px are left out."""
    pooled = [sizes(label) for label in labels]
    every, alone = (np.concatenate([p[k] for p in pooled]) + 2 * shift for k in (0, 1))
    every, alone = every[every >= smallest], alone[alone >= smallest]
    q = lambda d: " / ".join(f"{v:.1f}" for v in np.percentile(d, QUANTILES))  # noqa: E731
    return [name, f"{every.size}", q(every), f"{alone.size}", q(alone) if alone.size else "n/a"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a drgan.pipeline run (its profile/labels/)")
    parser.add_argument("dataset", type=Path, help="the annotated set (images/, masks/, split.json)")
    parser.add_argument("--smallest", type=float, default=0.0, help="leave out masks' particles below this (px)")
    args = parser.parse_args()
    ids = json.loads((args.dataset / "split.json").read_text())["train"]
    masks = [labels for _, labels in load_real_items(args.dataset, ids)]
    classical = [read_label_tiff(args.run / "profile" / "labels" / f"{i}.tif")[0] for i in ids]
    head = ["outlines", "particles", "diameter p10 / p25 / p50 / p75 / p90 (px)", "isolated", "isolated p10-p90"]
    print("| " + " | ".join(head) + " |\n|" + "---|" * len(head))
    for name, labels in (("annotated masks", masks), ("profile, at the classical outlines", classical)):
        print("| " + " | ".join(row(name, labels, smallest=args.smallest if labels is masks else 0.0)) + " |")
    sized = json.loads((args.run / "profile" / "profile.json").read_text())["sizes"]
    if sized.get("outline_shift_px"):  # profiles that measured at half contrast
        shift = sized["outline_shift_px"]
        print("| " + " | ".join(row(f"profile, at half contrast ({shift:+.2f} px)", classical, shift)) + " |")


if __name__ == "__main__":
    main()
