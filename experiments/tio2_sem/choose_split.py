"""Choose the touching-particle split settings (inference.split_depth, split_smooth) on real *train* images.

    python experiments/tio2_sem/choose_split.py SEGMENTER.ckpt [N_IMAGES]

Predicts the first N (default 10) train ids of the shared TiO2 SEM split with one segmenter, then scores
(DSC, AP50, PQ; drgan.metrics.instance_scores) the network's plain argmax and every depth x smoothing pair.
Test ids are never read. Prints a markdown table.
"""

from __future__ import annotations

import itertools
import os
import sys
from pathlib import Path

import numpy as np

from drgan.metrics.instance_scores import binarize_and_label, segmentation_scores
from drgan.segmenters.inference import predict_probs, split_touching
from drgan.segmenters.module import load_segmenter
from drgan.segmenters.pairs import load_real, real_ids


def main() -> None:
    ckpt, n = sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 10
    data = Path(os.environ.get("DRGAN_DATA", "../shared/datasets")) / "tio2_sem"
    samples = load_real(data, real_ids(data, None, "train")[:n], (712, 768))
    net = load_segmenter(ckpt)
    probs = [(predict_probs(net, image), labels) for _, image, labels in samples]

    def score(make_map) -> dict:
        rows = [segmentation_scores(binarize_and_label(make_map(p).astype(np.int64)), t) for p, t in probs]
        return {k: float(np.mean([r[k] for r in rows])) for k in ("dsc", "ap50", "pq")}

    print(f"{len(samples)} train images, segmenter {ckpt}\n")
    print("| split | depth px | smoothing px | DSC | AP50 | PQ |\n|---|---|---|---|---|---|")
    s = score(lambda p: p.argmax(0))
    print(f"| none (argmax) | | | {s['dsc']:.3f} | {s['ap50']:.3f} | {s['pq']:.3f} |")
    for depth, smooth in itertools.product((1.0, 2.0, 3.0, 5.0), (0.0, 1.0, 2.0)):
        s = score(lambda p, depth=depth, smooth=smooth: split_touching(p, depth, smooth))
        print(f"| watershed | {depth:g} | {smooth:g} | {s['dsc']:.3f} | {s['ap50']:.3f} | {s['pq']:.3f} |", flush=True)


if __name__ == "__main__":
    main()
