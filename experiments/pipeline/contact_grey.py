"""What does a contact between two touching particles look like, in generated pairs and in real annotated images?

Issue 51: touching tio2_sem particles stay merged after the split, in generated-trained segmenters more than in the
real-trained one. A segmenter can only learn to cut where the training images show a cue. For every pair of touching
instances (generated: the exact labels; real: the annotation's instances, which a 1 px line separates), the ridge
is the pixels with both particles within 1 px (3 x 3 window); its grey is put on the particles' own scale:

    neck = (median ridge grey - background grey) / (median core grey of the two - background grey)

1: the contact is as bright (dark) as the particles, no cue; 0: it falls to the background, a gap anyone can cut;
> 1: a line brighter than the particles (an SEM edge). Core: instance pixels with no other label within 2 px;
background: pixels with no particle within 3 px (the image's median). Prints the quartiles of ``neck`` and the
share of contacts below 0.5 (a visible gap) and above 1.1 (a bright line), per set. Also each contact's width
relative to the smaller particle of the two (the ridge's extent along its principal axis, sqrt(12 var), over the
smaller equivalent diameter): near 0 a point contact, near 1 a neck as wide as the particle (two particles that
look like one).

    python experiments/pipeline/contact_grey.py --generated runs/pipeline/bam_tio2_sem/generate \
        --real ../shared/datasets/tio2_sem --ids train
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from edge_offset import generated_images, real_images  # beside this script
from scipy import ndimage as ndi

from drgan.segmenters.pairs import contact_pairs


def contact_counts(labels: np.ndarray) -> tuple[int, int, int]:
    """(particles, their contacts, those touching another) over the particles of one label image that do not touch
    its border (a particle cut by the border may have lost its neighbours with it)."""
    labels = labels.astype(np.int64)
    big = labels.max() + 1
    ridge, low, high = contact_pairs(labels)
    pairs = np.unique(low[ridge] * big + high[ridge])
    degree = np.bincount(np.concatenate([pairs // big, pairs % big]), minlength=big)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    inner = np.setdiff1d(np.unique(labels[labels > 0]), border)
    return int(inner.size), int(degree[inner].sum()), int((degree[inner] > 0).sum())


def necks(image: np.ndarray, labels: np.ndarray, min_ridge: int = 3) -> list[tuple[float, float]]:
    """(normalised ridge grey, relative neck width) of every touching pair of instances in one image (pairs with
    >= ``min_ridge`` ridge pixels and a particle contrast of at least 0.05)."""
    labels = labels.astype(np.int64)
    big = labels.max() + 1
    ridge, low, high = contact_pairs(labels)
    core = (labels > 0) & (ndi.maximum_filter(labels, size=5) == labels)
    core &= ndi.minimum_filter(np.where(labels > 0, labels, big), size=5) == labels
    background = ndi.maximum_filter(labels, size=7) == 0
    if background.sum() < 100 or not ridge.any():
        return []
    bg = float(np.median(image[background]))
    ids = np.arange(1, big)
    core_grey = dict(zip(ids.tolist(), ndi.median(image, np.where(core, labels, 0), ids)))
    pair = low[ridge] * big + high[ridge]
    diameter = 2.0 * np.sqrt(np.bincount(labels.ravel(), minlength=big) / np.pi)
    coords = np.argwhere(ridge)
    out = []
    for key in np.unique(pair):
        grey = image[ridge][pair == key]
        a, b = int(key // big), int(key % big)
        cores = [core_grey.get(a), core_grey.get(b)]
        if grey.size < min_ridge or any(c is None or not np.isfinite(c) for c in cores):
            continue
        contrast = float(np.mean(cores)) - bg
        if abs(contrast) < 0.05:
            continue
        xy = coords[pair == key].astype(float)
        width = float(np.sqrt(12.0 * np.linalg.eigvalsh(np.cov(xy.T))[-1]))
        out.append(((float(np.median(grey)) - bg) / contrast, width / min(diameter[a], diameter[b])))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--generated", type=Path)
    parser.add_argument("--real", type=Path)
    parser.add_argument("--ids", default="train")
    parser.add_argument("--n", type=int, default=200)
    args = parser.parse_args()
    print(
        "| pairs | contacts | neck grey: quartiles (1 = as the particles, 0 = background) | gap (< 0.5) | line (> 1.1) "
        "| neck width / smaller diameter: quartiles | wide (> 0.7) | contacts per particle (not cut by the border) "
        "| particles touching |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for name, values in (
        (f"generated ({args.generated})", generated_images(args.generated, args.n) if args.generated else None),
        (f"real masks, {args.ids} ids ({args.real})", real_images(args.real, args.ids) if args.real else None),
    ):
        if values is not None:
            values = list(values)
            v, w = np.asarray([x for image, labels in values for x in necks(image, labels)]).T
            n, contacts, touching = np.sum([contact_counts(labels) for _, labels in values], axis=0)
            q, r = np.percentile(v, [25, 50, 75]), np.percentile(w, [25, 50, 75])
            print(f"| {name} | {len(v)} | {q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f} | {np.mean(v < 0.5):.0%} | "
                  f"{np.mean(v > 1.1):.0%} | {r[0]:.2f} / {r[1]:.2f} / {r[2]:.2f} | {np.mean(w > 0.7):.0%} | "
                  f"{contacts / n:.2f} | {touching / n:.0%} |")  # fmt: skip


if __name__ == "__main__":
    main()
