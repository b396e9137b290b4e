"""How high does the instance-aware segmenter's centre map rise inside a particle, by the particle's size? Its target
is 1 on every particle's medial core whatever the size (drgan.segmenters.instances); a network whose receptive field
is smaller than the particle cannot tell the core from the rim and leaves a plateau below the seed levels. Prints,
per diameter bin (px of the generated pairs) of the exact instances of N generated pairs (not cut by the border), the
median, 10th and 90th percentile of the predicted centre map's maximum inside each particle (the target's is 1 by
construction); a model that learnt at a working scale (loader.working_px) sees each pair shrunk as inference would.

    python experiments/statistics/centre_peaks.py runs/pipeline/saa890/extra/centres_0/checkpoints/last.ckpt \
        runs/pipeline/saa890/generate --n 30
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

from drgan.data.images import read_grey, resample
from drgan.metrics.statistics import particles
from drgan.segmenters.inference import predict_probs, resample_probs
from drgan.segmenters.noise_match import match_noise
from drgan.segmenters.pairs import read_raw_mask
from drgan.segmenters.registry import load_segmenter

BINS = (0, 16, 32, 64, 128, 256, 1024)  # equivalent diameter, px


def peaks(model, image: np.ndarray, labels: np.ndarray, level: float) -> tuple[np.ndarray, np.ndarray]:
    """(diameter, centre-map maximum) per particle of ``labels`` not touching the image border."""
    scale = float(getattr(model, "pixel_scale", 1.0))  # the working scale it learnt at (loader.working_px)
    small = resample(image, scale)
    probs = predict_probs(model, match_noise(small, level) if level else small)
    centre = (resample_probs(probs, image.shape) if scale != 1.0 else probs)[3]
    sized = particles(labels)  # in label order, as the ids below
    top = np.asarray(ndi.maximum(centre, labels, np.unique(labels[labels > 0])))
    return sized.diameter[~sized.border], top[~sized.border]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("ckpt")
    parser.add_argument("generated", help="a generated set (images/, labels/)")
    parser.add_argument("--n", type=int, default=30)
    args = parser.parse_args()
    model = load_segmenter(args.ckpt, "model").eval()
    level = getattr(model, "train_noise", None) or 0.0
    folder = Path(args.generated)
    names = sorted(p.name for p in (folder / "labels").glob("*.png"))[-args.n :]
    diameters, tops = [], []
    for name in names:
        d, t = peaks(model, read_grey(folder / "images" / name), read_raw_mask(folder / "labels" / name), level)
        diameters.append(d)
        tops.append(t)
    diameter, top = np.concatenate(diameters), np.concatenate(tops)
    print(f"{args.ckpt}: {len(names)} generated pairs, {diameter.size} particles not cut by the border")
    print("| diameter (px) | particles | centre-map maximum: median | 10th / 90th percentile |")
    print("|---|---|---|---|")
    for low, high in zip(BINS[:-1], BINS[1:]):
        sel = (diameter >= low) & (diameter < high)
        if sel.any():
            q10, q50, q90 = np.percentile(top[sel], [10, 50, 90])
            print(f"| {low}-{high} | {int(sel.sum())} | {q50:.2f} | {q10:.2f} / {q90:.2f} |")


if __name__ == "__main__":
    main()
