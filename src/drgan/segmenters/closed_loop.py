"""The segmenter's own size error, measured where the truth is exact: on generated pairs it never trained on.

drgan knows every synthetic particle's outline (the renderer's instance labels), so a segmenter trained on generated
pairs can be scored on more of them without any annotator's convention in the way. drgan.segment holds out
``check_fraction`` of the synthetic pairs (`hold_out`: never trained on, never used to choose the epoch or the
split), predicts them after training as evaluate/analyze predict real images (the same `predict`, the split calibrated
on the validation pairs; held out at the rendered scale and resampled by the segmenter's working scale, as real
images are; no noise matching, no figure-annotation removal: the pairs are the training distribution) and measures
them as drgan.evaluate measures real test images (drgan.metrics.statistics: equivalent diameters of particles not
cut by the border, specks under ``min_area_px`` left out on both sides, bootstrap intervals over pairs).

What `closed_loop` returns (and drgan.segment stores in the checkpoint as ``CLOSED_LOOP_KEY`` and in metrics.json):
``median_error`` / ``mean_error`` / ``count_error`` (relative, {value, low, high}); ``diameter_offset_px`` (median
predicted minus true equivalent diameter of the matched particles: twice the outline's offset from the true edge;
``edge_offset_px`` is that offset itself); ``merged`` / ``split`` / ``missed`` / ``outline`` (shares of the true
particles, drgan.metrics.instance_scores.error_sources), ``false`` (share of the predictions); AP50, DSC and SQ;
``n_pairs``, ``n_true`` and the pairs' ``ids``. drgan.segment also draws the first pairs (closed_loop.png: found
particles matched to a true one green, false ones red, true ones nothing found yellow). A report quotes it as "on
generated images like yours this segmenter measures diameters +x % [interval] and counts y %" (`trust_line`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from drgan.core.errors import ConfigError
from drgan.core.io import write_png
from drgan.core.progress import track
from drgan.metrics import overlays
from drgan.metrics.statistics import interval_text
from drgan.scene.labels import IGNORE

log = logging.getLogger(__name__)

CLOSED_LOOP_KEY = "drgan_closed_loop"  # checkpoint entry: the check's summary (plain numbers)
MIN_CHECK_PAIRS = 4  # held out at least, when the check is on and the pairs allow it
SHEET_PAIRS = 24  # pairs drawn in the check's picture (closed_loop.png)


def checkable(pair) -> bool:
    """A pair whose truth is exact and complete: a rendered pair with its instance labels and no IGNORE pixel (partial
    real backgrounds hold IGNORE where nothing is known; hand-made pairs have no labels)."""
    return pair.labels is not None and not bool((pair.mask == IGNORE).any())


def checked_fraction(fraction) -> float:
    """``check_fraction`` as a float in [0, 0.5), or a ConfigError naming it."""
    if isinstance(fraction, bool) or not isinstance(fraction, (int, float)) or not 0.0 <= fraction < 0.5:
        raise ConfigError(f"check_fraction={fraction!r}: expected a share of the generated pairs in [0, 0.5)")
    return float(fraction)


def hold_out(pairs: Sequence, fraction: float, seed: int) -> tuple[list, list]:
    """(rest, check): a seeded ``fraction`` of the `checkable` pairs set aside, the rest in their order. At least
    ``MIN_CHECK_PAIRS`` when the fraction is > 0, but never more than a quarter of the checkable pairs (too few pairs:
    no check, the training keeps them all)."""
    fraction = checked_fraction(fraction)
    candidates = [k for k, p in enumerate(pairs) if checkable(p)]
    n = max(int(round(fraction * len(candidates))), MIN_CHECK_PAIRS) if fraction > 0 else 0
    if n == 0 or n > len(candidates) // 4:
        return list(pairs), []
    order = np.random.default_rng((int(seed), 4242)).permutation(len(candidates))
    chosen = {candidates[int(i)] for i in order[:n]}
    return [p for k, p in enumerate(pairs) if k not in chosen], [p for k, p in enumerate(pairs) if k in chosen]


def check_inference(calibration: Mapping | None) -> dict:
    """The split settings the check predicts with: the calibration's (drgan.segmenters.calibrate), else the uncalibrated
    defaults evaluate would fall back to."""
    from drgan.segmenters.calibrate import UNCALIBRATED

    cal = dict(calibration or {})
    settings = {key: cal.get(key, value) for key, value in UNCALIBRATED.items()}
    settings["split_smooth"] = float(cal.get("split_smooth", 1.0))
    return settings


def closed_loop(
    model,
    pairs: Sequence,
    calibration: Mapping | None = None,
    min_area_px: float = 8.0,
    n_boot: int = 200,
    seed: int = 0,
    progress: bool = False,
    predictor=None,
    pixel_scale: float = 1.0,
    sheet: Path | None = None,
    **predict_kw,
) -> dict:
    """Score ``model`` on ``pairs`` (generated, exact labels; module docstring) and return the summary (plain numbers).
    ``pixel_scale``: the pairs resampled by it for the network (a segmenter that learnt them at a working scale);
    ``predictor``: image -> class map instead of the model's `predict` (tests); ``predict_kw``: more of `predict`'s
    keywords (e.g. ``mirror=True``); ``sheet``: also write there the first
    ``SHEET_PAIRS`` pairs' overlays (drgan.metrics.overlays: found particles matched green, false red, missed yellow),
    each captioned with its pair's id, pairs with particles before particle-free ones: the picture of what the check
    counted."""
    from drgan.metrics.instance_scores import binarize_and_label, error_sources, segmentation_scores
    from drgan.metrics.statistics import particles

    if not pairs:
        raise ValueError("closed_loop: no pairs to check")
    if predictor is None:
        from drgan.segmenters.inference import predict

        settings = check_inference(calibration)

        def predictor(image):
            return predict(
                model, image, pixel_scale=pixel_scale, noise_match=False, annotations=False, **settings, **predict_kw
            )

    iterator = track(pairs, "closed-loop check", unit="pairs") if progress else pairs
    found, truth, sources, scores, contacts = [], [], [], [], []
    drawn: dict[bool, list] = {True: [], False: []}  # (caption, overlay) of pairs with particles, and of the others
    for pair in iterator:
        true_labels = np.asarray(pair.instances()).astype(np.int64)
        pred_labels = binarize_and_label(np.asarray(predictor(pair.image)).astype(np.int64))
        kind = drawn[bool(true_labels.any())]
        if sheet is not None and len(kind) < SHEET_PAIRS:
            kind.append((str(pair.id), overlays.overlay(np.asarray(pair.image, np.float64), pred_labels, true_labels)))
        found.append(particles(pred_labels).at_least(min_area_px))
        truth.append(particles(true_labels).at_least(min_area_px))
        sources.append(error_sources(pred_labels, true_labels))
        scores.append(segmentation_scores(pred_labels, true_labels))
        contacts += contact_merges(pred_labels, true_labels, pair.image)
    summary = summarise(found, truth, sources, scores, n_boot, seed, contacts)
    shown = (drawn[True] + drawn[False])[:SHEET_PAIRS]  # particles first: a background pair shows only false ones
    if shown:
        write_png(sheet, overlays.sheet([tile for _, tile in shown], captions=[caption for caption, _ in shown]))
    return {**summary, "ids": [str(p.id) for p in pairs]}


def contact_merges(pred_labels: np.ndarray, true_labels: np.ndarray, image: np.ndarray) -> list[tuple[float, bool]]:
    """(neck grey, merged) per contact of two true particles (drgan.data.necks): merged when one prediction holds more
    than half of each (error_sources' rule, per contact)."""
    from drgan.data.necks import necks
    from drgan.metrics.instance_scores import majority_holders

    truth = np.asarray(true_labels, np.int64)
    held = majority_holders(np.asarray(pred_labels, np.int64), truth)
    return [
        (neck.grey, neck.a in held and held[neck.a] == held.get(neck.b))
        for neck in necks(np.asarray(image, np.float64), truth, min_ridge=1)
    ]


def contact_summary(contacts: Sequence[tuple[float, bool]]) -> dict | None:
    """How many contacts the images hide (neck grey >= drgan.data.necks.HIDDEN_NECK) and show, and the share of each
    merged; None without a contact."""
    from drgan.data.necks import HIDDEN_NECK

    if not contacts:
        return None
    grey = np.array([g for g, _ in contacts])
    merged = np.array([m for _, m in contacts])
    hidden = grey >= HIDDEN_NECK
    share = lambda keep: _plain(merged[keep].mean()) if keep.any() else None  # noqa: E731
    return {"n": len(contacts), "hidden": _plain(hidden.mean()), "hidden_merged": share(hidden),
            "shown_merged": share(~hidden)}  # fmt: skip


def summarise(found, truth, sources, scores, n_boot: int = 200, seed: int = 0, contacts=()) -> dict:
    """The check's summary from per-pair particles, error sources and scores (`closed_loop`), and the contacts'
    (neck grey, merged) (`contact_merges`)."""
    from drgan.metrics.statistics import compare_sizes

    sizes = compare_sizes(found, truth, n_boot=n_boot, seed=seed)
    n_true = sum(int(s["n_true"]) for s in sources)
    n_pred = sum(int(s["n_pred"]) for s in sources)
    offsets = np.concatenate([s["diameter_offset"] for s in sources] or [np.zeros(0)])
    offset = float(np.median(offsets)) if offsets.size else math.nan
    share = lambda key, total: sum(int(s[key]) for s in sources) / total if total else math.nan  # noqa: E731
    tp, fp, fn = (sum(int(s[k]) for s in scores) for k in ("tp", "fp", "fn"))
    cell = lambda c: {k: _plain(c[k]) for k in ("value", "low", "high")}  # noqa: E731
    return {
        "n_pairs": len(found),
        "n_true": n_true,
        "n_pred": n_pred,
        "median_diameter_true_px": _plain(sizes["median_diameter_true"]["value"]),
        "median_error": cell(sizes["median_error"]),
        "mean_error": cell(sizes["mean_error"]),
        "count_error": cell(sizes["count_error"]),
        "diameter_offset_px": _plain(offset),
        "edge_offset_px": _plain(offset / 2.0),
        **{key: _plain(share(key, n_true)) for key in ("matched", "merged", "split", "missed", "outline")},
        "false": _plain(share("false", n_pred)),
        "ap50": _plain(tp / (tp + fp + fn)) if tp + fp + fn else 1.0,
        "dsc": _plain(float(np.mean([s["dsc"] for s in scores]))),
        "sq": _plain(float(np.mean([s["sq"] for s in scores if s["tp"]])) if tp else math.nan),
        "contacts": contact_summary(contacts),
    }


def _plain(value) -> float | None:
    """A float for JSON and checkpoints (weights_only), None for nan/inf."""
    value = float(value)
    return value if math.isfinite(value) else None


def stored_closed_loop(checkpoint: Mapping) -> dict | None:
    """The check a checkpoint holds (``CLOSED_LOOP_KEY``), or None (trained before it existed, or on real images)."""
    entry = checkpoint.get(CLOSED_LOOP_KEY)
    ok = isinstance(entry, Mapping) and isinstance(entry.get("median_error"), Mapping)
    return dict(entry) if ok else None


def _percent(value) -> str:
    return "n/a" if value is None else f"{100 * value:+.1f} %"


def _interval(cell: Mapping) -> str:
    return interval_text({"value": cell.get("value"), "low": cell.get("low"), "high": cell.get("high")}, _percent)


def trust_line(check: Mapping) -> str:
    """One sentence a report prints: how far this segmenter's sizes and counts are off where the truth is exact."""
    offset = check.get("edge_offset_px")
    merged = check.get("merged")
    return (
        f"On {check.get('n_pairs')} generated images like yours that it never trained on ({check.get('n_true')} "
        f"particles, exact outlines), this segmenter's median diameter is off by {_interval(check['median_error'])} "
        f"and its count by {_interval(check['count_error'])}"
        + (f"; its outlines lie {offset:+.2f} px from the true edge" if offset is not None else "")
        + (f", {100 * merged:.1f} % of the particles merged with a neighbour" if merged is not None else "")
        + " (95 % intervals over images)"
        + _contacts_clause(check.get("contacts"))
        + "."
    )


def _contacts_clause(contacts: Mapping | None) -> str:
    """Where the merges are: the contacts the images hide and those they show (`contact_summary`)."""
    if not contacts or contacts.get("hidden_merged") is None or contacts.get("shown_merged") is None:
        return ""
    return (
        f"; it merged {100 * contacts['hidden_merged']:.0f} % of the touching pairs whose contact the image hides "
        f"({100 * contacts['hidden']:.0f} % of {contacts['n']}) and {100 * contacts['shown_merged']:.0f} % of those "
        "it shows"
    )


def log_summary(check: Mapping) -> None:
    log.info(
        "closed-loop check on %d held-out generated pairs (%d particles): median diameter %s, mean %s, count %s, "
        "edge offset %s px, merged %s, split %s, missed %s, AP50 %s",
        check["n_pairs"],
        check["n_true"],
        _interval(check["median_error"]),
        _interval(check["mean_error"]),
        _interval(check["count_error"]),
        "n/a" if check.get("edge_offset_px") is None else f"{check['edge_offset_px']:+.2f}",
        *("n/a" if check.get(k) is None else f"{100 * check[k]:.1f} %" for k in ("merged", "split", "missed")),
        "n/a" if check.get("ap50") is None else f"{check['ap50']:.3f}",
    )
