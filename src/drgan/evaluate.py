"""`python -m drgan.evaluate model=A.ckpt data=DATASET out=DIR`: score segmenters on real test images.

Several runs (seeds): ``models=[A.ckpt,B.ckpt,...]``, each scored, then mean +- std over them. A run is a
segmenter checkpoint or a folder of predicted masks, e.g. nnU-Net's output folder (``model=PRED_DIR``: one
``<id>.png`` per test id, values 0 background, 1 particle, 2 contour); drgan.segmenters.predictors turns either
into class maps, and a folder is checked against every test image (missing, extra, size, values) first.

Per test image: the run's class map (a checkpoint: sliding-window prediction, touching particles split,
``inference.split``, see drgan.segmenters.inference) -> particle class only (contour and background are both "not
particle", so the contour separates touching particles) -> 4-connected components -> scores against the
4-connected components of the true binary mask (drgan.metrics.instance_scores):
- DSC: Dice of particle pixels;
- AP50: TP / (TP + FP + FN) with a match at IoU > 0.5 (the paper's single-threshold "AP", as in the Data
  Science Bowl 2018 / StarDist accuracy; no precision-recall curve);
- PQ = SQ * RQ of the particle class (the standard, things-only PQ);
- PQ classes: PQ averaged over background (a stuff class: one segment, PQ = its IoU when > 0.5, else 0) and
  particle; PQ semantic: the same with particle also a stuff class (pixel IoU, instances ignored), the only
  one of the three that can reach the DiffRenderGAN paper's PQ at its AP50 (drgan.metrics.instance_scores).
Test-set value of a run = the mean over its test images (every image weighs the same, whatever its particle
count). Over several runs (one checkpoint each): mean +- sample std (ddof = 1) of the runs' test-set values.

Writes results.csv (one row per run and image, plus per-run "mean" rows), results.md (per-image table as
mean +- std over runs, and the per-run and overall summary) and overlays/ID.png (first model's prediction:
true positive instances green, false positives red, missed true instances yellow, over the grey image), with that
prediction's particles as labels/ID.tif and rois/ID.zip for Fiji and napari (drgan.data.imagej).

Particle statistics (``statistics: true``; drgan.metrics.statistics): per run, the predicted particles' median and
mean equivalent diameter against the masks' (relative errors), the total count's error and the per-image count
errors, the Kolmogorov-Smirnov and first Wasserstein distances between the two diameter distributions, each with a
bootstrap interval over images (``bootstrap`` resamples); particles cut by the image border count but are left out
of sizes, on both sides. statistics.md, statistics.csv and sizes.png (histograms and cumulative curves of the
diameters, masks and every run overlaid). statistics.md also says where each run loses particles: the share of true
particles matched, merged with a neighbour, split, missed or badly outlined, the false particles, and the median
boundary offset of matched particles (drgan.metrics.instance_scores.error_sources), which is what to fix first.
All inputs (checkpoints, predicted mask folders, images, masks, split) are read and checked before any prediction.
"""

from __future__ import annotations

import csv
import io
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig

from drgan.core.errors import ConfigError, pixel_size
from drgan.core.io import write_bytes, write_json, write_with
from drgan.core.progress import track
from drgan.core.typed_settings import given, read_settings, setting, typed
from drgan.data.imagej import write_outlines
from drgan.launch.runtime import stage_main, start
from drgan.metrics.instance_scores import (
    ERROR_SOURCES,
    binarize_and_label,
    error_sources,
    segmentation_scores,
)
from drgan.metrics.overlays import overlay
from drgan.metrics.statistics import SPECK_PX, compare_sizes, count_errors, interval_text, particles, pooled
from drgan.segmenters.classical_check import check_reported, reported_particles

log = logging.getLogger(__name__)

SCORES = ("dsc", "ap50", "pq", "sq", "rq", "pq_classes", "pq_semantic")
HEADERS = {"pq_classes": "PQ classes", "pq_semantic": "PQ semantic"}  # markdown column names; others upper-case
COUNTS = ("tp", "fp", "fn")


def score_image(class_map: np.ndarray, true_labels: np.ndarray) -> tuple[dict, np.ndarray]:
    pred_labels = binarize_and_label(class_map.astype(np.int64), particle_class=1)
    return segmentation_scores(pred_labels, true_labels), pred_labels


def _header(score: str) -> str:
    return HEADERS.get(score, score.upper())


def _mean_std(values) -> tuple[float, float]:
    v = np.asarray(values, dtype=np.float64)
    return float(v.mean()), float(v.std(ddof=1)) if len(v) > 1 else 0.0


def tables(rows: list[dict], runs: list[str], ids: list[str], inference: str = "") -> tuple[str, str]:
    """(csv text, markdown text) of per-(run, image) rows; adds per-run mean rows to the CSV.
    inference: a line saying how class maps were made (shown in the markdown)."""
    fields = ["run", "model", "image", *SCORES, *COUNTS]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    run_means = {}
    for run in runs:
        mine = [r for r in rows if r["run"] == run]
        for r in mine:
            writer.writerow({k: (f"{r[k]:.6f}" if k in SCORES else r[k]) for k in fields})
        run_means[run] = {k: float(np.mean([r[k] for r in mine])) for k in SCORES}
        writer.writerow(
            {
                "run": run,
                "model": mine[0]["model"],
                "image": "mean",
                **{k: f"{run_means[run][k]:.6f}" for k in SCORES},
                **{k: sum(r[k] for r in mine) for k in COUNTS},
            }
        )

    md = [
        "# Segmentation on real test images",
        "",
        f"{len(ids)} test image(s), {len(runs)} run(s). Particle class only (contour = background), 4-connected instances, "
        "match at IoU > 0.5. AP50 = TP / (TP + FP + FN); PQ = SQ x RQ (particle class). PQ classes = mean PQ of "
        "background (stuff) and particle (things); PQ semantic = mean over background and particle both as stuff "
        "(IoU when > 0.5, else 0). A run's test-set value is the mean over its "
        "images; values below are mean +- sample std over runs." + (f" Inference: {inference}." if inference else ""),
        "",
        "## Test set",
        "",
        "| | " + " | ".join(_header(s) for s in SCORES) + " |",
        "|---|" + "---|" * len(SCORES),
    ]
    overall = {k: _mean_std([run_means[r][k] for r in runs]) for k in SCORES}
    md.append("| **all runs** | " + " | ".join(f"{m:.3f} +- {s:.3f}" for m, s in overall.values()) + " |")
    for run in runs:
        md.append(f"| {run} | " + " | ".join(f"{run_means[run][k]:.3f}" for k in SCORES) + " |")
    md += [
        "",
        "## Per image",
        "",
        "| image | " + " | ".join(_header(s) for s in SCORES) + " | TP | FP | FN |",
        "|---|" + "---|" * (len(SCORES) + 3),
    ]
    for i in ids:
        mine = [r for r in rows if r["image"] == i]
        cells = [f"{m:.3f} +- {s:.3f}" for m, s in (_mean_std([r[k] for r in mine]) for k in SCORES)]
        counts = [f"{np.mean([r[k] for r in mine]):.1f}" for k in COUNTS]
        md.append(f"| {i} | " + " | ".join(cells + counts) + " |")
    md += ["", "Runs: " + ", ".join(f"{r} = `{[x['model'] for x in rows if x['run'] == r][0]}`" for r in runs), ""]
    return buf.getvalue(), "\n".join(md)


NO_MODELS = (
    "evaluate: give model=CHECKPOINT (or a folder of predicted masks, one <id>.png per test image) "
    "or models=[A,B,...] (one per run)"
)


def statistics_min_area(stage: str, value) -> float:
    """``min_area_px`` (px^2, >= 0; null: 0): components below it are specks in the statistics, on both sides."""
    try:
        area = float(0 if value is None else value)
    except (TypeError, ValueError):
        area = -1.0
    if not area >= 0:
        raise ConfigError(f"{stage}: min_area_px={value!r}: expected an area in px^2 >= 0 (0: keep every component)")
    return area


@typed
@dataclass(frozen=True)
class EvaluateSettings:
    """Every key of conf/segmentation/evaluate.yaml with its type, its default and its check (`from_config`, before
    any checkpoint or image is read). The YAML stays the user's reference; the field defaults are the same values
    (tests/test_analyze.py composes evaluate.yaml and compares). A new key is a field here (+ its YAML line)."""

    data: Path
    out: Path
    models: tuple[str, ...] = ()  # ``model`` then ``models``: checkpoints or folders of predicted masks, one per run
    split: str | None = None  # split file; None: <data>/split.json
    subset: str = "test"
    crop_rows: Any = "auto"
    masks: str = "masks"
    mask_suffix: str = "auto"
    overlays: bool = True
    statistics: bool = True
    bootstrap: int = setting(1000, ge=0, expected="a number of resamples >= 0 (0: no intervals)")
    seed: int = 0
    nm_per_px: float | None = setting(None, check=pixel_size)
    min_area_px: float = setting(SPECK_PX, check=statistics_min_area)
    overlay_alpha: float = 0.5
    reported: Path | None = setting(None, check=lambda stage, value: check_reported(value) if value else None)  # an
    # analyze run of these images: the sizes it reported, scored as run "reported"
    inference: dict = field(default_factory=dict)  # checkpoints only

    @classmethod
    def from_config(cls, cfg: DictConfig, need_models: bool = True) -> EvaluateSettings:
        """From the composed config; ``need_models``: a run without model(s) is refused (evaluate given its
        predictors directly, as tests do, needs none)."""
        from drgan.segmenters.pairs import REAL_DATASET, check_dataset_folder

        data = given(
            cfg, "data", "evaluate: give data=DATASET (a real dataset folder with images/, masks/, split.json)"
        )
        data_dir = check_dataset_folder(data, "data", REAL_DATASET)  # before any checkpoint is read
        return read_settings(cls, cfg, "evaluate", data=data_dir, models=tuple(model_sources(cfg, need_models)))


def model_sources(cfg: DictConfig, need_models: bool = True) -> list[str]:
    """The runs to score: ``model=`` (one) and ``models=[A,B,...]`` (several), in that order; each a segmenter
    checkpoint or a folder of predicted masks (none: a ConfigError where ``need_models``)."""
    runs = read_settings(_Runs, cfg, "evaluate")
    models = [runs.model, *runs.models] if runs.model else list(runs.models)
    if not models and need_models:
        raise ConfigError(NO_MODELS)
    return models


@typed
@dataclass(frozen=True)
class _Runs:
    model: str | None = None
    models: tuple[str, ...] = setting((), expected="a list, e.g. models=[a.ckpt,b.ckpt]")


def _inference_line(predictors: dict) -> str:
    """How the class maps were made: one line for all runs when they agree, else one per run."""
    hows = {run: p.how for run, p in predictors.items() if p.how}
    distinct = list(dict.fromkeys(hows.values()))
    if len(distinct) == 1 and len(hows) == len(predictors):
        return distinct[0]
    return "; ".join(f"{run}: {how}" for run, how in hows.items())


def evaluate(settings: EvaluateSettings, predictors: dict | None = None) -> dict:
    """Score every run on the test ids; returns {"runs": {run: {score: value}}, "mean": {...}, "std": {...}}.

    predictors: optional {run name: Predictor, or f(image) -> class map} instead of the settings' models (tests)."""
    from drgan.segmenters.pairs import load_real_items, real_ids

    s = settings
    predictors = _predictors(s, predictors)
    ids = real_ids(s.data, s.split, s.subset, setting="data")
    samples = load_real_items(s.data, ids, s.crop_rows, s.mask_suffix, s.masks)  # every image/mask read and checked
    for predictor in predictors.values():
        predictor.check([item for item, _ in samples])  # a mask folder: every mask read and compared with its image
    rows, found, sources = score_runs(s, predictors, samples)
    result = write_scores(s.out, rows, ids, predictors)
    if s.statistics:
        truth = [particles(true_labels) for _, true_labels in samples]
        reported = (
            reported_particles(s.reported, [item.id for item, _ in samples], s.data / "images") if s.reported else None
        )
        if reported:  # the sizes the user's report gives for these images, scored as a run of their own
            found[REPORTED] = reported.particles
            write_json(s.out / "reported.json", {"analyze": str(s.reported), "table": reported.table,
                                                 "trusted": reported.trusted})  # fmt: skip
        else:
            (s.out / "reported.json").unlink(missing_ok=True)
        result["statistics"] = particle_statistics(s, s.out, found, truth, ids, sources, reported)
    return result


def _predictors(s: EvaluateSettings, given: dict | None) -> dict:
    """{run: Predictor}: ``given`` (tests) as predictors, else the settings' models loaded (run0, run1, ...)."""
    from drgan.segmenters.predictors import as_predictor, load_predictor

    if given is not None:
        return {run: as_predictor(p, run) for run, p in given.items()}
    if not s.models:
        raise ConfigError(NO_MODELS)
    return {f"run{k}": load_predictor(m, s.inference) for k, m in enumerate(s.models)}


def score_runs(s: EvaluateSettings, predictors: dict, samples: list) -> tuple[list[dict], dict, dict]:
    """(a row of scores per run and image, {run: each image's particles}, {run: each image's error sources}); the
    first run's overlays and outlines written per image."""
    rows = []
    found: dict[str, list] = {run: [] for run in predictors}
    sources: dict[str, list] = {run: [] for run in predictors}
    for k, (run, predictor) in enumerate(predictors.items()):
        for item, true_labels in track(samples, f"scoring {run}", unit="images"):
            image_id, image = item.id, item.image
            class_map = np.asarray(predictor(item))
            if class_map.shape != image.shape:
                raise ConfigError(
                    f"evaluate: {run} returned a class map of shape {class_map.shape} for image {image_id} {image.shape}"
                )
            scores, pred_labels = score_image(class_map, true_labels)
            found[run].append(particles(pred_labels))
            sources[run].append(error_sources(pred_labels, true_labels))
            rows.append({"run": run, "model": predictor.source, "image": image_id, **scores})
            log.info("%s %s: %s", run, image_id, {s: round(scores[s], 3) for s in SCORES})
            if k == 0 and s.overlays:
                from PIL import Image

                rgb = overlay(image, pred_labels, true_labels, s.overlay_alpha)
                write_with(
                    s.out / "overlays" / f"{image_id}.png",
                    lambda f, rgb=rgb: Image.fromarray(rgb).save(f, format="PNG"),
                )
                write_outlines(s.out, image_id, pred_labels)  # for Fiji and napari
    return rows, found, sources


def write_scores(out: Path, rows: list[dict], ids: list[str], predictors: dict) -> dict:
    """results.csv and results.md of the rows; {"runs": per-run means, "rows", "mean", "std" over the runs}."""
    runs = list(predictors)
    csv_text, md_text = tables(rows, runs, ids, _inference_line(predictors))
    write_bytes(out / "results.csv", csv_text.encode())
    write_bytes(out / "results.md", md_text.encode())
    per_run = {r: {s: float(np.mean([x[s] for x in rows if x["run"] == r])) for s in SCORES} for r in runs}
    stats = {s: _mean_std([per_run[r][s] for r in runs]) for s in SCORES}
    log.info("wrote %s: %s", out / "results.md", {s: f"{m:.3f} +- {sd:.3f}" for s, (m, sd) in stats.items()})
    return {
        "runs": per_run,
        "rows": rows,
        "mean": {s: v[0] for s, v in stats.items()},
        "std": {s: v[1] for s, v in stats.items()},
    }


def summed_sources(per_image: list[dict]) -> dict:
    """One run's error_sources over its images: counts summed, and the median boundary offset (px) of all matched
    particles pooled."""
    total = {key: sum(int(s[key]) for s in per_image) for key in ("n_true", "n_pred", *ERROR_SOURCES, "false")}
    offsets = np.concatenate([s["diameter_offset"] for s in per_image] or [np.zeros(0)])
    total["diameter_offset"] = float(np.median(offsets)) if len(offsets) else float("nan")
    return total


REPORTED = "reported"  # the run name of the sizes an analyze run reported (``reported=``)


def particle_statistics(
    s: EvaluateSettings,
    out: Path,
    found: dict,
    truth: list,
    ids: list[str],
    sources: dict | None = None,
    reported=None,
) -> dict:
    """Each run's particle statistics against the masks' (drgan.metrics.statistics); writes statistics.md,
    statistics.csv and sizes.png. Returns {run: {statistic: {value, low, high}}, plus "count_errors": [...] and,
    with ``sources`` (per run, error_sources of each image), "sources": summed_sources}. ``reported``: what the run
    named REPORTED holds (classical_check.Reported: an analyze run's table, its specks already left out)."""
    n_boot, seed, nm, min_area = s.bootstrap, s.seed, s.nm_per_px, s.min_area_px
    truth = [t.at_least(min_area) for t in truth]
    found = {run: mine if run == REPORTED else [p.at_least(min_area) for p in mine] for run, mine in found.items()}
    result = {}
    for run, mine in found.items():
        result[run] = compare_sizes(mine, truth, n_boot=n_boot, seed=seed)
        result[run]["count_errors"] = count_errors(mine, truth).tolist()
        if sources and run in sources:
            result[run]["sources"] = summed_sources(sources[run])
    write_bytes(out / "statistics.csv", statistics_csv(result).encode())
    write_bytes(out / "statistics.md", statistics_markdown(result, truth, ids, nm, n_boot, reported).encode())
    write_bytes(out / "sizes.png", size_figure(found, truth, nm))
    for run, values in result.items():
        log.info(
            "%s: median diameter %+.1f %%, count %+.1f %%, KS %.3f, W1 %.2f px",
            run,
            100 * values["median_error"]["value"],
            100 * values["count_error"]["value"],
            values["ks"]["value"],
            values["w1"]["value"],
        )
    return result


def statistics_csv(result: dict) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["run", "statistic", "value", "low", "high"])
    for run, values in result.items():
        for key, cell in values.items():
            if isinstance(cell, dict) and "value" in cell:
                writer.writerow([run, key, *(f"{cell[k]:.6g}" for k in ("value", "low", "high"))])
        for key, count in values.get("sources", {}).items():  # where particles are lost: counts, offset in px
            writer.writerow([run, f"sources/{key}", f"{count:.6g}", "", ""])
    return buf.getvalue()


def statistics_markdown(result: dict, truth: list, ids: list[str], nm: float | None, n_boot: int, reported=None) -> str:
    def interval(cell: dict, scale: float = 1.0, fmt: str = "{:.3f}") -> str:
        return interval_text(cell, lambda value: fmt.format(scale * value))

    unit = "nm" if nm else "px"
    scale = float(nm) if nm else 1.0
    whole = sum(t.whole().count for t in truth)
    first = next(iter(result.values()))
    md = [
        "# Particle statistics on real test images",
        "",
        f"{len(ids)} test image(s); the masks hold {sum(t.count for t in truth)} particles, {whole} of them not cut by "
        f"the image border (median equivalent diameter {scale * first['median_diameter_true']['value']:.1f} {unit}, "
        f"mean {scale * first['mean_diameter_true']['value']:.1f} {unit}). Sizes: equivalent diameter 2 sqrt(area / pi) "
        "of the particles not touching the border, on both sides; counts: all particles. Errors: prediction / masks - "
        f"1. Brackets: 95 % percentile bootstrap interval over images ({n_boot} resamples).",
        "",
        f"| run | median diameter ({unit}) | median error | mean error | count error | mean abs count error per "
        f"image | KS | W1 ({unit}) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for run, v in result.items():
        abs_count = float(np.mean(np.abs(v["count_errors"])))
        md.append(
            f"| {run} | {interval(v['median_diameter'], scale, '{:.1f}')} | {interval(v['median_error'], 100, '{:+.1f} %')} "
            f"| {interval(v['mean_error'], 100, '{:+.1f} %')} | {interval(v['count_error'], 100, '{:+.1f} %')} "
            f"| {abs_count:.1f} | {interval(v['ks'])} | {interval(v['w1'], scale, '{:.2f}')} |"
        )
    if reported:
        md += [
            "",
            f"{REPORTED}: the sizes the analyze run (reported=) gave for these images: {reported.words()}.",
        ]
    runs = {run: v for run, v in result.items() if run != REPORTED}
    if len(runs) > 1:
        keys = ("median_error", "mean_error", "count_error", "ks", "w1")
        spread = {k: _mean_std([v[k]["value"] for v in runs.values()]) for k in keys}
        md += [
            "",
            "Over runs (mean +- sample std): " + ", ".join(f"{k} {m:.3f} +- {s:.3f}" for k, (m, s) in spread.items()),
        ]
    with_sources = {run: v for run, v in result.items() if "sources" in v}
    if with_sources:
        md += [
            "",
            "## Where particles are lost",
            "",
            "Each true particle is matched (IoU > 0.5), merged (more than half of it in a prediction that also holds "
            "more than half of another), split (mostly predicted, but in pieces), missed (at most half predicted) or "
            "badly outlined (the rest); false: predictions mostly off the true particles. Boundary offset: median "
            f"predicted minus true equivalent diameter of the matched particles ({unit}).",
            "",
            f"| run | true particles | {' | '.join(ERROR_SOURCES)} | false | boundary offset ({unit}) |",
            "|---|---|" + "---|" * len(ERROR_SOURCES) + "---|---|",
        ]
        for run, v in with_sources.items():
            src = v["sources"]
            share = " | ".join(f"{100 * src[k] / max(src['n_true'], 1):.1f} %" for k in ERROR_SOURCES)
            md.append(
                f"| {run} | {src['n_true']} | {share} | {src['false']} ({100 * src['false'] / max(src['n_pred'], 1):.1f} % "
                f"of {src['n_pred']} predicted) | {scale * src['diameter_offset']:+.2f} |"
            )
    md.append("")
    return "\n".join(md)


def size_figure(found: dict, truth: list, nm: float | None) -> bytes:
    """PNG: histograms (left) and cumulative curves (right) of the whole particles' diameters, masks and runs."""
    from drgan.core.io import figure_png

    scale = float(nm) if nm else 1.0
    unit = "nm" if nm else "px"
    sets = {"masks": scale * pooled(truth), **{run: scale * pooled(mine) for run, mine in found.items()}}
    values = np.concatenate([v for v in sets.values() if len(v)] or [np.zeros(1)])
    bins = np.linspace(0.0, float(values.max()) * 1.05 + 1e-9, 30)

    def draw(plt):
        fig, (hist, cdf) = plt.subplots(1, 2, figsize=(10, 4))
        for name, v in sets.items():
            style = {"color": "black", "linewidth": 2.0} if name == "masks" else {"linewidth": 1.0}
            if len(v):
                hist.hist(v, bins=bins, histtype="step", density=True, label=f"{name} ({len(v)})", **style)
                cdf.plot(np.sort(v), np.arange(1, len(v) + 1) / len(v), label=name, **style)
        for axis, label in ((hist, "density"), (cdf, "cumulative fraction")):
            axis.set_xlabel(f"equivalent diameter ({unit})")
            axis.set_ylabel(label)
        hist.legend(fontsize=8)
        fig.suptitle("Particle sizes on the test images: masks (black) and each run")
        fig.tight_layout()
        return fig

    return figure_png(draw)


@stage_main("conf/segmentation", "evaluate")
def main(cfg: DictConfig):
    evaluate(EvaluateSettings.from_config(cfg))


if __name__ == "__main__":
    start(main)
