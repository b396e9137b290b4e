"""How blurred are particle outlines, in real images and in renders? (the profile's `edge_blur`, third session)

The profile measures the outlines' blur of a user's images (drgan.data.measurements.edge_blur: the Gaussian whose
slope at a step matches the steepest slope against the local grey range) and gives SEM materials the renderer filter
whose renders show the same blur (drgan.profiling.proposal.FILTER_FOR_BLUR). This script prints the three numbers
that table rests on:

    # real: a pipeline run's profiled images, outlines from the profile's own segmentation
    python experiments/pipeline/outline_blur.py real runs/pipeline/cej_v2 runs/pipeline/bam_tio2_sem ...
    # generated: a run's generated pairs (their exact masks), the first 40
    python experiments/pipeline/outline_blur.py generated runs/pipeline/cej runs/pipeline/bam_tio2_sem ...
    # renders of one material per reconstruction filter (6 layouts each, the FCN at its initial values)
    python experiments/pipeline/outline_blur.py filters runs/pipeline/cej_v2 --filters 0.5 1.0 1.5 2.0 3.0
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

from drgan.data import measurements as est
from drgan.data.classical import SegmentParams
from drgan.data.images import list_images, read_grey


def real(run: Path) -> tuple[float, int]:
    profile = json.loads((run / "profile" / "profile.json").read_text())
    params = SegmentParams(**profile["segmentation"]["params"])
    polarity, crop = profile["polarity"]["value"], profile["data"]["crop_rows"]
    paths = list_images(Path(profile["data"]["dir"]), profile["data"]["ids"])
    blurs = []
    for path in paths:
        image = read_grey(path, crop)
        blurs.append(est.edge_blur(image, est.segment_image(image, params, polarity)[1]))
    found = [b for b in blurs if b is not None]
    return float(np.median(found)), len(found)


def _read(path: Path) -> np.ndarray:
    image = np.asarray(Image.open(path), np.float64)
    image = image[..., 0] if image.ndim == 3 else image
    return image / (65535.0 if image.max() > 255 else 255.0)


def masked_blur(images: list[Path], masks: list[Path]) -> tuple[float, int]:
    found = []
    for image, mask in zip(images, masks):
        classes = np.asarray(Image.open(mask))
        blur = est.edge_blur(_read(image), (classes == 1) | (classes == 2))
        if blur is not None:
            found.append(blur)
    return float(np.median(found)), len(found)


def generated(run: Path, n: int = 40) -> tuple[float, int]:
    folder = run / "generate"
    images = sorted((folder / "images").glob("syn_*.png"))[:n]
    return masked_blur(images, [folder / "masks" / p.name for p in images])


def filters(run: Path, values: list[float], layouts: int = 6) -> dict[float, tuple[float, int]]:
    conf = run / "drgan_conf"
    material = next((conf / "material").glob("*.yaml")).stem
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for value in values:
            folders = []
            for seed in range(layouts):
                folder = Path(tmp) / f"{value}_{seed}"
                subprocess.run(
                    [sys.executable, "-m", "drgan.render", f"hydra.searchpath=[file://{conf.resolve()}]",
                     f"material={material}", f"material.filter_stddev={value}", f"seed={seed}", f"out={folder}"],
                    check=True, capture_output=True,
                )  # fmt: skip
                folders.append(folder)
            out[value] = masked_blur([f / "image.png" for f in folders], [f / "mask.png" for f in folders])
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("what", choices=["real", "generated", "filters"])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--filters", nargs="+", type=float, default=[0.5, 1.0, 1.5, 2.0, 3.0])
    args = parser.parse_args()
    print("| run | what | outline blur (px, median) | images |\n|---|---|---|---|")
    for run in args.runs:
        if args.what == "filters":
            for value, (blur, n) in filters(run, args.filters).items():
                print(f"| {run.name} | renders, filter_stddev {value:g} | {blur:.2f} | {n} |")
        else:
            blur, n = real(run) if args.what == "real" else generated(run)
            print(f"| {run.name} | {args.what} | {blur:.2f} | {n} |")


if __name__ == "__main__":
    main()
