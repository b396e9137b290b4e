"""Does the image's own grey separate touching particles that the distance transform leaves merged? On annotated
*train* ids only (never test ids): the U-Net's probabilities once per image (noise-matched as evaluate does), then
the watershed split with its seed landscape = the smoothed distance transform of the particle core times the grey
(normalised per image: 0 at the background's median, 1 at the particles' median; clipped to [0, 1]; inverted for
dark particles) to the power ``gamma`` (0: the default split). A sintered SEM neck dips to 0.69 of the particles'
contrast (experiments/statistics/merges.md, "What a contact looks like"), so gamma > 0 deepens the saddle between two
particles' maxima. Prints pooled AP50 and merged / split shares per (gamma, depth).

    python experiments/statistics/grey_split.py runs/pipeline/bam_tio2_sem/segment/checkpoints/last.ckpt \
        ../shared/datasets/tio2_sem --level 0.0225 --gammas 0 0.5 1 2 --depths 1 2
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import ndimage as ndi
from skimage.morphology import h_maxima

from drgan.data.classical.watershed import distance_watershed, flood
from drgan.metrics.instance_scores import binarize_and_label, error_sources, match_instances
from drgan.segmenters.inference import predict_probs, separate_regions, without_annotations
from drgan.segmenters.noise_match import match_noise
from drgan.segmenters.pairs import load_real_pairs, real_ids
from drgan.segmenters.registry import load_segmenter


def grey_scale(image: np.ndarray, foreground: np.ndarray, smooth: float = 1.0) -> np.ndarray:
    """The image's grey on the particles' scale: 0 at the background's median, 1 at the particles' (either
    polarity), smoothed by ``smooth`` px, clipped to [0, 1]."""
    grey = ndi.gaussian_filter(image.astype(np.float32), smooth) if smooth > 0 else image
    inside, outside = np.median(image[foreground]), np.median(image[~foreground])
    if abs(inside - outside) < 1e-6:
        return np.ones_like(grey)
    return np.clip((grey - outside) / (inside - outside), 0.0, 1.0)


def foreground_and_core(probs: np.ndarray, core_level: float | None) -> tuple[np.ndarray, np.ndarray]:
    """The U-Net split's foreground (particle + contour > 0.5) and seed core, as drgan.segmenters.inference has them."""
    core = probs.argmax(axis=0) == 1 if core_level is None else probs[1] > core_level
    return probs[1] + probs[2] > 0.5, core


def grey_split(probs, image, depth, core_level, gamma, smooth=1.0):
    foreground, core = foreground_and_core(probs, core_level)
    if not core.any():
        return np.zeros(core.shape, np.uint8)
    distance = ndi.gaussian_filter(ndi.distance_transform_edt(core), smooth)
    if gamma > 0:
        distance = distance * grey_scale(image, foreground) ** gamma
    seeds = h_maxima(distance, depth).astype(bool)
    return separate_regions(flood(distance, seeds, foreground))


def region_table(cached, depth, core_level) -> None:
    """How the default split's regions differ by how many true particles each holds (more than half of them): their
    area over the image's median region area, solidity and eccentricity (10th / 50th / 90th percentiles). Whether a
    shape or size rule could tell a merged region from a single particle."""
    from skimage.measure import regionprops

    rows = []
    for probs, _, truth in cached:
        foreground, core = foreground_and_core(probs, core_level)
        regions = regionprops(distance_watershed(core, foreground, smooth=1.0, depth=depth))  # the default split
        median = np.median([r.area for r in regions]) if regions else 1.0
        true_area = np.bincount(truth.ravel())
        for r in regions:
            inside = truth[r.slice][r.image]
            ids, counts = np.unique(inside[inside > 0], return_counts=True)
            held = int(sum(c > true_area[i] / 2 for i, c in zip(ids, counts)))
            rows.append((r.area / median, r.solidity, r.eccentricity, min(held, 3)))
    table = np.array(rows)
    print("| true particles held | regions | area / median | solidity | eccentricity |")
    print("|---|---|---|---|---|")
    for held, name in ((0, "0"), (1, "1"), (2, "2"), (3, "3 or more")):
        sel = table[:, 3] == held
        if sel.any():
            q = [" / ".join(f"{v:.2f}" for v in np.percentile(table[sel, k], [10, 50, 90])) for k in range(3)]
            print(f"| {name} | {int(sel.sum())} | {q[0]} | {q[1]} | {q[2]} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("ckpt")
    parser.add_argument("data")
    parser.add_argument("--level", type=float, default=0.0, help="noise-matching level (the segmenter's own)")
    parser.add_argument("--n", type=int, default=32)
    parser.add_argument("--gammas", type=float, nargs="+", default=[0.0, 0.5, 1.0, 2.0])
    parser.add_argument("--cache", help="save the probabilities, images and labels here (.npz)")
    parser.add_argument("--depths", type=float, nargs="+", default=None, help="default: the calibrated one")
    args = parser.parse_args()
    model = load_segmenter(args.ckpt, "model").eval()
    calibration = getattr(model, "split_calibration", None) or {}
    core = calibration.get("split_core")
    depths = args.depths or [calibration.get("split_depth", 1.0)]
    ids = real_ids(args.data, None, "train")[: args.n]
    pairs = load_real_pairs(args.data, ids, 1)
    cached = []
    for pair in pairs:
        image = match_noise(pair.image, args.level).astype(np.float32) if args.level else pair.image
        cached.append((predict_probs(model, image), pair.image, pair.labels))
    if args.cache:
        np.savez_compressed(args.cache, **{f"{k}_{i}": v for i, c in enumerate(cached) for k, v in zip("pil", c)})
    print(f"{args.ckpt}: {len(pairs)} train images, core {core}")
    region_table(cached, depths[0], core)
    print("| gamma | depth | AP50 | merged | split | n_pred / n_true |")
    print("|---|---|---|---|---|---|")
    for gamma in args.gammas:
        for depth in depths:
            tp = fp = fn = merged = split = n_true = n_pred = 0
            for probs, image, truth in cached:
                classes = without_annotations(grey_split(probs, image, depth, core, gamma), image)
                pred = binarize_and_label(classes)
                m = match_instances(pred, truth)
                tp, fp, fn = tp + m.tp, fp + m.fp, fn + m.fn
                e = error_sources(pred, truth)
                merged, split = merged + e["merged"], split + e["split"]
                n_true, n_pred = n_true + e["n_true"], n_pred + e["n_pred"]
            ap50 = tp / max(tp + fp + fn, 1)
            print(
                f"| {gamma} | {depth} | {ap50:.3f} | {merged / n_true:.1%} | {split / n_true:.1%} | "
                f"{n_pred} / {n_true} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
