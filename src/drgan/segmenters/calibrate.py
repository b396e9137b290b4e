"""The touching-particle split chosen per segmenter, on its own validation pairs.

``split_touching`` seeds one particle per h-maximum of the distance transform of a particle *core*: where the
particle probability exceeds ``split_core``. How strict that core should be depends on how confident the network
is: a strict core opens the necks between touching particles for a confident network and breaks a less confident
one's particles into pieces (experiments/statistics/merges.md, "The split chosen per segmenter on its validation
pairs"). So after training, ``drgan.segment`` scores a small grid of (split_seeds, split_depth, split_core) on the
held-out validation pairs (never test images), keeps the setting its objective chooses (``sizes``: the sizes and
counts nearest the truth within ``SIZES_AP50_MARGIN`` of the best AP50; ``ap50``: the best pooled AP50) and stores it
in the checkpoint under ``CHECKPOINT_KEY``; the ``auto`` split settings of evaluate and analyze read it back.

Settings within ``TIE`` of the best AP50 are ties: on particles of ``LARGE_PARTICLE_PX`` and more (median over the
validation pairs) the largest tied depth wins, else the smallest; then the most lenient core of that depth.

Validation instances are the 4-connected components of each pair's particle class (the contour class separates
touching particles in the targets), compared with the particle-class components of the split's class map, the way
``drgan.evaluate`` scores a class map.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence

import numpy as np

from drgan.core.checkpoint_io import positive_entry
from drgan.core.errors import ConfigError
from drgan.core.progress import track
from drgan.metrics.statistics import SPECK_PX, median_diameter

log = logging.getLogger(__name__)

CHECKPOINT_KEY = "drgan_split"
# the defaults of evaluate/analyze for a checkpoint that has no calibration (chosen on TiO2 SEM train images)
SEEDED = ("centres", "star")  # splits seeded at a level of a predicted map (seed_level), not at a split depth
UNCALIBRATED = {"split_depth": 1.0, "split_core": 0.95, "seed_level": 0.5, "split_seeds": "hmaxima"}
GRID_DEFAULTS = {
    "objective": "sizes",  # sizes: the nearest sizes and counts within 0.05 AP50 (sizes_best); ap50: the highest AP50
    "seeds": ["hmaxima", "components"],  # inference.split_seeds (drgan.segmenters.inference.SEED_RULES); ties: first
    "cores": [None, 0.5, 0.7, 0.8, 0.9, 0.95, 0.98],
    "depths": [1.0, 2.0, 4.0, 8.0, 16.0],  # px; the larger ones for particles of 100 px and more
    "levels": [0.3, 0.4, 0.5, 0.6, 0.7],  # the instance-aware segmenter's seed levels (drgan.segmenters.instances)
    "max_pairs": 100,
}
TIE = 0.002  # AP50 differences below this are ties, broken by the particles' size (tied_best)
SIZES_AP50_MARGIN = 0.05  # objective sizes: the split may give up this much validation AP50 for exact sizes
# Median diameter (px) of the validation pairs' particles from which a tie between split depths goes to the larger
# depth: large particles have rough or faceted outlines that a shallow split cuts into fragments, small ones touch
# and a deep split merges them (ties scored both ways on annotated train ids: experiments/pipeline/README.md, "Tied
# split depths").
LARGE_PARTICLE_PX = 40.0
# Image px per real px of the pairs a segmenter learned from (a generated set's manifest pixel_scale: below 1 when
# the GAN saw large particles in windows wider than its render); inference resamples real images by it.
PIXEL_SCALE_KEY = "drgan_pixel_scale"
# Area-weighted median diameter (px, at the network's scale; drgan.metrics.statistics.area_median) of the particles
# of the pairs a segmenter learned from: inference with pixel_scale=per_image resamples each image so that its
# particles' own span it (drgan.segmenters.inference).
WORKING_DIAMETER_KEY = "drgan_working_diameter"


def check_grid(grid: Mapping | None, name: str = "split_calibration") -> dict | None:
    """The `split_calibration` block as numbers (None: calibration off); a ConfigError names a bad entry."""
    if grid is None:
        return None
    unknown = set(grid) - set(GRID_DEFAULTS)
    if unknown:
        raise ConfigError(f"{name}: unknown key(s) {sorted(unknown)}; expected {sorted(GRID_DEFAULTS)}")
    settings = {**GRID_DEFAULTS, **dict(grid)}
    cores, depths = list(settings["cores"] or []), list(settings["depths"] or [])
    levels = list(settings["levels"] or [])
    seeds = list(settings["seeds"] or [])
    objective = settings["objective"]
    if objective not in ("ap50", "sizes"):
        raise ConfigError(f"{name}.objective: {objective!r}: expected ap50 or sizes")
    from drgan.segmenters.inference import SEED_RULES

    if not seeds or any(rule not in SEED_RULES for rule in seeds):
        raise ConfigError(f"{name}.seeds: {seeds!r}: expected one or more of {list(SEED_RULES)}")
    if not cores or not depths or not levels:
        raise ConfigError(
            f"{name}: cores, depths and levels need at least one value each (got {cores}, {depths}, {levels})"
        )
    for level in levels:
        if isinstance(level, bool) or not (isinstance(level, (int, float)) and 0.0 < level < 1.0):
            raise ConfigError(f"{name}.levels: {level!r} is not a centre-map level in (0, 1)")
    for core in cores:
        if core is not None and not (isinstance(core, (int, float)) and 0.0 < core < 1.0):
            raise ConfigError(f"{name}.cores: {core!r} is not a particle probability in (0, 1) or null (the argmax)")
    for depth in depths:
        if not (isinstance(depth, (int, float)) and depth > 0):
            raise ConfigError(f"{name}.depths: {depth!r} is not a positive depth in px")
    max_pairs = settings["max_pairs"]
    if not (isinstance(max_pairs, int) and max_pairs >= 1):
        raise ConfigError(f"{name}.max_pairs: {max_pairs!r} is not a positive integer")
    return {
        "cores": [None if c is None else float(c) for c in cores],
        "depths": [float(d) for d in depths],
        "levels": [float(v) for v in levels],
        "seeds": [str(rule) for rule in seeds],
        "objective": objective,
        "max_pairs": max_pairs,
    }


def calibrate_split(
    model, pairs: Sequence, grid: Mapping | None = None, split_smooth: float = 1.0, progress: bool = False, **predict_kw
) -> dict:
    """Score every (depth, core) of ``grid`` on ``pairs`` (images with their class masks), or every seed level for
    the instance-aware segmenter (its split "centres"); return the best setting with its pooled AP50 and the whole
    table. The network runs once per pair; only the split is repeated."""
    from drgan.metrics.instance_scores import binarize_and_label, match_instances
    from drgan.segmenters.inference import predict_probs, split_by_centres, split_of, split_touching

    settings = check_grid(grid if grid is not None else {})
    if not pairs:
        raise ValueError("calibrate_split: no validation pairs")
    chosen = list(pairs)[: settings["max_pairs"]]
    iterator = track(chosen, "split calibration: predicting", unit="pairs") if progress else chosen
    probs, truths = [], []
    for pair in iterator:
        probs.append(predict_probs(model, pair.image, **predict_kw))
        truths.append(np.asarray(pair.instances()).astype(np.int64))  # exact labels where known, as evaluate scores
    own = split_of(model)
    centres = own in SEEDED
    if centres:
        from drgan.segmenters.inference import split_by_stars

        seeded = split_by_stars if own == "star" else split_by_centres
        candidates = [({"seed_level": level}, lambda p, v=level: seeded(p, v)) for level in settings["levels"]]
    else:
        candidates = [
            (
                {"split_seeds": rule, "split_depth": depth, "split_core": core},
                lambda p, d=depth, c=core, r=rule: split_touching(p, d, split_smooth, c, r),
            )
            for rule in settings["seeds"]
            for depth in settings["depths"]
            for core in settings["cores"]
        ]
    from drgan.metrics.statistics import compare_sizes, particles

    true_particles = [particles(truth).at_least(SPECK_PX) for truth in truths]
    table = []
    for setting, split in track(candidates, "split calibration: scoring", unit="settings") if progress else candidates:
        tp = fp = fn = 0
        found = []
        for p, truth in zip(probs, truths):
            labels = binarize_and_label(split(p))
            match = match_instances(labels, truth)
            tp, fp, fn = tp + match.tp, fp + match.fp, fn + match.fn
            found.append(particles(labels).at_least(SPECK_PX))
        ap50 = tp / (tp + fp + fn) if tp + fp + fn else math.nan
        sizes = compare_sizes(found, true_particles, n_boot=0)  # as drgan.evaluate measures them
        # None, not nan, where unknown: the table goes to JSON and checkpoints
        errors = {key: sizes[key]["value"] for key in ("median_error", "count_error")}
        errors = {key: float(value) if math.isfinite(value) else None for key, value in errors.items()}
        table.append({**setting, "ap50": ap50, "tp": tp, "fp": fp, "fn": fn, **errors})
    scored = [row for row in table if not math.isnan(row["ap50"])]
    if not scored:
        raise ValueError("calibrate_split: the validation pairs hold no particles and no prediction found any")
    particle_px = median_diameter(truths)
    best = sizes_best(scored, particle_px) if settings["objective"] == "sizes" else tied_best(scored, particle_px)
    chosen_setting = {"split": own, "seed_level": best["seed_level"]} if centres else {"split": "watershed"}
    return {
        **chosen_setting,
        "split_depth": best.get("split_depth", UNCALIBRATED["split_depth"]),
        "split_core": best.get("split_core", UNCALIBRATED["split_core"]),
        "split_seeds": best.get("split_seeds", UNCALIBRATED["split_seeds"]),
        "split_smooth": float(split_smooth),
        "ap50": best["ap50"],
        "median_error": best.get("median_error"),
        "count_error": best.get("count_error"),
        "objective": settings["objective"],
        "n_pairs": len(chosen),
        "particle_px": particle_px,
        "table": table,
    }


def size_error(row: Mapping) -> float:
    """|median diameter error| + |count error| of a calibration row (inf where either is unknown)."""
    median, count = row.get("median_error"), row.get("count_error")
    return math.inf if median is None or count is None else abs(median) + abs(count)


def sizes_best(rows: Sequence[Mapping], particle_px: float) -> Mapping:
    """The calibration row of ``objective: sizes``: among the rows within ``SIZES_AP50_MARGIN`` of the best AP50 (the
    detection kept), the one whose sizes and counts are nearest the truth (`size_error`; ties: `tied_best`'s order)."""
    top = max(row["ap50"] for row in rows)
    near = [row for row in rows if row["ap50"] >= top - SIZES_AP50_MARGIN]
    least = min(size_error(row) for row in near)
    if not math.isfinite(least):
        return tied_best(rows, particle_px)
    return tied_best([row for row in near if size_error(row) <= least + 1e-9], particle_px)


def tied_best(rows: Sequence[Mapping], particle_px: float) -> Mapping:
    """The calibration table's chosen row: among the rows within ``TIE`` of the best AP50 (in grid order), the
    largest split depth's first row when the particles are ``LARGE_PARTICLE_PX`` or more across, else the first.
    Rows without a depth (the instance-aware segmenter's seed levels) keep the first."""
    top = max(row["ap50"] for row in rows)
    tied = [row for row in rows if row["ap50"] >= top - TIE]
    if particle_px >= LARGE_PARTICLE_PX and "split_depth" in tied[0]:
        deepest = max(row["split_depth"] for row in tied)
        return next(row for row in tied if row["split_depth"] == deepest)
    return tied[0]


# The size-first choice stands unless its particle count on the user's own images (the agreement check's, up to 8 the
# profile segmented) falls more than this below the classical segmentation's count there; the setting within the AP50
# margin nearest that count is taken then: generated validation pairs can rank the splits by size the other way from
# the real images, choosing a split that merges on them. One-sided, since the classical watershed merges far more
# often than it splits (on packed spheres a right segmenter counts well above it). Measured:
# experiments/statistics/chain.md, "The closed loop over the sets, three seeds".
REAL_COUNT_GUARD = 0.10
# Above, a choice stands up to this many times the classical count: right splits of packed or merged-by-the-classical
# particles counted up to +91 % over it in every recorded run; the two that counted more (+150 %, +177 %) cut real
# particles into pieces. Beyond it the setting within the margin that counts the most particles under the ceiling is
# taken (the least move that meets it). Measured: experiments/statistics/closed_loop.md, "The real-count guard's
# upper side".
REAL_COUNT_CEILING = 2.0


def _count(labels: np.ndarray) -> int:
    """Particles of an instance label image, specks under SPECK_PX left out."""
    return int((np.bincount(np.asarray(labels, np.int64).ravel())[1:] >= SPECK_PX).sum())


def real_count_guard(model, calibration: dict, items: Sequence[tuple[object, np.ndarray]]) -> dict:
    """``calibration`` (a watershed one, `calibrate_split`'s) checked on the user's images: ``items`` are (image item,
    classical instance labels) pairs (drgan.segmenters.agreement.read_reference). The network (``model`` as
    drgan.segmenters.registry.load_segmenter returns it, with its checkpoint's pixel scale and noise level) runs once
    per image as evaluate and analyze predict; each setting within the objective's AP50
    margin splits it, and the particles (specks left out, figure annotations dropped) are counted against the
    classical ones. Returns the calibration with ``real_count`` (the counts, every setting's and the decision) and,
    where the chosen count falls more than REAL_COUNT_GUARD below the classical count (the split merges what even
    the classical segmentation separates), the setting nearest that count instead; where it exceeds
    REAL_COUNT_CEILING times the classical count (the split cuts real particles into pieces), the setting that counts
    the most particles under that ceiling."""
    from drgan.metrics.instance_scores import binarize_and_label
    from drgan.segmenters.inference import (
        check_noise_match,
        filled_holes,
        probs_at_scale,
        split_touching,
        without_annotations,
    )

    if calibration.get("split") != "watershed" or not items:
        return calibration
    scale = float(getattr(model, "pixel_scale", 1.0) or 1.0)
    level = check_noise_match(getattr(model, "train_noise", None))
    smooth = calibration.get("split_smooth", 1.0)
    predicted = [(item.image, probs_at_scale(model.eval(), item.image, scale, level)) for item, _ in items]
    classical = sum(_count(labels) for _, labels in items)
    if classical == 0:
        return calibration
    keys = ("split_seeds", "split_depth", "split_core")
    top = max(row["ap50"] for row in calibration["table"] if not math.isnan(row["ap50"]))
    margin = SIZES_AP50_MARGIN if calibration.get("objective") == "sizes" else TIE
    rows = [row for row in calibration["table"] if not math.isnan(row["ap50"]) and row["ap50"] >= top - margin]
    counts = []
    for row in rows:
        n = 0
        for image, probs in predicted:
            classes = split_touching(probs[:3], row["split_depth"] / scale, smooth / scale, row["split_core"],
                                     row["split_seeds"])  # fmt: skip
            n += _count(binarize_and_label(without_annotations(filled_holes(classes), image).astype(np.int64)))
        counts.append(n)
    chosen = next(k for k, row in enumerate(rows) if all(row[key] == calibration[key] for key in keys))
    off = [abs(n / classical - 1.0) for n in counts]
    ceiling = REAL_COUNT_CEILING * classical
    if counts[chosen] < (1.0 - REAL_COUNT_GUARD) * classical:  # merges: the classical count is a floor
        side = "below"
        pick = min(range(len(rows)), key=lambda k: (off[k], k != chosen))
    elif counts[chosen] > ceiling:  # cuts particles apart: the least move under the ceiling
        side = "above"
        under = [k for k in range(len(rows)) if counts[k] <= ceiling]
        pick = max(under, key=lambda k: (counts[k], -k)) if under else chosen
    else:
        side, pick = None, chosen
    moved = pick != chosen and off[pick] < off[chosen]
    if not moved:
        pick = chosen
    guard = {
        "images": len(items),
        "classical": classical,
        "chosen_count": counts[chosen],
        "count": counts[pick],
        "moved": moved,
        "side": side,
        "ceiling": ceiling,
        "from": {key: calibration[key] for key in keys},
        "counts": [{**{key: row[key] for key in keys}, "count": n} for row, n in zip(rows, counts)],
    }
    result = {**calibration, "real_count": guard}
    if moved:
        result.update({key: rows[pick][key] for key in (*keys, "ap50", "median_error", "count_error")})
    return result


def stored_pixel_scale(checkpoint: Mapping, source: str = "checkpoint") -> float:
    """The pixel scale a checkpoint holds (``PIXEL_SCALE_KEY``); 1.0 when it holds none (checkpoints from before it
    was stored, real-trained ones) or a malformed one (with a warning: the checkpoint still loads)."""
    scale = positive_entry(checkpoint, PIXEL_SCALE_KEY)
    if scale is None and checkpoint.get(PIXEL_SCALE_KEY) is not None:
        log.warning(
            "%s: its %s entry %r is not a pixel scale; 1.0 used", source, PIXEL_SCALE_KEY, checkpoint[PIXEL_SCALE_KEY]
        )
    return 1.0 if scale is None else scale


def stored_working_diameter(checkpoint: Mapping) -> float | None:
    """The training pairs' area-weighted median particle diameter a checkpoint holds (``WORKING_DIAMETER_KEY``, px
    at the network's scale), or None (checkpoints from before it was stored, or a malformed entry)."""
    return positive_entry(checkpoint, WORKING_DIAMETER_KEY)


def stored_split(checkpoint: Mapping, source: str = "checkpoint") -> dict | None:
    """The calibration a checkpoint holds (``CHECKPOINT_KEY``), or None; a malformed entry is ignored with a
    warning (the checkpoint still loads)."""
    from drgan.segmenters.inference import SEED_RULES

    entry = checkpoint.get(CHECKPOINT_KEY)
    if entry is None:
        return None
    ok = (
        isinstance(entry, Mapping)
        and isinstance(entry.get("split_depth"), (int, float))
        and entry["split_depth"] > 0
        and (
            entry.get("split_core") is None or (isinstance(entry["split_core"], float) and 0 < entry["split_core"] < 1)
        )
    )
    level = entry.get("seed_level") if isinstance(entry, Mapping) else None
    if level is not None and not (isinstance(level, float) and 0 < level < 1):
        ok = False
    if ok and entry.get("split_seeds", "hmaxima") not in SEED_RULES:
        ok = False
    if not ok:
        log.warning("%s: its %s entry is not a split calibration; ignored", source, CHECKPOINT_KEY)
        return None
    return dict(entry)


def resolve_auto(inference: Mapping, calibration: Mapping | None, source: str = "model") -> tuple[dict, str]:
    """``inference`` with every ``auto`` split setting replaced: the checkpoint's calibration, else ``UNCALIBRATED``
    (with a warning). Returns the settings and a note for reports ("" when nothing was auto)."""
    settings = dict(inference)
    auto = [key for key in UNCALIBRATED if settings.get(key) == "auto"]
    if not auto:
        return settings, ""
    if calibration is not None:
        for key in auto:
            settings[key] = calibration.get(key, UNCALIBRATED[key])
        return settings, f"calibrated on {calibration.get('n_pairs', '?')} validation pairs"
    log.warning(
        "%s: inference %s=auto but the checkpoint holds no split calibration (trained before drgan.segment chose "
        "one, or without validation pairs); using %s. Resume its training (`python -m drgan.segment ... "
        "ckpt_path=last`) to calibrate it",
        source,
        "/".join(auto),
        ", ".join(f"{key} {UNCALIBRATED[key]}" for key in auto),
    )
    for key in auto:
        settings[key] = UNCALIBRATED[key]
    return settings, "uncalibrated defaults"


def markdown_table(calibration: Mapping) -> str:
    """The calibration grid as a markdown table (depth rows, core columns, AP50; a seed level row for the
    instance-aware segmenter)."""
    rows = calibration["table"]
    if calibration.get("split") in SEEDED:
        levels = [row["seed_level"] for row in rows]
        cells = [
            f"**{row['ap50']:.3f}**" if row["seed_level"] == calibration["seed_level"] else f"{row['ap50']:.3f}"
            for row in rows
        ]
        return "\n".join(
            ["| seed level | " + " | ".join(f"{v:g}" for v in levels) + " |", "|" + "---|" * (len(levels) + 1),
             "| AP50 | " + " | ".join(cells) + " |"]
        )  # fmt: skip
    cores = list(dict.fromkeys(row["split_core"] for row in rows))
    depths = list(dict.fromkeys(row["split_depth"] for row in rows))
    rules = list(dict.fromkeys(row.get("split_seeds", "hmaxima") for row in rows))
    chosen_rule = calibration.get("split_seeds", "hmaxima")
    head = "| seeds, depth \\ core | " + " | ".join("argmax" if c is None else f"{c:g}" for c in cores) + " |"
    lines = [head, "|" + "---|" * (len(cores) + 1)]
    for rule in rules:
        for depth in depths:
            cells = []
            for core in cores:
                row = next(
                    r for r in rows
                    if r["split_depth"] == depth and r["split_core"] == core and r.get("split_seeds", "hmaxima") == rule
                )  # fmt: skip
                chosen = (
                    depth == calibration["split_depth"] and core == calibration["split_core"] and rule == chosen_rule
                )
                cells.append(f"**{row['ap50']:.3f}**" if chosen else f"{row['ap50']:.3f}")
            lines.append(f"| {rule}, {depth:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def as_array_free(calibration: Mapping) -> dict:
    """Plain Python numbers only (a checkpoint read with weights_only=True accepts these)."""

    def plain(value):
        if isinstance(value, (np.floating, np.integer)):
            return value.item()
        if isinstance(value, Mapping):
            return {str(k): plain(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        return value

    return plain(calibration)
