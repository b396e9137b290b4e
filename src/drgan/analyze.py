"""`python -m drgan.analyze model=CKPT images=DIR out=DIR [nm_per_px=...] [wires=true]`: particle statistics.

``model``: a segmenter checkpoint, or a folder of predicted masks named like the images (e.g. nnU-Net's output
folder; drgan.segmentation.predictors). Each image -> class map (a checkpoint: sliding windows) -> particle class (contour separates touching particles) ->
4-connected instances. Writes:
- particles.csv: one row per particle: id, image, area_px, equivalent_diameter_px (diameter of the disk of
  equal area, 2 sqrt(area / pi)), centroid_y/x, bbox (min_row, min_col, max_row, max_col; max exclusive),
  touches_border, and area_nm2 / equivalent_diameter_nm when nm_per_px is given;
- histograms.png: area and equivalent diameter;
- wires=true: thickness/ID.png (local-thickness map over the image) and thickness_histogram.png.
  Local thickness of a pixel = diameter of the largest disk inside the particle (particle + contour class)
  that contains the pixel, computed with the `localthickness` package (its output is a radius, doubled here).
"""

from __future__ import annotations

import csv
import io
import logging
import os
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig

from drgan.errors import ConfigError
from drgan.io import figure_png, write_bytes
from drgan.metrics.segmentation import binarize_and_label

log = logging.getLogger(__name__)


def particle_rows(
    image_id: str,
    labels: np.ndarray,
    nm_per_px: float | None = None,
    min_area_px: int = 0,
    exclude_border: bool = False,
) -> list[dict]:
    from skimage.measure import regionprops

    h, w = labels.shape
    rows = []
    for region in regionprops(labels):
        area = int(region.area)
        r0, c0, r1, c1 = region.bbox
        border = r0 == 0 or c0 == 0 or r1 == h or c1 == w
        if area < min_area_px or (exclude_border and border):
            continue
        row = {
            "id": int(region.label),
            "image": image_id,
            "area_px": area,
            "equivalent_diameter_px": 2.0 * np.sqrt(area / np.pi),
            "centroid_y": float(region.centroid[0]),
            "centroid_x": float(region.centroid[1]),
            "bbox_min_row": r0,
            "bbox_min_col": c0,
            "bbox_max_row": r1,
            "bbox_max_col": c1,
            "touches_border": border,
        }
        if nm_per_px:
            row["area_nm2"] = area * nm_per_px**2
            row["equivalent_diameter_nm"] = row["equivalent_diameter_px"] * nm_per_px
        rows.append(row)
    return rows


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


def analyze(cfg: DictConfig, predictor=None) -> list[dict]:
    """Analyse every image of cfg.images; returns the particle rows.
    predictor: a Predictor or a function image -> class map, instead of cfg.model (tests)."""
    from drgan.data.images import list_images
    from drgan.segmentation.data import read_image_item
    from drgan.segmentation.predictors import as_predictor, load_predictor

    if not cfg.get("images"):
        raise ConfigError("analyze: give images=DIR (a folder of images)")
    nm = cfg.get("nm_per_px")
    if nm is not None and not float(nm) > 0:
        raise ConfigError(f"analyze: nm_per_px={nm}: expected a positive pixel size")
    paths = list_images(cfg.images)
    if predictor is None:
        if not cfg.get("model"):
            raise ConfigError(
                "analyze: give model=CHECKPOINT (a segmenter from python -m drgan.segment) or a folder of "
                "predicted masks named like the images"
            )
        predictor = load_predictor(cfg.model, cfg.inference)
    else:
        predictor = as_predictor(predictor, "predictor")
    crop = cfg.get("crop_rows")
    crop = crop if crop is None or isinstance(crop, str) else tuple(crop)
    items = [read_image_item(p, p.stem, crop) for p in paths]  # all read (and checked) before predicting
    predictor.check(items)

    out = Path(cfg.out)
    rows, thickness_values = [], []
    for item in items:
        image_id, image = item.id, item.image
        class_map = np.asarray(predictor(item))
        labels = binarize_and_label(class_map.astype(np.int64), particle_class=1)
        rows += particle_rows(
            image_id, labels, float(nm) if nm else None, int(cfg.min_area_px), bool(cfg.exclude_border)
        )
        if cfg.get("wires"):
            thick = local_thickness(class_map > 0)
            thickness_values.append(thick[class_map > 0] * (float(nm) if nm else 1.0))
            png = figure_png(lambda plt, im=image, t=thick: _thickness_map(plt, im, t, nm))
            write_bytes(out / "thickness" / f"{image_id}.png", png)
        log.info("%s: %d particles", image_id, sum(r["image"] == image_id for r in rows))

    fields = list(rows[0]) if rows else ["id", "image", "area_px", "equivalent_diameter_px"]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    write_bytes(out / "particles.csv", buf.getvalue().encode())
    write_bytes(out / "histograms.png", figure_png(lambda plt: _histograms(plt, rows, nm, int(cfg.bins))))
    if cfg.get("wires"):
        values = np.concatenate(thickness_values) if thickness_values else np.zeros(0)
        write_bytes(
            out / "thickness_histogram.png",
            figure_png(lambda plt: _thickness_histogram(plt, values, nm, int(cfg.bins))),
        )
    log.info("wrote %s: %d particles in %d images", out / "particles.csv", len(rows), len(items))
    return rows


def _histograms(plt, rows, nm, bins):
    unit = "nm" if nm else "px"
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    area = [r["area_nm2" if nm else "area_px"] for r in rows]
    diam = [r["equivalent_diameter_nm" if nm else "equivalent_diameter_px"] for r in rows]
    axes[0].hist(area, bins=bins)
    axes[0].set_xlabel(f"area ({unit}²)")
    axes[1].hist(diam, bins=bins)
    axes[1].set_xlabel(f"equivalent diameter ({unit})")
    for ax in axes:
        ax.set_ylabel("particles")
    fig.suptitle(f"{len(rows)} particles")
    return fig


def _thickness_map(plt, image, thick, nm):
    fig, ax = plt.subplots(figsize=(6, 6 * image.shape[0] / image.shape[1]))
    ax.imshow(image, cmap="gray", vmin=0, vmax=1)
    shown = np.ma.masked_where(thick == 0, thick * (nm or 1.0))
    im = ax.imshow(shown, cmap="viridis", alpha=0.7)
    fig.colorbar(im, ax=ax, label=f"local thickness ({'nm' if nm else 'px'})")
    ax.axis("off")
    return fig


def _thickness_histogram(plt, values, nm, bins):
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.hist(values, bins=bins)
    ax.set_xlabel(f"local thickness ({'nm' if nm else 'px'})")
    ax.set_ylabel("pixels")
    return fig


@hydra.main(version_base="1.3", config_path="conf/segmentation", config_name="analyze")
def main(cfg: DictConfig):
    analyze(cfg)


if __name__ == "__main__":
    os.environ.setdefault("HYDRA_FULL_ERROR", "0")
    from drgan.configs import setup

    setup()
    main()
