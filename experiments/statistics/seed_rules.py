"""Which seeds split touching particles best, given one trained network's outputs? (issue 67: merges are the error)

    python experiments/statistics/seed_rules.py SEGMENT_RUN GENERATED [--pairs validation|check|both]

The network runs once per pair (its own scale); each seed rule then splits the same probabilities and is scored as the
closed-loop check scores (drgan.segmenters.closed_loop): on the validation pairs drgan.segment calibrates on (choose
there) and on the held-out check pairs (report there). Rules: the calibrated split and the grid's h-maxima /
components seeds (drgan.segmenters.inference.split_touching), and seeds from the particle probability's own levels
(`level_seeds`: a core piece that falls apart into two pieces of at least MIN px as the threshold rises is two
particles), flooded over the distance transform or over the probability.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi
from skimage.segmentation import watershed

from drgan.segmenters.closed_loop import check_inference, closed_loop
from drgan.segmenters.inference import predict_probs, separate_regions, split_touching
from drgan.segmenters.pairs import load_generated_pairs, split_pairs
from drgan.segmenters.registry import load_segmenter

FOUR = ndi.generate_binary_structure(2, 1)
LEVELS = (0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.93, 0.95, 0.97, 0.98, 0.99)


def level_seeds(p: np.ndarray, levels=LEVELS, min_px: int = 8) -> np.ndarray:
    """int32 seed labels: the leaves of the component tree of ``p`` over ``levels`` whose pieces hold >= ``min_px``."""
    seeds = np.zeros(p.shape, np.int32)
    count = 0
    pieces, n = ndi.label(p > levels[0], structure=FOUR)
    stack = [(pieces[box] == i, box, 1) for i, box in enumerate(ndi.find_objects(pieces), start=1) if box is not None]
    while stack:
        region, box, k = stack.pop()
        if region.sum() < min_px:
            continue
        children = []
        for level in levels[k:]:
            sub, m = ndi.label(region & (p[box] > level), structure=FOUR)
            sizes = np.bincount(sub.ravel(), minlength=m + 1)[1:]
            kept = [j + 1 for j in range(m) if sizes[j] >= min_px]
            if len(kept) >= 2:
                children = [sub == j for j in kept]
                k = levels.index(level) + 1
                break
            if not kept:
                break
            region = sub == kept[0]
        if children:
            stack.extend((c, box, k) for c in children)
        else:
            count += 1
            seeds[box][region] = count
    return seeds


def level_split(probs: np.ndarray, min_px: int, over: str) -> np.ndarray:
    foreground = probs[1] + probs[2] > 0.5
    markers = level_seeds(probs[1], min_px=min_px)
    if over == "probability":
        surface = -ndi.gaussian_filter(probs[1], 1.0)
    else:
        surface = -ndi.gaussian_filter(ndi.distance_transform_edt(probs[1] > 0.5), 1.0)
    return separate_regions(watershed(surface, markers, mask=foreground))


def rules(calibrated: dict) -> dict:
    out = {"calibrated " + ", ".join(f"{k}={v}" for k, v in calibrated.items()): None}
    for seeds in ("hmaxima", "components"):
        for depth in (1.0, 2.0):
            for core in (None, 0.8, 0.95):
                out[f"{seeds}, depth {depth:g}, core {core}"] = lambda p, s=seeds, d=depth, c=core: split_touching(
                    p, d, 1.0, c, s
                )
    for min_px in (4, 8, 16, 32):
        for over in ("distance", "probability"):
            out[f"levels, min {min_px} px, over {over}"] = lambda p, m=min_px, o=over: level_split(p, m, o)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("generated", type=Path)
    parser.add_argument("--pairs", default="both", choices=("validation", "check", "both"))
    args = parser.parse_args()
    model = load_segmenter(str(args.run / "checkpoints" / "last.ckpt")).eval()
    pairs = load_generated_pairs(str(args.generated), setting="data")
    ids = set((model.closed_loop or {}).get("ids") or [])
    check = [p for p in pairs if p.id in ids]
    validation = split_pairs([p for p in pairs if p.id not in ids], 0.1, 0)[1]
    sets = {"validation": validation, "check": check}
    chosen = [args.pairs] if args.pairs != "both" else ["validation", "check"]
    settings = check_inference(model.split_calibration)
    calibrated = {k: settings[k] for k in ("split_depth", "split_core", "split_seeds") if k in settings}
    table = rules(calibrated)
    table[next(iter(table))] = lambda p: split_touching(p, **{"split_smooth": 1.0, **calibrated})
    probs = {}
    for name in chosen:
        for pair in sets[name]:
            probs[id(pair.image)] = predict_probs(model, np.asarray(pair.image, np.float32))[:3]
    header = " | ".join(f"{n}: median / count / merged / AP50" for n in chosen)
    print(f"| seeds | {header} |")
    print("|---|" + "---|" * len(chosen))
    for rule, split in table.items():
        cells = []
        for name in chosen:
            c = closed_loop(None, sets[name], predictor=lambda image, f=split: f(probs[id(image)]), n_boot=0)
            cells.append(
                f"{100 * c['median_error']['value']:+.1f} / {100 * c['count_error']['value']:+.1f} / "
                f"{100 * c['merged']:.1f} % / {c['ap50']:.3f}"
            )
        print(f"| {rule} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
