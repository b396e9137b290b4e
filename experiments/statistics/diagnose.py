"""Where a segmenter loses particles, and what the touching-particle split changes, on real *train* images.

    python experiments/statistics/diagnose.py SEGMENTER.ckpt [SET] [--ids val|all|N] [--variants ...]

SET: tio2_sem (default) or tio2_tsem under $DRGAN_DATA (default ../shared/datasets). --ids: the train ids to use:
``all`` (default: every train id, for a segmenter trained on generated pairs, which saw none of them), ``val``
(the validation ids a real-trained segmenter of seed --seed held out: drgan.segment's split_pairs of the train
ids with val_fraction 0.1) or a
number N (the first N train ids). Test ids are never read.

Predicts each image's class probabilities once, then for every split variant prints one markdown row: DSC, AP50,
median-diameter and count errors against the masks, and the share of true particles matched / merged / split /
missed / badly outlined, false particles and the boundary offset (drgan.metrics.instance_scores.error_sources).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from drgan.metrics.instance_scores import ERROR_SOURCES, binarize_and_label, error_sources, segmentation_scores
from drgan.metrics.statistics import compare_sizes, particles
from drgan.segmenters.inference import predict_probs, split_touching
from drgan.segmenters.pairs import load_real_items, real_ids, split_pairs
from drgan.segmenters.predictors import load_predictor


def parse_variant(text: str) -> dict:
    """'depth=2,smooth=1' -> split_touching keywords (floats); 'none' -> the network's argmax."""
    if text == "none":
        return {}
    return {key: float(value) for key, value in (item.split("=") for item in text.split(","))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("ckpt", type=Path)
    parser.add_argument("set", nargs="?", default="tio2_sem")
    parser.add_argument("--ids", default="all")
    parser.add_argument("--seed", type=int, default=0, help="--ids val: the real-trained segmenter's seed")
    parser.add_argument(
        "--variants",
        nargs="+",
        default=["none", "depth=2,smooth=1", "depth=1,smooth=1", "depth=1,smooth=0.5", "depth=0.5,smooth=1"],
    )
    args = parser.parse_args()
    data = Path(os.environ.get("DRGAN_DATA", "../shared/datasets")) / args.set
    train = real_ids(data, None, "train")
    if args.ids == "all":
        ids = train
    elif args.ids == "val":
        ids = split_pairs(train, 0.1, args.seed)[1]
    else:
        ids = train[: int(args.ids)]
    samples = load_real_items(data, ids, "auto", "auto", "masks")
    predictor = load_predictor(str(args.ckpt), {})
    net = predictor.model
    probs = [predict_probs(net, item.image) for item, _ in samples]
    truth = [particles(labels) for _, labels in samples]
    print(f"{len(ids)} train images of {args.set}, segmenter {args.ckpt}\n")
    heads = ["DSC", "AP50", "median error", "count error", *ERROR_SOURCES, "false", "boundary offset px"]
    print("| split | " + " | ".join(heads) + " |\n|---|" + "---|" * len(heads))
    for text in args.variants:
        keywords = parse_variant(text)
        rows, found, sources = [], [], []
        for p, (_, true_labels) in zip(probs, samples):
            class_map = p.argmax(0) if text == "none" else split_touching(p, **_keywords(keywords))
            labels = binarize_and_label(class_map.astype(np.int64))
            rows.append(segmentation_scores(labels, true_labels))
            found.append(particles(labels))
            sources.append(error_sources(labels, true_labels))
        stats = compare_sizes(found, truth, n_boot=0)
        n_true = sum(s["n_true"] for s in sources)
        n_pred = sum(s["n_pred"] for s in sources)
        share = [f"{100 * sum(s[k] for s in sources) / n_true:.1f} %" for k in ERROR_SOURCES]
        offset = float(np.median(np.concatenate([s["diameter_offset"] for s in sources])))
        cells = [
            f"{np.mean([r['dsc'] for r in rows]):.3f}",
            f"{np.mean([r['ap50'] for r in rows]):.3f}",
            f"{100 * stats['median_error']['value']:+.1f} %",
            f"{100 * stats['count_error']['value']:+.1f} %",
            *share,
            f"{100 * sum(s['false'] for s in sources) / max(n_pred, 1):.1f} %",
            f"{offset:+.2f}",
        ]
        print(f"| {text} | " + " | ".join(cells) + " |", flush=True)


def _keywords(variant: dict) -> dict:
    names = {"depth": "split_depth", "smooth": "split_smooth", "core": "split_core"}
    return {names.get(k, k): v for k, v in variant.items()}


if __name__ == "__main__":
    main()
