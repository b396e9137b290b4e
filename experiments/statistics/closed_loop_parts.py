"""Where a segmenter's size error on exact truth comes from: the closed-loop check taken apart.

On the held-out generated pairs a segment run scored itself on (its checkpoint's closed-loop ids), the network's
probabilities are computed once, then turned into instances several ways, each measured against the exact labels as
drgan.segmenters.closed_loop measures:
- ``default``: the segmenter's prediction as the check makes it (`drgan.segmenters.inference.predict` with the
  calibrated split): what the check reports;
- ``oracle split``: the network's foreground (particle + contour > 0.5) cut by a watershed seeded at the true
  particles' cores: what is left is the foreground's outline alone;
- ``fg > t``: the oracle split of the foreground at other thresholds t of 1 - p(background);
and, per pair, the foreground's outward offset in px: (predicted - true foreground area) / true perimeter.

    python experiments/statistics/closed_loop_parts.py runs/pipeline/cej/segment/checkpoints/last.ckpt \
        runs/pipeline/cej/generate [--thresholds 0.3 0.5 0.7]
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import ndimage as ndi
from skimage.measure import perimeter
from skimage.segmentation import watershed

from drgan.metrics.instance_scores import binarize_and_label, error_sources, segmentation_scores
from drgan.metrics.statistics import particles
from drgan.scene.labels import centre_distance
from drgan.segmenters.closed_loop import check_inference, summarise
from drgan.segmenters.inference import predict, predict_probs
from drgan.segmenters.pairs import load_generated_pairs
from drgan.segmenters.registry import load_segmenter


def oracle_split(foreground: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """The foreground cut into the true particles' regions: seeds are the true cores (centre distance > 0.5)."""
    seeds = np.where((centre_distance(truth) > 0.5) & foreground, truth, 0)
    labels = watershed(-ndi.distance_transform_edt(foreground), seeds, mask=foreground)
    # regions without a seed stay 0; one 4-connected region per seed as the class map would give it
    return labels.astype(np.int64)


def measure(rows) -> dict:
    found, truth, sources, scores = zip(*rows)
    return summarise(list(found), list(truth), list(sources), list(scores), n_boot=200)


def row(pred_labels, true_labels):
    return (
        particles(pred_labels).at_least(8),
        particles(true_labels).at_least(8),
        error_sources(pred_labels, true_labels),
        segmentation_scores(pred_labels, true_labels),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("ckpt")
    parser.add_argument("generated")
    parser.add_argument("--thresholds", type=float, nargs="*", default=[0.3, 0.5, 0.7])
    parser.add_argument("--tile", type=int, default=384, help="sliding-window tile (px); 128 cuts a pair into tiles")
    parser.add_argument(
        "--through-scale", type=float, default=None,
        help="also predict each pair enlarged by 1 / S (bilinear) at pixel_scale S, as a real image of S x finer "
        "pixels would be, scored against its labels enlarged alike",
    )  # fmt: skip
    args = parser.parse_args()
    model = load_segmenter(args.ckpt)
    ids = set((model.closed_loop or {}).get("ids") or [])
    if not ids:
        raise SystemExit(f"{args.ckpt}: no closed-loop ids (trained before the check, or with check_fraction=0)")
    pairs = [p for p in load_generated_pairs(args.generated) if p.id in ids]
    settings = check_inference(model.split_calibration)
    ways = {"default": [], **{f"oracle split, fg > {t:g}": [] for t in args.thresholds}}
    if args.through_scale:
        ways[f"through pixel scale {args.through_scale:g}"] = []
    offsets = []
    for pair in pairs:
        truth = np.asarray(pair.instances()).astype(np.int64)
        probs = predict_probs(model, pair.image, tile=args.tile)
        if args.through_scale:
            from drgan.data.images import resample
            from drgan.segmenters.pairs import _nearest

            big = resample(pair.image, 1.0 / args.through_scale)
            big_truth = _nearest(truth, big.shape).astype(np.int64)
            classes = predict(
                model, big, pixel_scale=args.through_scale, noise_match=False, annotations=False, tile=args.tile,
                **settings,
            )  # fmt: skip
            ways[f"through pixel scale {args.through_scale:g}"].append(
                row(binarize_and_label(classes.astype(np.int64)), big_truth)
            )
        # as drgan.segmenters.closed_loop predicts: the calibrated split (seed rule and hole filling included)
        classes = predict(model, pair.image, noise_match=False, annotations=False, tile=args.tile, **settings)
        ways["default"].append(row(binarize_and_label(np.asarray(classes).astype(np.int64)), truth))
        for t in args.thresholds:
            fg = 1.0 - probs[0] > t
            ways[f"oracle split, fg > {t:g}"].append(row(oracle_split(fg, truth), truth))
        fg, true_fg = 1.0 - probs[0] > 0.5, truth > 0
        offsets.append(((fg.sum() - true_fg.sum()), perimeter(true_fg)))
    print(f"{len(pairs)} held-out pairs of {args.generated}; segmenter {args.ckpt}")
    area, length = np.sum(offsets, axis=0)
    print(f"foreground (1 - p_bg > 0.5) outward offset: {area / length:+.3f} px (area gap / true perimeter)")
    print("| instances | median error | mean error | count error | edge offset px | merged | split | missed | AP50 |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, rows in ways.items():
        c = measure(rows)
        print(
            f"| {name} | {100 * c['median_error']['value']:+.1f} % | {100 * c['mean_error']['value']:+.1f} % | "
            f"{100 * c['count_error']['value']:+.1f} % | {c['edge_offset_px']:+.2f} | {100 * c['merged']:.1f} % | "
            f"{100 * c['split']:.1f} % | {100 * c['missed']:.1f} % | {c['ap50']:.3f} |"
        )


if __name__ == "__main__":
    main()
