"""The figures drgan.analyze writes: the size distribution (sizes.png, with the classical one beside where it was
measured), the area and diameter histograms, an image's particle outlines (overlays/ID.png) and the local-thickness
map and histogram (wires=true). Each takes the measured values; ``plt`` is matplotlib.pyplot (drgan.core.io.figure_png
passes it)."""

from __future__ import annotations

import io
import math

import numpy as np


def fmt(value, digits: int = 3) -> str:
    """A number to ``digits`` significant digits; "n/a" for what is not a finite number."""
    return f"{value:.{digits}g}" if isinstance(value, (int, float)) and math.isfinite(value) else "n/a"


def density(model: dict | None, x: np.ndarray) -> tuple[np.ndarray, str] | None:
    if not model:
        return None
    fit = next(f for f in model["fits"] if f["kind"] == model["chosen"])
    p = fit["params"]

    def lognormal(median, sigma):
        return np.exp(-0.5 * ((np.log(x) - np.log(median)) / sigma) ** 2) / (x * sigma * np.sqrt(2 * np.pi))

    if fit["kind"] == "normal":
        y = np.exp(-0.5 * ((x - p["mean"]) / p["std"]) ** 2) / (p["std"] * np.sqrt(2 * np.pi))
    elif fit["kind"] == "lognormal":
        y = lognormal(p["median"], p["sigma"])
    else:
        y = p["weight1"] * lognormal(p["median1"], p["sigma1"]) + (1 - p["weight1"]) * lognormal(
            p["median2"], p["sigma2"]
        )
    return y, fit["kind"]


def size_figure(
    plt, diameters: np.ndarray, stats: dict, unit: str, bins: int, classical: np.ndarray | None = None, trusted=None
):
    """sizes.png: the segmenter's size distribution (histogram, the chosen fit, the median and its interval) and its
    cumulative curve; with ``classical``, the profile's classical sizes drawn over both (the trusted one named)."""
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.8))
    mark = {trusted: " (trusted)"} if trusted in ("segmenter", "classical") else {}
    if len(diameters):
        edges = np.histogram_bin_edges(
            diameters if classical is None or not len(classical) else np.concatenate([diameters, classical]), bins
        )
        left.hist(
            diameters, bins=edges, density=True, color="0.75",
            label=f"segmenter{mark.get('segmenter', '')}: {len(diameters)} sized particles",
        )  # fmt: skip
        x = np.linspace(max(diameters.min() * 0.8, 1e-6), diameters.max() * 1.1, 400)
        fitted = density(stats.get("model"), x)
        if fitted is not None:
            left.plot(x, fitted[0], "C3", label=f"{fitted[1]} fit")
        median = stats["median_diameter"]
        left.axvline(
            median["value"],
            color="C0",
            ls="--",
            label=f"{'segmenter ' if classical is not None else ''}median {fmt(median['value'])} {unit}",
        )
        if math.isfinite(median["low"]):
            left.axvspan(median["low"], median["high"], color="C0", alpha=0.15, label="95 % interval")
        ordered = np.sort(diameters)
        right.step(ordered, np.arange(1, len(ordered) + 1) / len(ordered), where="post", color="k", label="segmenter")
        if classical is not None and len(classical):
            name = f"classical{mark.get('classical', '')}"
            left.hist(classical, bins=edges, density=True, histtype="step", color="C2", lw=1.5,
                      label=f"{name}: {len(classical)} particles, median {fmt(float(np.median(classical)))} {unit}")  # fmt: skip
            ordered = np.sort(classical)
            right.step(ordered, np.arange(1, len(ordered) + 1) / len(ordered), where="post", color="C2", label=name)
            right.legend(fontsize=8)
    left.set_xlabel(f"equivalent diameter ({unit})")
    left.set_ylabel("density")
    if len(diameters):
        left.legend(fontsize=8)
    right.set_xlabel(f"equivalent diameter ({unit})")
    right.set_ylabel("cumulative fraction")
    right.set_ylim(0, 1)
    fig.tight_layout()
    return fig


def histograms(plt, rows, in_nm, bins):
    unit = "nm" if in_nm else "px"
    sized = [r for r in rows if r["sized"]]
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    axes[0].hist([r["area_nm2" if in_nm else "area_px"] for r in sized], bins=bins)
    axes[0].set_xlabel(f"area ({unit}²)")
    axes[1].hist([r["equivalent_diameter_nm" if in_nm else "equivalent_diameter_px"] for r in sized], bins=bins)
    axes[1].set_xlabel(f"equivalent diameter ({unit})")
    for ax in axes:
        ax.set_ylabel("particles")
    fig.suptitle(f"{len(sized)} sized particles ({len(rows) - len(sized)} cut by the border, counted only)")
    return fig


OUTLINE, CUT = (255, 200, 0), (0, 170, 255)  # sized particles' outlines, and those of particles cut by the border


def overlay_png(image: np.ndarray, labels: np.ndarray, rows: list[dict]) -> bytes:
    """The image in grey with each counted particle's outline (cut ones in another colour) and its id."""
    from PIL import Image, ImageDraw
    from skimage.segmentation import find_boundaries

    grey = (np.clip(np.asarray(image, float), 0, 1) * 255).astype(np.uint8)
    rgb = np.repeat(grey[..., None], 3, axis=2)
    counted = np.zeros(int(labels.max()) + 1, bool)
    cut = np.zeros_like(counted)
    for row in rows:
        counted[row["id"]] = True
        cut[row["id"]] = row["touches_border"]
    edge = find_boundaries(labels, mode="inner") & counted[labels]
    rgb[edge & ~cut[labels]] = OUTLINE
    rgb[edge & cut[labels]] = CUT
    picture = Image.fromarray(rgb)
    draw = ImageDraw.Draw(picture)
    for row in rows:
        draw.text((row["centroid_x"] - 4, row["centroid_y"] - 5), str(row["id"]), fill=(255, 60, 60))
    buf = io.BytesIO()
    picture.save(buf, format="PNG")
    return buf.getvalue()


def thickness_map(plt, image, thick, nm):
    fig, ax = plt.subplots(figsize=(6, 6 * image.shape[0] / image.shape[1]))
    ax.imshow(image, cmap="gray", vmin=0, vmax=1)
    shown = np.ma.masked_where(thick == 0, thick * (nm or 1.0))
    im = ax.imshow(shown, cmap="viridis", alpha=0.7)
    fig.colorbar(im, ax=ax, label=f"local thickness ({'nm' if nm else 'px'})")
    ax.axis("off")
    return fig


def thickness_histogram(plt, values, in_nm, bins):
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.hist(values, bins=bins)
    ax.set_xlabel(f"local thickness ({'nm' if in_nm else 'px'})")
    ax.set_ylabel("pixels")
    return fig
