"""`python -m drgan.analyze model=CKPT images=DIR out=DIR`: the particle statistics a paper reports.

``model``: a segmenter checkpoint, or a folder of predicted masks named like the images (e.g. nnU-Net's output
folder; drgan.segmenters.predictors). Each image -> class map (a checkpoint: sliding windows and the segmenter's
own split of touching particles) -> particle class -> 4-connected instances, measured exactly as drgan.evaluate
measures a prediction (drgan.metrics.statistics): components under ``min_area_px`` are specks (neither counted nor
sized); particles cut by the image border are counted but not sized (a cut particle's area is not its size).

The pixel size: ``nm_per_px`` when given, else read from each image's metadata (a TIFF's microscope or resolution
tags, drgan.data.measurements.pixel_size_nm); images without one are measured in px (the log says which key to set
before anything is predicted).

Writes, in ``out``:
- particles.csv: one row per particle: id, image, area_px, equivalent_diameter_px (2 sqrt(area / pi)),
  axis_ratio, centroid_y/x, bbox (min_row, min_col, max_row, max_col; max exclusive), touches_border, sized (not cut
  by the border), and area_nm2 / equivalent_diameter_nm with a pixel size;
- statistics.md and summary.json: counts (total, per image, per area), median and mean diameter, the size
  distribution's model (normal / lognormal / two-lognormal mixture by BIC, as the profile fits it) and its
  parameters, each with a 95 % percentile bootstrap interval over images (images are the independent samples);
  with ``profile=``, the same for the profile's classical segmentation of the images beside them, and whose sizes
  drgan trusts and why (drgan.segmenters.classical_check; summary.json's ``trusted``, ``verdict``);
- particles_classical.csv (with ``profile=``): the classical particles as particles.csv, plus
  half_contrast_diameter_px (the diameter at half contrast, where the profile measured the images' mean edge), and
  their outlines in classical/ (overlays/ID.png, labels/ID.tif, rois/ID.zip, at the segmented outline);
- sizes.png: histogram of the sized particles with the fitted density, and the cumulative distribution;
  histograms.png: area and diameter histograms;
- overlays/ID.png: every image with each particle's outline (cut particles in another colour) and its id, to check
  the outlines against the image;
- statistics.html: all of it in one page that opens in any browser, offline (figures embedded, the overlays image by
  image, the particle table sortable);
- labels/ID.tif and rois/ID.zip: the particles of particles.csv for Fiji and napari, a 16-bit label image (pixel
  value = the particle's id; the pixel size in its tags, so Fiji measures in nm) and an ImageJ ROI set (one traced
  outline per particle, named by its id: File > Open, or drag onto Fiji, fills the ROI Manager) (drgan.data.imagej);
- wires=true: thickness/ID.png (local-thickness map) and thickness_histogram.png. Local thickness of a pixel =
  diameter of the largest disk inside the particle (particle + contour class) that contains the pixel (the
  `localthickness` package; its radius doubled).
"""

from __future__ import annotations

import csv
import io
import logging
import math
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from drgan.core.errors import ConfigError, pixel_size
from drgan.core.io import figure_png, write_bytes, write_json
from drgan.core.progress import track
from drgan.core.typed_settings import given, read_settings, setting, typed
from drgan.data.imagej import write_outlines
from drgan.launch.runtime import stage_main, start
from drgan.metrics.instance_scores import binarize_and_label
from drgan.metrics.statistics import SPECK_PX, Particles, bootstrap, interval_text, particles, pooled
from drgan.metrics.statistics_figures import (
    fmt,
    histograms,
    overlay_png,
    size_figure,
    thickness_histogram,
    thickness_map,
)

log = logging.getLogger(__name__)

LEVEL = 0.95  # of the bootstrap intervals
SAME_PIXEL = 0.01  # images whose metadata pixel sizes differ by less than this (relative) share one


# --- particles -----------------------------------------------------------------------------------------------


def particle_rows(
    image_id: str,
    labels: np.ndarray,
    nm_per_px: float | None = None,
    min_area_px: float = 0,
    exclude_border: bool = False,
) -> list[dict]:
    """One row per particle of an instance label image: the particles drgan.metrics.statistics counts (area >=
    ``min_area_px``), in id order; ``exclude_border`` leaves cut particles out of the rows altogether."""
    from skimage.measure import regionprops

    h, w = labels.shape
    rows = []
    for region in regionprops(labels):
        area = int(region.area)
        r0, c0, r1, c1 = region.bbox
        border = r0 == 0 or c0 == 0 or r1 == h or c1 == w
        if area < min_area_px or (exclude_border and border):
            continue
        major, minor = float(region.axis_major_length), float(region.axis_minor_length)
        row = {
            "id": int(region.label),
            "image": image_id,
            "area_px": area,
            "equivalent_diameter_px": 2.0 * np.sqrt(area / np.pi),
            "axis_ratio": major / minor if minor > 0 else math.inf,
            "centroid_y": float(region.centroid[0]),
            "centroid_x": float(region.centroid[1]),
            "bbox_min_row": r0,
            "bbox_min_col": c0,
            "bbox_max_row": r1,
            "bbox_max_col": c1,
            "touches_border": border,
            "sized": not border,
        }
        if nm_per_px:
            row["area_nm2"] = area * nm_per_px**2
            row["equivalent_diameter_nm"] = row["equivalent_diameter_px"] * nm_per_px
        rows.append(row)
    return rows


def classical_particle_rows(image_id: str, labels: np.ndarray, nm_per_px, s, reference) -> list[dict]:
    """particles_classical.csv's rows: the profile's classical particles of one image as `particle_rows` (their label
    ids are those of the profile's labels/ID.tif), with the equivalent diameter at half contrast beside the segmented
    one (``reference``: the profile's classical_check.ClassicalReference, whose outline shift moves it, as its
    median)."""
    rows = particle_rows(image_id, labels, nm_per_px, s.min_area_px, s.exclude_border)
    for row in rows:
        row["half_contrast_diameter_px"] = float(reference.at_half_contrast(row["equivalent_diameter_px"]))
        if nm_per_px:
            row["half_contrast_diameter_nm"] = row["half_contrast_diameter_px"] * nm_per_px
    return rows


def statistics_html(out: Path) -> str:
    """statistics.html: statistics.md, the figures, the overlays image by image and the sortable particle table."""
    from drgan.core.html import data_uri, markdown_html, page, particles_and_overlays

    body = markdown_html((out / "statistics.md").read_text(), out)
    for name, caption in (("sizes.png", "Size distribution"), ("histograms.png", "Areas and diameters")):
        if (out / name).is_file():
            body += f'<h2>{caption}</h2><img class="figure" src="{data_uri(out / name)}" alt="{name}">'
    return page("drgan analyze: particle statistics", body + particles_and_overlays(out))


def pixel_sizes(paths: Sequence[Path], given: float | None) -> tuple[list[float | None], str]:
    """Per image its pixel size in nm (None: unknown) and where it came from: ``nm_per_px`` for all when given,
    else each image's metadata; metadata sizes within SAME_PIXEL of their median are taken as that median."""
    from drgan.data.measurements import pixel_size_nm

    if given is not None:
        return [float(given)] * len(paths), f"nm_per_px={given} (given)"
    found = [pixel_size_nm(p) for p in paths]
    sizes = [s for s, _ in found]
    known = [s for s in sizes if s is not None]
    if not known:
        return sizes, "unknown: no pixel size in the images' metadata (set nm_per_px=... for sizes in nm)"
    median = float(np.median(known))
    sizes = [median if s is not None and abs(s / median - 1) < SAME_PIXEL else s for s in sizes]
    source = next(how for s, how in found if s is not None)
    missing = sum(s is None for s in sizes)
    note = f"{median:.4g} nm/px from the images' metadata ({source})"
    if missing:
        note += f"; {missing} image(s) without one are measured in px only (nm_per_px=... sets one for all)"
    return sizes, note


# --- statistics ------------------------------------------------------------------------------------------------


def _sizes(images: Sequence[Particles], scales: Sequence[float]) -> np.ndarray:
    return np.concatenate([p.whole().diameter * s for p, s in zip(images, scales)] or [np.zeros(0)])


def _point(images: Sequence[Particles], scales: Sequence[float], areas: Sequence[float]) -> dict[str, float]:
    d = _sizes(images, scales)
    counts = np.array([p.count for p in images], float)
    nan = math.nan
    logd = np.log(d[d > 0])
    return {
        "count": float(counts.sum()),
        "count_per_image": float(counts.mean()) if len(counts) else nan,
        "count_per_area": float(counts.sum() / sum(areas)) if sum(areas) else nan,
        "sized": float(len(d)),
        "median_diameter": float(np.median(d)) if len(d) else nan,
        "mean_diameter": float(np.mean(d)) if len(d) else nan,
        "normal_mean": float(np.mean(d)) if len(d) else nan,
        "normal_std": float(np.std(d)) if len(d) else nan,
        "lognormal_median": float(np.exp(logd.mean())) if len(logd) else nan,
        "lognormal_sigma": float(logd.std()) if len(logd) else nan,
    }


def size_statistics(
    images: Sequence[Particles], scales: Sequence[float], areas: Sequence[float], n_boot: int = 1000, seed: int = 0
) -> dict:
    """Counts, median and mean diameter, normal and lognormal parameters (in the unit ``scales`` converts px to) of
    the particles of ``images``, each {"value", "low", "high"} with a percentile bootstrap interval over images;
    ``areas``: each image's area in the unit of the count per area. Plus the model the sizes fit best (BIC)."""
    from drgan.data.measurements import fit_sizes

    result = bootstrap(
        len(images),
        lambda pick: _point([images[i] for i in pick], [scales[i] for i in pick], [areas[i] for i in pick]),
        n_boot if len(images) > 1 else 0,
        seed,
        LEVEL,
    )
    d = _sizes(images, scales)
    if len(d) >= 2:
        fits, chosen = fit_sizes(d)
        result["model"] = {"chosen": chosen.kind, "fits": [f.as_dict() for f in fits]}
    else:
        result["model"] = None
    return result


# --- the command ---------------------------------------------------------------------------------------------


@typed
@dataclass(frozen=True)
class AnalyzeSettings:
    """Every key of conf/segmentation/analyze.yaml with its type, its default and its check (`from_config`, before
    any image is read). The YAML stays the user's reference; the field defaults are the same values
    (tests/test_analyze.py composes analyze.yaml and compares). A new key is a field here (+ its YAML line)."""

    images: Path
    out: Path
    model: str | None = None  # a segmenter checkpoint, or a folder of predicted masks named like the images
    crop_rows: tuple[int, int] | str | None = "auto"  # info-bar rows [start, stop) to drop; auto: detected; None: none
    nm_per_px: float | None = setting(None, check=pixel_size)  # None: read from each image's metadata, else px
    min_area_px: float = setting(SPECK_PX, ge=0, expected="an area in px^2 >= 0")  # smaller components are specks (as
    # drgan.evaluate's statistics)
    exclude_border: bool = False
    bootstrap: int = setting(1000, ge=0, expected="a number of resamples >= 0 (0: no intervals)")
    seed: int = 0
    wires: bool = False
    bins: int = setting(30, ge=1, expected="a positive integer")
    profile: Path | None = None  # a drgan.profile run of these images: its classical sizes to compare with
    inference: dict = field(default_factory=dict)  # checkpoints only

    @classmethod
    def from_config(cls, cfg: DictConfig) -> AnalyzeSettings:
        images = given(cfg, "images", "analyze: give images=DIR (a folder of images)")
        return read_settings(cls, cfg, "analyze", images=Path(str(images)))


def analyze(settings: AnalyzeSettings, predictor=None) -> list[dict]:
    """Analyse every image of the settings' images folder; returns the particle rows.
    predictor: a Predictor or a function image -> class map, instead of the settings' model (tests)."""
    from drgan.data.images import list_images
    from drgan.segmenters import classical_check
    from drgan.segmenters.pairs import read_image_item

    s = settings
    reference = classical_check.ClassicalReference.of_run(s.profile) if s.profile else None
    paths = list_images(s.images)
    predictor = _predictor(s, predictor)
    scales, pixel_note = pixel_sizes(paths, s.nm_per_px)
    log.info("pixel size: %s", pixel_note)
    items = [read_image_item(p, p.stem, s.crop_rows) for p in paths]  # all read (and checked) before predicting
    predictor.check(items)
    measured = segment_images(s, predictor, items, scales, reference)
    summary, sizes = summarize(s, predictor, items, scales, pixel_note, measured, reference)
    write_results(s, summary, measured, sizes)
    log.info(
        "wrote %s: %d particles in %d images, median diameter %s %s",
        s.out / "particles.csv",
        len(measured.rows),
        len(items),
        fmt(summary["statistics"]["median_diameter"]["value"]),
        summary["unit"],
    )
    return measured.rows


def _predictor(s: AnalyzeSettings, predictor):
    """The settings' segmenter (a checkpoint, or a folder of predicted masks), or ``predictor`` checked."""
    from drgan.segmenters.predictors import as_predictor, load_predictor

    if predictor is not None:
        return as_predictor(predictor, "predictor")
    if not s.model:
        raise ConfigError(
            "analyze: give model=CHECKPOINT (a segmenter from python -m drgan.segment) or a folder of "
            "predicted masks named like the images"
        )
    return load_predictor(s.model, s.inference)


@dataclass
class Measured:
    """What `segment_images` measured, image by image: particle rows and particles (the segmenter's; the classical
    ones where the profile's classical segmentation covers the image), the two segmentations compared, and local
    thickness values (``wires``)."""

    rows: list = field(default_factory=list)
    found: list = field(default_factory=list)  # Particles per image, as drgan.evaluate counts and sizes them
    thickness: list = field(default_factory=list)
    comparisons: list = field(default_factory=list)  # classical_check.outline_comparison per image compared
    compared: list = field(default_factory=list)  # (id, classical Particles at half contrast, scale, image area)
    classical_rows: list = field(default_factory=list)


def segment_images(s: AnalyzeSettings, predictor, items: list, scales: list, reference) -> Measured:
    """Each image segmented and measured; its overlay, label TIFF and ROI set (and the classical ones, the thickness
    map) written as it is done, so that a long folder holds one image's arrays at a time."""
    from drgan.segmenters import classical_check

    out, min_area, m = s.out, s.min_area_px, Measured()
    for item, scale in track(list(zip(items, scales)), "segmenting images", unit="images"):
        class_map = np.asarray(predictor(item))
        labels = binarize_and_label(class_map.astype(np.int64), particle_class=1)
        mine = particles(labels).at_least(min_area)  # what drgan.evaluate counts and sizes
        m.found.append(mine)
        image_rows = particle_rows(item.id, labels, scale, min_area, s.exclude_border)
        m.rows += image_rows
        write_bytes(out / "overlays" / f"{item.id}.png", overlay_png(item.image, labels, image_rows))
        write_outlines(out, item.id, labels, [r["id"] for r in image_rows], scale)  # for Fiji and napari
        classical = reference.labels_of(item.id, item.image) if reference else None
        if classical is not None:  # the profile's classical segmentation of the same image, particle by particle
            counted = np.where(np.bincount(labels.ravel())[labels] >= min_area, labels, 0)  # specks out, as above
            m.comparisons.append(classical_check.outline_comparison(counted, classical))
            m.compared.append((item.id, reference.particles(classical, min_area), scale, item.image.size))
            these = classical_particle_rows(item.id, classical, scale, s, reference)
            m.classical_rows += these
            # the classical outlines where microscopists look at them (at the segmented outline: a label image
            # cannot move by a fraction of a pixel): classical/overlays, labels/ and rois/, ids of particles_classical
            write_bytes(out / "classical" / "overlays" / f"{item.id}.png", overlay_png(item.image, classical, these))
            write_outlines(out / "classical", item.id, classical, [r["id"] for r in these], scale)
        if s.wires:
            thick = local_thickness(class_map > 0)
            m.thickness.append(thick[class_map > 0] * (scale or 1.0))
            png = figure_png(lambda plt, im=item.image, t=thick, s=scale: thickness_map(plt, im, t, s))
            write_bytes(out / "thickness" / f"{item.id}.png", png)
        log.info("%s: %d particles (%d cut by the border)", item.id, mine.count, int(mine.border.sum()))
    return m


def summarize(s: AnalyzeSettings, predictor, items, scales, pixel_note, m: Measured, reference) -> tuple[dict, dict]:
    """(summary.json's content, the size figure's inputs): the size statistics in nm where every image has a pixel
    size (else px), the classical particles' beside them where images were segmented both ways, and the verdict on
    whose sizes drgan trusts (drgan.segmenters.classical_check)."""
    from drgan.segmenters import classical_check

    in_nm = all(scale is not None for scale in scales)
    factors = [scale if in_nm else 1.0 for scale in scales]
    areas = [item.image.size * (f * f * 1e-6 if in_nm else 1e-6) for item, f in zip(items, factors)]
    stats = size_statistics(m.found, factors, areas, s.bootstrap, s.seed)
    whole = pooled(m.found)
    classical_summary = classical_check.pool(m.comparisons, reference) if reference else None
    classical_d = None  # drawn beside the segmenter's distribution
    if m.compared:  # the classical particles' statistics, as the segmenter's, over the images segmented both ways
        segmented, classical_found, classical_scales, image_sizes = zip(*m.compared)
        classical_factors = [f if in_nm else 1.0 for f in classical_scales]
        classical_areas = [n * (f * f * 1e-6 if in_nm else 1e-6) for n, f in zip(image_sizes, classical_factors)]
        classical_summary["statistics"] = size_statistics(
            classical_found, classical_factors, classical_areas, s.bootstrap, s.seed
        )
        classical_summary["segmented"] = list(segmented)  # the images particles_classical.csv covers
        # the verdict compares like with like: the classical median of the images analyzed (the profile's own, of
        # its images only, kept beside it), as the right-hand column of statistics.md shows it
        theirs = pooled(classical_found)
        classical_summary["profile_median_diameter_px"] = classical_summary["median_diameter_px"]
        classical_summary["median_diameter_px"] = float(np.median(theirs)) if theirs.size else None
        classical_d = _sizes(classical_found, classical_factors)
    median_px = float(np.median(whole)) if whole.size else None
    closed_loop = getattr(getattr(predictor, "model", None), "closed_loop", None)
    verdict = (
        classical_check.judge(median_px, classical_summary.get("median_diameter_px"), closed_loop, classical_summary)
        if classical_summary
        else None
    )
    summary = {
        "images": len(items),
        "images_dir": str(Path(s.images).resolve()),  # where the images lie (the napari reader opens them beside)
        "median_diameter_px": median_px,
        # the segmenter's own error on held-out generated pairs (drgan.segmenters.closed_loop), when it has one
        "closed_loop": closed_loop,
        # the profile's classical sizes and segmentation of the same images (drgan.segmenters.classical_check), with
        # the classical particles' statistics when analyze compared images, and whose sizes drgan trusts
        "classical": classical_summary,
        "trusted": verdict.trusted if verdict else None,
        "verdict": verdict.sentence if verdict else None,
        "unit": "nm" if in_nm else "px",
        "area_unit": "µm²" if in_nm else "Mpx",
        "pixel_size": pixel_note,
        "min_area_px": s.min_area_px,
        "exclude_border": s.exclude_border,
        "model": predictor.source,
        "inference": predictor.how,
        "statistics": stats,
        "per_image": [
            {"image": item.id, "count": p.count, "cut_by_border": int(p.border.sum()), "nm_per_px": scale}
            for item, p, scale in zip(items, m.found, scales)
        ],
    }
    return summary, {"diameters": _sizes(m.found, factors), "classical": classical_d}


def write_results(s: AnalyzeSettings, summary: dict, m: Measured, sizes: dict) -> None:
    """The run's tables, summary, statistics.md, figures and statistics.html (each written whole: drgan.core.io)."""
    out, bins, unit = s.out, s.bins, summary["unit"]
    in_nm = unit == "nm"
    write_bytes(out / "particles.csv", _csv(m.rows).encode())
    if m.classical_rows:
        write_bytes(out / "particles_classical.csv", _csv(m.classical_rows).encode())
    else:  # a rerun into the same folder must not leave an earlier run's classical table beside this run's
        (out / "particles_classical.csv").unlink(missing_ok=True)
        shutil.rmtree(out / "classical", ignore_errors=True)
    write_json(out / "summary.json", summary)
    write_bytes(out / "statistics.md", statistics_markdown(summary).encode())
    stats, trusted = summary["statistics"], summary["trusted"]
    write_bytes(
        out / "sizes.png",
        figure_png(lambda plt: size_figure(plt, sizes["diameters"], stats, unit, bins, sizes["classical"], trusted)),
    )
    write_bytes(out / "histograms.png", figure_png(lambda plt: histograms(plt, m.rows, in_nm, bins)))
    write_bytes(out / "statistics.html", statistics_html(out).encode())
    if s.wires:
        values = np.concatenate(m.thickness) if m.thickness else np.zeros(0)
        write_bytes(
            out / "thickness_histogram.png",
            figure_png(lambda plt: thickness_histogram(plt, values, in_nm, bins)),
        )


def local_thickness(particle: np.ndarray) -> np.ndarray:
    """Local thickness (a diameter, px) of every foreground pixel; 0 outside."""
    import localthickness

    particle = np.asarray(particle, dtype=bool)
    if not particle.any():
        return np.zeros(particle.shape)
    # A one-pixel background frame: a mask with no background pixel has an infinite distance transform.
    framed = np.pad(particle, 1)
    radius = np.asarray(localthickness.local_thickness(framed), dtype=np.float64)[1:-1, 1:-1]
    return 2.0 * radius * particle


# --- outputs -----------------------------------------------------------------------------------------------


# the header of a table without particles: particle_rows' columns (pixel units)
EMPTY_TABLE_COLUMNS = ("id", "image", "area_px", "equivalent_diameter_px", "axis_ratio", "centroid_y", "centroid_x",
                       "bbox_min_row", "bbox_min_col", "bbox_max_row", "bbox_max_col", "touches_border", "sized")  # fmt: skip


def _csv(rows: list[dict]) -> str:
    fields = list(rows[0]) if rows else list(EMPTY_TABLE_COLUMNS)
    for row in rows:  # images with and without a pixel size: every column once
        fields += [k for k in row if k not in fields]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n", restval="")
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


def _interval(cell: dict, digits: int = 3) -> str:
    return interval_text(cell, lambda value: fmt(value, digits))


def _statistic_rows(s: dict, unit: str, area_unit: str) -> list[tuple[str, str]]:
    return [
        ("particles counted", f"{fmt(s['count']['value'], 6)} ({fmt(s['sized']['value'], 6)} sized)"),
        ("particles per image", _interval(s["count_per_image"])),
        (f"particles per {area_unit}", _interval(s["count_per_area"])),
        (f"median diameter ({unit})", _interval(s["median_diameter"])),
        (f"mean diameter ({unit})", _interval(s["mean_diameter"])),
        (f"normal fit: mean, std ({unit})", f"{_interval(s['normal_mean'])}, {_interval(s['normal_std'])}"),
        (
            f"lognormal fit: median ({unit}), sigma",
            f"{_interval(s['lognormal_median'])}, {_interval(s['lognormal_sigma'])}",
        ),
    ]


TRUSTED_WORDS = {  # statistics.md's headline on whose sizes drgan trusts (classical_check.Verdict.trusted)
    "classical": "**drgan trusts the classical sizes** (the right-hand column; why: below): the segmenter's "
    "particle table and outlines are its own, the classical particles are in particles_classical.csv.",
    "segmenter": "**drgan trusts the segmenter's sizes** (the left-hand column; why: below).",
    "both": "The two median diameters agree within 5 %: **drgan trusts these sizes** and reports the segmenter's "
    "(the left-hand column, particles.csv; why: below).",
    None: "**Neither size is trusted over the other** (why: below): compare the two columns and the overlays.",
}


def statistics_markdown(summary: dict) -> str:
    s, unit, area_unit = summary["statistics"], summary["unit"], summary["area_unit"]
    model = s.get("model")
    classical = (summary.get("classical") or {}).get("statistics")
    lines = [
        "# Particle statistics",
        "",
        f"{summary['images']} images; segmenter `{summary['model']}` ({summary['inference'] or 'as given'}). Pixel size: "
        f"{summary['pixel_size']}. Components under {summary['min_area_px']:g} px² are specks (not counted); particles "
        "cut by the image border are counted but not sized. Intervals: 95 % percentile bootstrap over images.",
        "",
    ]
    if classical:  # the two side by side, the trusted one named
        images = summary["classical"]["images"]
        lines += [
            f"Beside the segmenter's: the profile's classical segmentation (threshold + watershed at the profile's "
            f"settings, no training) of {images} of the images, "
            + (
                "sized at half contrast of the images' mean edge. "
                if summary["classical"].get("half_contrast")
                else "sized at its segmented outlines (the profile found no mean edge to move them to half contrast). "
            )
            + TRUSTED_WORDS[summary.get("trusted")],
            "",
            "| statistic | segmenter: value [95 % interval] | classical: value [95 % interval] |",
            "|---|---|---|",
        ]
        lines += [
            f"| {name} | {mine} | {theirs} |"
            for (name, mine), (_, theirs) in zip(
                _statistic_rows(s, unit, area_unit), _statistic_rows(classical, unit, area_unit)
            )
        ]
    else:
        lines += ["| statistic | value [95 % interval] |", "|---|---|"]
        lines += [f"| {name} | {value} |" for name, value in _statistic_rows(s, unit, area_unit)]
    if model:
        bics = ", ".join(f"{f['kind']} {f['bic']:.1f}" for f in model["fits"])
        lines += ["", f"The segmenter's sizes fit a **{model['chosen']}** distribution best (lowest BIC: {bics})."]
    lines += ["", "## How far these sizes can be trusted", "", trust_paragraph(summary.get("closed_loop"))]
    if summary.get("classical"):
        lines += ["", classical_paragraph(summary)]
    lines += ["", "| image | particles | cut by the border |", "|---|---|---|"]
    lines += [f"| {r['image']} | {r['count']} | {r['cut_by_border']} |" for r in summary["per_image"]]
    return "\n".join(lines) + "\n"


def trust_paragraph(check: dict | None) -> str:
    """statistics.md's words on the segmenter's own error: its closed-loop check (drgan.segmenters.closed_loop), or
    why there is none."""
    from drgan.segmenters.closed_loop import trust_line

    if not check:
        return (
            "No closed-loop check: this segmenter was not trained on generated pairs with exact outlines held out "
            "(trained on real images, before drgan.segment held them out, or with check_fraction=0), so its own size "
            "error is unknown; drgan.evaluate on annotated images measures it."
        )
    return trust_line(check)


def classical_paragraph(summary: dict) -> str:
    """statistics.md's comparison with the profile's classical sizes of the same images, and which drgan trusts."""
    from drgan.segmenters.classical_check import compare_with_classical

    if summary.get("verdict"):  # as analyze judged it
        return summary["verdict"]
    classical = summary["classical"]
    return compare_with_classical(
        summary.get("median_diameter_px"), classical.get("median_diameter_px"), summary.get("closed_loop"), classical
    )


@stage_main("conf/segmentation", "analyze")
def main(cfg: DictConfig):
    analyze(AnalyzeSettings.from_config(cfg))


if __name__ == "__main__":
    start(main)
