"""Why the classical baseline, good on real images, fails on drgan's generated pairs: the patch size or the texture?

    python experiments/statistics/classical_on_pairs.py GENERATED [--n 48] [--polarity bright|dark] [--real DATASET]

drgan.evaluate model=classical counts hundreds of false specks on generated 256-px pairs (issue 67) while it does well
on real images of the same material. Each variant below changes one thing and runs the same classical segmentation
(drgan.data.classical.segment_particles) on the last N rendered pairs (exact instance labels):

- ``own``: as evaluate runs it (the scale searched per image);
- ``true scale``: the particle diameter fixed to the pair's true median (isolates the scale search);
- ``mosaic 2x2``: four pairs side by side, one 512-px image (the patch size, with the scale searched);
- ``smoothed s=1 / s=2``: the image Gaussian-smoothed first (the fine texture: noise, Monte Carlo grain);
- ``real``: with --real, the same segmentation of the data set's annotated train ids against their masks.

Printed: per variant the true and found particles (not cut by the border, specks under the 5th percentile of the
pairs' particle areas left out on both sides), count and median-diameter error, false particles per image, merged and
missed shares, AP50; and the fine-scale texture of each source (the standard deviation of the image minus its 2-px
Gaussian, in the background and in particles), the quantity the smoothing removes.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

from drgan.data.classical import SegmentParams, segment_particles
from drgan.metrics.instance_scores import ap50, error_sources
from drgan.metrics.statistics import particles
from drgan.segmenters.closed_loop import checkable
from drgan.segmenters.pairs import load_generated_pairs, load_real_items, real_ids


def rendered_pairs(folder: Path, n: int) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """The last ``n`` pairs whose truth is exact (the closed loop's `checkable`: rendered, not on a real background)."""
    pairs = [p for p in load_generated_pairs(folder, setting="GENERATED") if checkable(p)][-n:]
    if not pairs:
        raise SystemExit(f"{folder}: no rendered pair (images/, masks/ and labels/ PNGs without IGNORE pixels)")
    return [(p.id, p.image, p.labels) for p in pairs]


def real_pairs(dataset: Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """The annotated train ids as drgan.evaluate reads them (info bar dropped, masks as instance labels)."""
    items = load_real_items(dataset, real_ids(dataset, None, "train", setting="--real"))
    return [(item.id, item.image, labels.astype(np.int32)) for item, labels in items]


def mosaics(pairs):
    """Pairs four at a time side by side (2 x 2), labels offset so that ids stay distinct."""
    out = []
    for k in range(0, len(pairs) - 3, 4):
        group = pairs[k : k + 4]
        images = [g[1] for g in group]
        labels, offset = [], 0
        for g in group:
            lab = g[2].copy()
            lab[lab > 0] += offset
            offset = int(lab.max())
            labels.append(lab)
        image = np.block([[images[0], images[1]], [images[2], images[3]]])
        label = np.block([[labels[0], labels[1]], [labels[2], labels[3]]])
        out.append((f"mosaic{k // 4}", image, label))
    return out


def texture(pairs) -> tuple[float, float]:
    """Median over images of the fine texture's std (image minus its 2-px Gaussian) on background and on particles,
    each in units of the image's contrast (particles' median grey minus the background's): comparable across grey
    scales."""
    back, part = [], []
    for _, image, labels in pairs:
        fine = image - ndimage.gaussian_filter(image, 2.0)
        inside = ndimage.binary_erosion(labels > 0, iterations=2)
        outside = ndimage.binary_erosion(labels == 0, iterations=2)
        if outside.sum() < 50 or inside.sum() < 50:
            continue
        contrast = abs(float(np.median(image[inside]) - np.median(image[outside]))) or float("nan")
        back.append(float(fine[outside].std()) / contrast)
        part.append(float(fine[inside].std()) / contrast)
    return float(np.median(back)) if back else float("nan"), float(np.median(part)) if part else float("nan")


def score(pairs, polarity: str, min_area: float, params=lambda labels: None, smooth: float = 0.0) -> dict:
    true_d, pred_d, n_true, n_pred, false, merged, missed, aps = [], [], 0, 0, 0, 0, 0, []
    for _, image, truth in pairs:
        if smooth:
            image = ndimage.gaussian_filter(image, smooth)
        found, _ = segment_particles(image, params=params(truth), polarity=polarity)
        t, p = particles(truth).whole().at_least(min_area), particles(found).whole().at_least(min_area)
        true_d.append(t.diameter)
        pred_d.append(p.diameter)
        n_true, n_pred = n_true + t.count, n_pred + p.count
        s = error_sources(found, truth)
        false, merged, missed = false + s["false"], merged + s["merged"], missed + s["missed"]
        aps.append(ap50(found, truth))
    med_t, med_p = (np.median(np.concatenate(d)) if sum(map(len, d)) else np.nan for d in (true_d, pred_d))
    total = sum(len(np.unique(t)) - 1 for _, _, t in pairs)
    return {
        "true": n_true,
        "found": n_pred,
        "count": n_pred / n_true - 1,
        "median": med_p / med_t - 1,
        "false_per_image": false / len(pairs),
        "merged": merged / total,
        "missed": missed / total,
        "ap50": float(np.mean(aps)),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("generated", type=Path)
    ap.add_argument("--n", type=int, default=48)
    ap.add_argument("--polarity", default=None, help="bright or dark (default: detected on the generated images)")
    ap.add_argument("--real", type=Path, default=None, help="a data set (images/, masks/, split.json)")
    args = ap.parse_args()
    pairs = rendered_pairs(args.generated, args.n)
    polarity = args.polarity
    if polarity is None:
        from drgan.data.polarity import detect_polarity

        polarity = detect_polarity([p[1] for p in pairs]).polarity
    true_areas = np.concatenate([particles(t).whole().area for _, _, t in pairs])
    min_area = float(np.percentile(true_areas, 5)) if true_areas.size else 0.0
    true_scale = lambda labels: SegmentParams(scale=float(np.median(particles(labels).diameter)))  # noqa: E731
    variants = {
        "own (as evaluate runs it)": dict(pairs=pairs),
        "true scale": dict(pairs=pairs, params=true_scale),
        "mosaic 2x2 (512 px)": dict(pairs=mosaics(pairs)),
        "smoothed s=1": dict(pairs=pairs, smooth=1.0),
        "smoothed s=2": dict(pairs=pairs, smooth=2.0),
        "true scale, smoothed s=1": dict(pairs=pairs, params=true_scale, smooth=1.0),
    }
    real = real_pairs(args.real) if args.real else None  # read once: the segmentation and the texture
    if real:
        variants["real train ids (own)"] = dict(pairs=real)
    print(f"{len(pairs)} rendered pairs of {args.generated}, polarity {polarity}, specks under {min_area:.0f} px^2 out")
    print("| variant | true / found | count error | median error | false per image | merged | missed | AP50 |")
    print("|---|---|---|---|---|---|---|---|")
    for name, kw in variants.items():
        r = score(kw.pop("pairs"), polarity, min_area, **kw)
        print(f"| {name} | {r['true']} / {r['found']} | {100 * r['count']:+.1f} % | {100 * r['median']:+.1f} % | "
              f"{r['false_per_image']:.1f} | {100 * r['merged']:.1f} % | {100 * r['missed']:.1f} % | "
              f"{r['ap50']:.3f} |")  # fmt: skip
        sys.stdout.flush()
    print("\n| source | fine texture std / contrast, background | in particles |")
    print("|---|---|---|")
    sources = {"generated": pairs, **({"real train ids": real} if real else {})}
    for name, group in sources.items():
        b, p = texture(group)
        print(f"| {name} | {b:.2f} | {p:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
