"""Instance segmentation scores of label images: DSC, AP50 and panoptic quality (three definitions).

A label image is a 2-D array of non-negative integers: 0 is background, every other value one particle
instance (values need not be consecutive). Data flow: network output (class or probability map) ->
``binarize_and_label`` -> label image -> ``match_instances`` against the true labels -> scores.

A predicted and a true instance match when their IoU is strictly greater than the threshold (0.5 for
every score here). Above 0.5 each instance can match at most one other (see ``match_instances``), so
the matching needs no assignment step and every score is unambiguous.

Panoptic quality, three ways: ``panoptic_quality`` is the standard PQ of the particle (thing) class;
``class_averaged_pq`` averages it with the background as a stuff class (PQ over both classes);
``semantic_pq`` averages background and particle both as stuff (pixel IoUs, instances ignored). The
DiffRenderGAN paper's PQ (TiO2 SEM: 0.845 at AP50 0.474 synthetic, 0.930 at AP50 0.567 real) exceeds what
either instance-based definition allows at its AP50 (RQ = 2 AP50 / (1 + AP50), PQ <= RQ and
PQ_classes <= (1 + RQ) / 2: 0.82 and 0.86), so only ``semantic_pq`` can be that number.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.optimize import linear_sum_assignment

from drgan.core.errors import ConfigError, DataError

__all__ = [
    "binarize_and_label",
    "dice",
    "InstanceMatch",
    "match_instances",
    "ap50",
    "panoptic_quality",
    "class_averaged_pq",
    "semantic_pq",
    "segmentation_scores",
    "ERROR_SOURCES",
    "error_sources",
]

# 4-connectivity: pixels touching only at a corner belong to different particles.
_FOUR_CONNECTED = ndimage.generate_binary_structure(2, 1)


def _check_pair(pred: np.ndarray, true: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    pred, true = np.asarray(pred), np.asarray(true)
    if pred.shape != true.shape:
        raise DataError(f"{what}: prediction shape {pred.shape} differs from ground truth shape {true.shape}")
    if pred.ndim != 2:
        raise DataError(f"{what}: expected 2-D images, got shape {pred.shape}")
    return pred, true


def _check_labels(labels: np.ndarray, name: str) -> np.ndarray:
    if labels.dtype == bool or not np.issubdtype(labels.dtype, np.integer):
        raise DataError(
            f"{name}: expected an integer label image (0 = background), got dtype {labels.dtype}; "
            "use binarize_and_label for masks or probability maps"
        )
    if labels.size and labels.min() < 0:
        raise DataError(f"{name}: label values must be >= 0, got minimum {labels.min()}")
    return labels


def binarize_and_label(prob_or_class_map: np.ndarray, particle_class: int = 1, threshold: float = 0.5) -> np.ndarray:
    """Particle instances of a segmentation output as a label image (int32, 0 = background).

    - Integer (or bool) input is a class map: pixels equal to ``particle_class`` are particle. Any other
      class, in particular a contour / boundary class drawn between touching particles, counts as not
      particle, so that it separates the instances.
    - Float input is a particle probability map in [0, 1]: pixels > ``threshold`` are particle.

    Instances are the 4-connected components of the particle pixels (diagonal neighbours are separate).
    """
    arr = np.asarray(prob_or_class_map)
    if arr.ndim != 2:
        raise DataError(f"binarize_and_label: expected a 2-D class or probability map, got shape {arr.shape}")
    if arr.dtype == bool or np.issubdtype(arr.dtype, np.integer):
        particle = arr == particle_class
    elif np.issubdtype(arr.dtype, np.floating):
        if not 0.0 <= threshold < 1.0:
            raise ConfigError(f"binarize_and_label: threshold must be in [0, 1), got {threshold}")
        if arr.size and (not np.isfinite(arr).all() or arr.min() < 0.0 or arr.max() > 1.0):
            raise DataError(
                "binarize_and_label: a float map must be probabilities in [0, 1]; pass class maps as integers"
            )
        particle = arr > threshold
    else:
        raise DataError(f"binarize_and_label: unsupported dtype {arr.dtype}")
    labels, _ = ndimage.label(particle, structure=_FOUR_CONNECTED)
    return labels.astype(np.int32)


def dice(pred_mask: np.ndarray, true_mask: np.ndarray) -> float:
    """Dice similarity coefficient 2|P & T| / (|P| + |T|) of the foregrounds (nonzero pixels).

    Both foregrounds empty is a perfect prediction: 1.0.
    """
    pred, true = _check_pair(pred_mask, true_mask, "dice")
    p, t = pred != 0, true != 0
    total = int(p.sum()) + int(t.sum())
    if total == 0:
        return 1.0
    return 2.0 * int((p & t).sum()) / total


@dataclass(frozen=True)
class InstanceMatch:
    """Result of ``match_instances``. Ids are the label values of the two images."""

    pairs: list[tuple[int, int]]  # (pred_id, true_id), one per true positive
    ious: np.ndarray  # IoU of each pair, float64, same order
    unmatched_pred: list[int]  # false positives
    unmatched_true: list[int]  # false negatives

    @property
    def tp(self) -> int:
        return len(self.pairs)

    @property
    def fp(self) -> int:
        return len(self.unmatched_pred)

    @property
    def fn(self) -> int:
        return len(self.unmatched_true)


DENSE_PAIRS = 1 << 24  # (largest pred id + 1) x (largest true id + 1) up to which `_overlaps` counts by id directly


def _overlaps(pred: np.ndarray, true: np.ndarray):
    """Pixel counts of every (pred instance, true instance) intersection, each instance's area, and the ids of
    rows and columns (background left out). Labels of non-negative ids up to a few thousand (those of ndimage.label)
    are counted by id at once; others through their sorted unique ids (a sort of every pixel: the costly way)."""
    pred, true = np.asarray(pred), np.asarray(true)
    top_p, top_t = (int(a.max(initial=0)) for a in (pred, true))
    if min(pred.min(initial=0), true.min(initial=0)) >= 0 and (top_p + 1) * (top_t + 1) <= DENSE_PAIRS:
        counts = np.bincount(
            pred.ravel().astype(np.int64) * (top_t + 1) + true.ravel(), minlength=(top_p + 1) * (top_t + 1)
        ).reshape(top_p + 1, top_t + 1)
        rows, cols = counts.sum(axis=1) > 0, counts.sum(axis=0) > 0  # the ids present (as np.unique finds them)
        counts, pred_ids, true_ids = counts[np.ix_(rows, cols)], np.flatnonzero(rows), np.flatnonzero(cols)
    else:
        pred_ids, pred_idx = np.unique(pred, return_inverse=True)  # index 0 is background if present
        true_ids, true_idx = np.unique(true, return_inverse=True)
        counts = np.bincount(
            pred_idx.ravel() * len(true_ids) + true_idx.ravel(), minlength=len(pred_ids) * len(true_ids)
        ).reshape(len(pred_ids), len(true_ids))
    keep_p, keep_t = pred_ids != 0, true_ids != 0
    inter = counts[np.ix_(keep_p, keep_t)].astype(np.float64)
    area_pred = counts.sum(axis=1)[keep_p].astype(np.float64)
    area_true = counts.sum(axis=0)[keep_t].astype(np.float64)
    return inter, area_pred, area_true, pred_ids[keep_p], true_ids[keep_t]


def _iou_matrix(pred: np.ndarray, true: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IoU of every (pred instance, true instance) pair, with the instance ids of rows and columns."""
    inter, area_pred, area_true, pred_ids, true_ids = _overlaps(pred, true)
    union = area_pred[:, None] + area_true[None, :] - inter
    return inter / np.maximum(union, 1.0), pred_ids, true_ids


def match_instances(pred_labels: np.ndarray, true_labels: np.ndarray, iou_threshold: float = 0.5) -> InstanceMatch:
    """Match predicted to true instances; a pair matches when IoU > ``iou_threshold`` (strictly).

    For thresholds >= 0.5 the matching is unique: IoU(p, t) > 0.5 means |p & t| > |p | t| / 2 >= |t| / 2,
    i.e. p covers more than half of t, and two disjoint predictions cannot both do that (nor can one
    prediction cover more than half of two disjoint true instances). So every pair above the threshold is
    a match. At exactly 0.5 this fails (two halves of one particle both have IoU 0.5), which is why the
    comparison is strict: IoU == 0.5 is not a match. Below 0.5 the one-to-one matching that maximises the
    summed IoU over pairs above the threshold is found with the Hungarian algorithm.
    """
    pred, true = _check_pair(pred_labels, true_labels, "match_instances")
    pred, true = _check_labels(pred, "pred_labels"), _check_labels(true, "true_labels")
    if not 0.0 <= iou_threshold < 1.0:
        raise ConfigError(f"match_instances: iou_threshold must be in [0, 1), got {iou_threshold}")
    iou, pred_ids, true_ids = _iou_matrix(pred, true)

    if iou_threshold >= 0.5:
        rows, cols = np.nonzero(iou > iou_threshold)
    else:
        rows, cols = linear_sum_assignment(np.where(iou > iou_threshold, iou, 0.0), maximize=True)
        ok = iou[rows, cols] > iou_threshold
        rows, cols = rows[ok], cols[ok]
    order = np.argsort(pred_ids[rows], kind="stable")
    rows, cols = rows[order], cols[order]
    matched_p, matched_t = set(rows.tolist()), set(cols.tolist())
    return InstanceMatch(
        pairs=[(int(pred_ids[r]), int(true_ids[c])) for r, c in zip(rows, cols)],
        ious=iou[rows, cols].astype(np.float64),
        unmatched_pred=[int(i) for k, i in enumerate(pred_ids) if k not in matched_p],
        unmatched_true=[int(i) for k, i in enumerate(true_ids) if k not in matched_t],
    )


def _ap50(m: InstanceMatch) -> float:
    total = m.tp + m.fp + m.fn
    return 1.0 if total == 0 else m.tp / total


def _pq(m: InstanceMatch) -> tuple[float, float, float]:
    if m.tp + m.fp + m.fn == 0:
        return 1.0, 1.0, 1.0
    sq = float(m.ious.mean()) if m.tp else 0.0
    rq = m.tp / (m.tp + 0.5 * m.fp + 0.5 * m.fn)
    return sq * rq, sq, rq


def ap50(pred_labels: np.ndarray, true_labels: np.ndarray) -> float:
    """The "AP at IoU 0.5" of the DiffRenderGAN paper: TP / (TP + FP + FN).

    TP are predicted/true pairs with IoU > 0.5 (one-to-one, see ``match_instances``), FP unmatched
    predictions, FN unmatched true instances. This is the single-threshold "average precision" of the
    Data Science Bowl 2018 / StarDist ("accuracy" in StarDist's ``matching``), not the area under a
    precision-recall curve over detection scores (there are no scores here). Both images without
    instances give 1.0.
    """
    return _ap50(match_instances(pred_labels, true_labels, 0.5))


def panoptic_quality(pred_labels: np.ndarray, true_labels: np.ndarray) -> tuple[float, float, float]:
    """(PQ, SQ, RQ) of the particle class (Kirillov et al., 2019): the standard, things-only PQ.

    SQ = mean IoU of the matched pairs (IoU > 0.5), RQ = TP / (TP + FP/2 + FN/2), PQ = SQ * RQ.
    No matches gives SQ = 0 (and PQ = RQ = 0); both images without instances give (1, 1, 1).
    """
    return _pq(match_instances(pred_labels, true_labels, 0.5))


def _stuff_pq(pred_mask: np.ndarray, true_mask: np.ndarray) -> float | None:
    """PQ of a stuff class (one segment per image: all its pixels): its IoU when > 0.5, else 0 (an unmatched
    prediction and an unmatched truth); None when neither image has the class."""
    union = int((pred_mask | true_mask).sum())
    if union == 0:
        return None
    iou = int((pred_mask & true_mask).sum()) / union
    return iou if iou > 0.5 else 0.0


def _class_mean(values: list[float | None]) -> float:
    present = [v for v in values if v is not None]
    return float(np.mean(present)) if present else 1.0


def _class_averaged_pq(m: InstanceMatch, pred: np.ndarray, true: np.ndarray) -> float:
    particle = None if m.tp + m.fp + m.fn == 0 else _pq(m)[0]
    return _class_mean([_stuff_pq(pred == 0, true == 0), particle])


def _semantic_pq(pred: np.ndarray, true: np.ndarray) -> float:
    return _class_mean([_stuff_pq(pred == 0, true == 0), _stuff_pq(pred != 0, true != 0)])


def class_averaged_pq(pred_labels: np.ndarray, true_labels: np.ndarray) -> float:
    """PQ averaged over the two classes, background as a stuff class and particle as a thing class.

    PQ_classes = (PQ_background + PQ_particle) / 2, the panoptic quality of Kirillov et al. (2019) over all
    classes, as ``torchmetrics.detection.PanopticQuality(things={1}, stuffs={0})`` computes it for one image:
    PQ_particle is ``panoptic_quality``; the background is one segment per image (all label-0 pixels), so
    PQ_background = IoU(background) when it is > 0.5, else 0. A class in neither image is left out of the
    mean (both images without particles: PQ_background alone). Since PQ_particle <= RQ = 2 AP50 / (1 + AP50),
    PQ_classes <= (1 + RQ) / 2.
    """
    pred, true = _check_pair(pred_labels, true_labels, "class_averaged_pq")
    m = match_instances(pred, true, 0.5)
    return _class_averaged_pq(m, pred, true)


def semantic_pq(pred_labels: np.ndarray, true_labels: np.ndarray) -> float:
    """PQ averaged over background and particle, both as stuff classes (instances ignored).

    PQ_semantic = (PQ_background + PQ_particle_pixels) / 2 with PQ_c = IoU_c when IoU_c > 0.5, else 0, where
    IoU_particle_pixels is the IoU of the two particle masks (every instance merged): what a panoptic-quality
    implementation returns when it is given semantic masks without instance ids. It depends on the pixel
    overlap only, so no AP50 bounds it. A class in neither image is left out of the mean.
    """
    pred, true = _check_pair(pred_labels, true_labels, "semantic_pq")
    pred, true = _check_labels(pred, "pred_labels"), _check_labels(true, "true_labels")
    return _semantic_pq(pred, true)


def segmentation_scores(pred_labels: np.ndarray, true_labels: np.ndarray) -> dict[str, float | int]:
    """All scores of one image pair: dsc, ap50, pq, sq, rq, pq_classes, pq_semantic and the counts tp, fp, fn."""
    m = match_instances(pred_labels, true_labels, 0.5)
    pred, true = np.asarray(pred_labels), np.asarray(true_labels)
    pq, sq, rq = _pq(m)
    return {
        "dsc": dice(pred_labels, true_labels),
        "ap50": _ap50(m),
        "pq": pq,
        "sq": sq,
        "rq": rq,
        "pq_classes": _class_averaged_pq(m, pred, true),
        "pq_semantic": _semantic_pq(pred, true),
        "tp": m.tp,
        "fp": m.fp,
        "fn": m.fn,
    }


# What becomes of each true particle (error_sources), in the order a table lists them.
ERROR_SOURCES = ("matched", "merged", "split", "missed", "outline")


def majority_holders(pred_labels: np.ndarray, true_labels: np.ndarray) -> dict[int, int]:
    """Per true particle id, the prediction id that holds more than half of it (`error_sources`' rule; at most one
    can); particles no prediction holds so are absent."""
    inter, _, area_true, pred_ids, true_ids = _overlaps(pred_labels, true_labels)
    rows, cols = np.nonzero(inter > area_true[None, :] / 2.0)
    return dict(zip(true_ids[cols].tolist(), pred_ids[rows].tolist()))


def error_sources(pred_labels: np.ndarray, true_labels: np.ndarray) -> dict[str, int | np.ndarray]:
    """Where an instance segmentation loses particles, per true particle and per prediction.

    Each true particle is exactly one of (``ERROR_SOURCES``):

    - matched: IoU > 0.5 with a prediction (a true positive of ``match_instances``);
    - merged: more than half of it lies in one prediction that also holds more than half of another true
      particle (touching particles counted as one: the count falls and the sizes grow);
    - split: more than half of it is predicted foreground, but no single prediction holds more than half;
    - missed: at most half of it is predicted foreground;
    - outline: the rest: one prediction holds most of it, yet their IoU is <= 0.5 (an outline far too large
      or too small).

    Predictions that hold no more than half of any true particle and lie mostly (more than half their area) off
    the true particles are ``false`` particles. And
    ``diameter_offset``: per matched pair, predicted minus true equivalent diameter (px): a systematic boundary
    offset shifts every reported size by its median. Returns {source: count, "n_true", "n_pred", "false",
    "diameter_offset": array}."""
    pred, true = _check_pair(pred_labels, true_labels, "error_sources")
    pred, true = _check_labels(pred, "pred_labels"), _check_labels(true, "true_labels")
    inter, area_pred, area_true, pred_ids, true_ids = _overlaps(pred, true)
    iou = inter / np.maximum(area_pred[:, None] + area_true[None, :] - inter, 1.0)
    half_true = inter > area_true[None, :] / 2.0  # prediction p holds more than half of true particle t
    matched = (iou > 0.5).any(axis=0)
    covered = inter.sum(axis=0) > area_true / 2.0
    holder = half_true.any(axis=0)
    holds_two = half_true.sum(axis=1) >= 2  # per prediction
    merged = ~matched & (half_true & holds_two[:, None]).any(axis=0)
    split = ~matched & ~merged & covered & ~holder
    missed = ~matched & ~covered
    outline = ~matched & ~merged & ~split & ~missed
    false = ~half_true.any(axis=1) & (inter.sum(axis=1) < area_pred / 2.0)
    rows, cols = np.nonzero(iou > 0.5)
    diameter = lambda area: 2.0 * np.sqrt(area / np.pi)  # noqa: E731
    return {
        "n_true": len(true_ids),
        "n_pred": len(pred_ids),
        "matched": int(matched.sum()),
        "merged": int(merged.sum()),
        "split": int(split.sum()),
        "missed": int(missed.sum()),
        "outline": int(outline.sum()),
        "false": int(false.sum()),
        "diameter_offset": diameter(area_pred[rows]) - diameter(area_true[cols]),
    }
