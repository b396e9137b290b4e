"""The splits' own ceiling: each instance split fed the outputs a perfect network would give for the held-out pairs of
a segment run (exact classes, centre map and ray distances from the exact labels), scored as the closed-loop check
scores (drgan.segmenters.closed_loop). What remains is the representation's error, not the network's.

    python experiments/statistics/split_ceiling.py SEGMENT_RUN/checkpoints/last.ckpt GENERATED
    python experiments/statistics/split_ceiling.py - FRESH      # every checkable pair of FRESH (none trained on)

The "shape only" rows take away the contour class (its pixels become particle): the outputs of a network that finds
every particle's outline but no line between touching ones, so what is split is the foreground's shape alone; the
ceiling of any seed rule on contacts the image does not show.
"""

from __future__ import annotations

import argparse

import numpy as np

from drgan.scene.labels import centre_distance, class_mask
from drgan.segmenters.closed_loop import checkable, closed_loop
from drgan.segmenters.inference import split_by_centres, split_by_stars, split_touching
from drgan.segmenters.pairs import load_generated_pairs
from drgan.segmenters.polygons import ray_distances
from drgan.segmenters.registry import load_segmenter


def exact_outputs(labels: np.ndarray, n_rays: int = 16) -> np.ndarray:
    """Classes (one-hot), the centre map and the ray distances of ``labels``: a perfect star-convex segmenter's outputs."""
    classes = class_mask(labels, 1)
    onehot = np.stack([(classes == c).astype(np.float32) for c in range(3)])
    return np.concatenate([onehot, centre_distance(labels)[None], ray_distances(labels, n_rays, 32)])


def shape_only(outputs: np.ndarray) -> np.ndarray:
    """The three class channels with the contour class folded into the particle class."""
    return np.stack([outputs[0], outputs[1] + outputs[2], np.zeros_like(outputs[2])])


SPLITS = {
    "watershed, h-maxima, depth 1, core 0.95": lambda o: split_touching(o[:3], 1.0, 1.0, 0.95),
    "watershed, h-maxima, depth 2, argmax": lambda o: split_touching(o[:3], 2.0, 1.0, None),
    "watershed, components, depth 1, argmax": lambda o: split_touching(o[:3], 1.0, 1.0, None, "components"),
    "watershed, components, depth 2, argmax": lambda o: split_touching(o[:3], 2.0, 1.0, None, "components"),
    "centres, level 0.5": lambda o: split_by_centres(o[:4], 0.5),
    "star, level 0.5": lambda o: split_by_stars(o, 0.5),
    "shape only: h-maxima, depth 1": lambda o: split_touching(shape_only(o), 1.0, 1.0, None),
    "shape only: h-maxima, depth 2": lambda o: split_touching(shape_only(o), 2.0, 1.0, None),
    "shape only: h-maxima, depth 4": lambda o: split_touching(shape_only(o), 4.0, 1.0, None),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("ckpt", help="a segment checkpoint (its held-out pairs), or - for every checkable pair")
    parser.add_argument("generated")
    args = parser.parse_args()
    if args.ckpt == "-":
        pairs = [p for p in load_generated_pairs(args.generated) if checkable(p)]
    else:
        ids = set((load_segmenter(args.ckpt).closed_loop or {}).get("ids") or [])
        pairs = [p for p in load_generated_pairs(args.generated) if p.id in ids]
    outputs = {id(p.image): exact_outputs(np.asarray(p.labels)) for p in pairs}
    print(
        "| split (exact inputs) | median error | count error | merged | split | missed | AP50 | hidden / shown contacts merged |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name, split in SPLITS.items():
        c = closed_loop(None, pairs, predictor=lambda image, f=split: f(outputs[id(image)]), n_boot=0)
        print(
            f"| {name} | {100 * c['median_error']['value']:+.1f} % | {100 * c['count_error']['value']:+.1f} % | "
            f"{100 * c['merged']:.1f} % | {100 * c['split']:.1f} % | {100 * c['missed']:.1f} % | {c['ap50']:.3f} | "
            f"{contacts(c['contacts'])} |"
        )


def contacts(summary) -> str:
    """The hidden and shown contacts' merged shares (drgan.segmenters.closed_loop.contact_summary)."""
    if not summary:
        return "-"
    share = lambda v: "-" if v is None else f"{100 * v:.1f} %"  # noqa: E731
    return (
        f"{share(summary['hidden_merged'])} / {share(summary['shown_merged'])} ({100 * summary['hidden']:.0f} % hidden)"
    )


if __name__ == "__main__":
    main()
