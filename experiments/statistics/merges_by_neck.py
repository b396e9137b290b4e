"""Which touching particles does a segmenter merge: those whose contact the image shows, or those it does not?

On a segment run's held-out generated pairs (its closed-loop ids), every contact between two true particles is put in
a bin by its neck grey (the ridge's grey on the particles' own scale, drgan.data.necks: 1 = as
dark/bright as the particles, no cue; 0 = the background, a gap) and counted as merged when one predicted particle
holds more than half of both (drgan.metrics.instance_scores.error_sources' rule, per contact). If merges gather where
the neck grey is ~1, the image shows nothing to cut there: the check measures the scene's ambiguity, and real
images whose contacts show a neck (tio2_tsem annotations: median 0.80) are easier than the check.

    python experiments/statistics/merges_by_neck.py SEGMENT_RUN/checkpoints/last.ckpt GENERATED
    python experiments/statistics/merges_by_neck.py CKPT --real DATASET --ids train   # annotated real images, as
                                                                                       # analyze predicts them
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from drgan.metrics.instance_scores import binarize_and_label
from drgan.segmenters.closed_loop import check_inference, contact_merges
from drgan.segmenters.inference import predict
from drgan.segmenters.pairs import load_generated_pairs
from drgan.segmenters.registry import load_segmenter

BINS = (-np.inf, 0.5, 0.8, 0.9, 0.97, 1.03, 1.1, np.inf)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("ckpt")
    parser.add_argument("generated", nargs="?")
    parser.add_argument("--real", type=Path, help="an annotated dataset instead of the held-out generated pairs")
    parser.add_argument("--ids", default="train", help="--real: the split's subset (train, test or all)")
    args = parser.parse_args()
    rows = []
    if args.real:
        from drgan.segmenters.pairs import load_real_items, real_ids
        from drgan.segmenters.predictors import load_predictor

        predictor = load_predictor(args.ckpt, {})
        items = load_real_items(args.real, real_ids(args.real, None, args.ids, setting="--real"))
        for item, truth in items:
            pred = binarize_and_label(np.asarray(predictor(item)).astype(np.int64))
            rows += contact_merges(pred, truth, np.asarray(item.image, np.float64))
        source = f"{len(items)} {args.ids} images of {args.real}"
    else:
        model = load_segmenter(args.ckpt)
        ids = set((model.closed_loop or {}).get("ids") or [])
        pairs = [p for p in load_generated_pairs(args.generated) if p.id in ids]
        settings = check_inference(model.split_calibration)
        for pair in pairs:
            truth = np.asarray(pair.instances()).astype(np.int64)
            classes = predict(model, pair.image, noise_match=False, annotations=False, **settings)
            pred = binarize_and_label(classes.astype(np.int64))
            rows += contact_merges(pred, truth, np.asarray(pair.image, np.float64))
        source = f"{len(pairs)} held-out pairs of {args.generated}"
    grey = np.array([g for g, _ in rows])
    merged = np.array([m for _, m in rows])
    print(f"{source}, {len(rows)} contacts; segmenter {args.ckpt}")
    print("| neck grey | contacts | share of contacts | merged |")
    print("|---|---|---|---|")
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        inside = (grey >= lo) & (grey < hi)
        if inside.any():
            name = f"< {hi:g}" if lo == -np.inf else (f">= {lo:g}" if hi == np.inf else f"{lo:g}-{hi:g}")
            print(f"| {name} | {inside.sum()} | {inside.mean():.0%} | {merged[inside].mean():.0%} |")
    print(f"| all | {len(rows)} | 100% | {merged.mean():.0%} |")


if __name__ == "__main__":
    main()
