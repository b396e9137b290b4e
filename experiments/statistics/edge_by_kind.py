"""Where a segmenter's outline offset on exact truth sits: the closed loop's matched particles by kind.

On a segment run's held-out generated pairs (its closed-loop ids), predicted as the check predicts them, every predicted
particle matched to a true one (IoU > 0.5) gives its diameter offset (predicted minus true equivalent diameter); the
medians are printed by what the true particle is: cut by the border, inner and alone, inner and touching another,
inner and whole (solidity >= 0.95). An offset that every kind shares is the outline's; one only touching or cut
particles carry is the split's or the border's.

    python experiments/statistics/edge_by_kind.py RUN/segment/checkpoints/last.ckpt RUN/generate
"""

from __future__ import annotations

import argparse

import numpy as np
from skimage.measure import regionprops

from drgan.data.necks import contact_pairs
from drgan.metrics.instance_scores import binarize_and_label, match_instances
from drgan.segmenters.closed_loop import check_inference
from drgan.segmenters.inference import predict
from drgan.segmenters.pairs import load_generated_pairs
from drgan.segmenters.registry import load_segmenter


def matched_rows(model, pairs) -> np.ndarray:
    """Per matched particle: (diameter offset px, cut by the border, touching another, solidity, true diameter px)."""
    settings = check_inference(model.split_calibration)
    rows = []
    for pair in pairs:
        truth = np.asarray(pair.instances()).astype(np.int64)
        # as drgan.segmenters.closed_loop predicts: the calibrated split at the segmenter's own working scale
        classes = predict(model, pair.image, noise_match=False, annotations=False, **settings)
        pred = binarize_and_label(np.asarray(classes).astype(np.int64))
        ridge, low, high = contact_pairs(truth)
        touching = set(np.unique(low[ridge]).tolist()) | set(np.unique(high[ridge]).tolist())
        border = set(np.unique(np.concatenate([truth[0], truth[-1], truth[:, 0], truth[:, -1]])).tolist())
        true_props = {r.label: r for r in regionprops(truth)}
        pred_props = {r.label: r for r in regionprops(pred)}
        for p, t in match_instances(pred, truth, 0.5).pairs:
            true_d = 2 * np.sqrt(true_props[t].area / np.pi)
            offset = 2 * np.sqrt(pred_props[p].area / np.pi) - true_d
            rows.append((offset, t in border, t in touching, true_props[t].solidity, true_d))
    return np.array(rows, dtype=float).reshape(-1, 5)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("ckpt")
    parser.add_argument("generated")
    args = parser.parse_args()
    model = load_segmenter(args.ckpt)
    ids = set((model.closed_loop or {}).get("ids") or [])
    if not ids:
        raise SystemExit(f"{args.ckpt}: no closed-loop ids (trained before the check, or with check_fraction=0)")
    rows = matched_rows(model, [p for p in load_generated_pairs(args.generated) if p.id in ids])
    border, touching, solidity = rows[:, 1] > 0, rows[:, 2] > 0, rows[:, 3]
    print("| matched particles | n | median diameter offset px | edge offset px | true diameter median px |")
    print("|---|---|---|---|---|")
    kinds = {
        "all": np.ones(len(rows), bool), "cut by the border": border, "inner, alone": ~border & ~touching,
        "inner, touching": ~border & touching, "inner, whole (solidity >= 0.95)": ~border & (solidity >= 0.95),
    }  # fmt: skip
    for name, keep in kinds.items():
        if keep.any():
            offset = float(np.median(rows[keep, 0]))
            print(
                f"| {name} | {int(keep.sum())} | {offset:+.2f} | {offset / 2:+.2f} | {np.median(rows[keep, 4]):.1f} |"
            )


if __name__ == "__main__":
    main()
