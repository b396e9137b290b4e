"""Where do outlines sit on the edge? Issue 51's "outlines where a microscopist draws them".

For each particle: its equivalent diameter in the mask (generated: the exact label; real: the annotation), and the
equivalent diameter of the part of it that stands out by at least half of the particle's own contrast (the
half-contrast outline, where a microscopist's eye puts an edge): contrast = how far a pixel is from the local
background grey towards the particle's core grey (the median of its pixels 2 px or more inside the mask); the
background grey is the median of the ring 3-6 px outside the mask (other particles left out). Prints, per set, the
median of (mask diameter - half-contrast diameter) in px: > 0 when masks are drawn wider than the visible edge.

    python experiments/pipeline/edge_offset.py --generated runs/pipeline/bam_tio2_tsem/generate \
        --real ../shared/datasets/tio2_tsem --ids train
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

from drgan.data.images import read_grey


def offsets(image: np.ndarray, labels: np.ndarray, polarity: str) -> list[float]:
    out = []
    sign = -1.0 if polarity == "dark" else 1.0
    other = labels > 0
    for index, box in enumerate(ndi.find_objects(labels), start=1):
        if box is None:
            continue
        y0, y1 = max(box[0].start - 8, 0), min(box[0].stop + 8, labels.shape[0])
        x0, x1 = max(box[1].start - 8, 0), min(box[1].stop + 8, labels.shape[1])
        lab, img = labels[y0:y1, x0:x1], image[y0:y1, x0:x1]
        mask = lab == index
        if (
            mask.sum() < 30
            or box[0].start == 0
            or box[1].start == 0
            or box[0].stop == labels.shape[0]
            or (box[1].stop == labels.shape[1])
        ):
            continue  # small or cut by the border
        inside = ndi.distance_transform_edt(mask)
        outside = ndi.distance_transform_edt(~mask)
        core = img[inside >= 3]
        ring = img[(outside >= 3) & (outside <= 6) & ~other[y0:y1, x0:x1]]
        if core.size < 5 or ring.size < 10:
            continue
        c, b = np.median(core), np.median(ring)
        if sign * (c - b) <= 0.05:
            continue  # no contrast to speak of
        half = sign * (img - b) >= 0.5 * sign * (c - b)
        visible = ndi.binary_fill_holes(half & ndi.binary_dilation(mask, iterations=3))
        labelled, _ = ndi.label(visible)
        centre = labelled[tuple(np.argwhere(inside == inside.max())[0])]
        if centre == 0:
            continue
        area_mask, area_half = mask.sum(), (labelled == centre).sum()
        out.append(2 * np.sqrt(area_mask / np.pi) - 2 * np.sqrt(area_half / np.pi))
    return out


def generated_images(folder: Path, n: int):
    """(image, exact instance labels) of the first ``n`` synthetic pairs of a generated set."""
    from PIL import Image

    for path in sorted((folder / "labels").glob("syn_*.png"))[:n]:
        yield read_grey(folder / "images" / path.name), np.asarray(Image.open(path)).astype(np.int32)


def real_images(folder: Path, ids: str):
    """(image, annotated instance labels) of a real dataset's ``ids`` subset (train / test / all)."""
    from drgan.segmenters.pairs import load_real_items, real_ids

    for item, labels in load_real_items(folder, real_ids(folder, None, ids, "real")):
        yield item.image, labels


def generated(folder: Path, polarity: str, n: int) -> list[float]:
    return [v for image, labels in generated_images(folder, n) for v in offsets(image, labels, polarity)]


def real(folder: Path, ids: str, polarity: str) -> list[float]:
    return [v for image, labels in real_images(folder, ids) for v in offsets(image, labels, polarity)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--generated", type=Path)
    parser.add_argument("--real", type=Path)
    parser.add_argument("--ids", default="train")
    parser.add_argument("--polarity", default="dark")
    parser.add_argument("--n", type=int, default=200)
    args = parser.parse_args()
    for name, values in (
        ("generated labels", generated(args.generated, args.polarity, args.n) if args.generated else None),
        (f"real masks ({args.ids})", real(args.real, args.ids, args.polarity) if args.real else None),
    ):
        if values is not None:
            v = np.asarray(values)
            print(f"{name}: {len(v)} particles, mask - half-contrast diameter median {np.median(v):+.2f} px "
                  f"(quartiles {np.percentile(v, 25):+.2f} / {np.percentile(v, 75):+.2f})")  # fmt: skip


if __name__ == "__main__":
    main()
