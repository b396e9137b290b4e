"""The figures `python -m drgan.profile` writes beside its report: scale_search.png (how the particle scale was
found), sizes.png (the diameters and their fits), background_noise.png (background grey, high-pass residual,
particles per patch), edge_profile.png (the mean particle edge and its fitted fringe) and particles.png (real images
with the detected outlines: keep them out of repositories).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from drgan.core.io import figure_png, write_bytes
from drgan.data import measurements
from drgan.data.classical import CALIBRATION, Fixed
from drgan.data.particle_edge import edge_model


def scale_figure(out: Path, search: dict) -> None:
    """scale_search.png: the segments' median diameter at each scale segmented, per neck depth, against the diagonal
    where a segmentation agrees with its own scale (band: Calibration.consistent); the fixed points found, marked by how many
    scales segment to their size (the basin), and the one chosen (`drgan.data.classical.search_scale`)."""
    grid = np.array([[s, d, np.nan if m is None else m] for s, d, m, _ in search["grid"]], dtype=float)
    fixed = [Fixed.from_list(c) for c in search["candidates"]]

    def plot(plt):
        fig, ax = plt.subplots(figsize=(6.5, 5))
        lo, hi = np.nanmin(grid[:, :1]) / 1.5, np.nanmax(grid[:, [0, 2]]) * 1.5
        x = np.geomspace(lo, hi, 50)
        ax.fill_between(
            x,
            x * math.exp(-CALIBRATION.consistent),
            x * math.exp(CALIBRATION.consistent),
            color="0.9",
            label="agrees with its scale",
        )
        ax.plot(x, x, color="0.6", lw=0.8)
        for depth, colour in ((0.0, "C0"), (CALIBRATION.neck_depth, "C1")):
            row = grid[grid[:, 1] == depth]
            row = row[np.argsort(row[:, 0])]
            what = "every maximum seeds" if depth == 0 else f"seeds at necks ({depth})"
            ax.plot(row[:, 0], row[:, 2], "o-", ms=3, color=colour, label=f"segments' median, {what}")
            for f in (f for f in fixed if f.depth == depth):
                ax.scatter(f.scale, f.median, s=20 + 15 * f.basin, facecolors="none", edgecolors=colour)
                ax.annotate(str(f.basin), (f.scale, f.median), textcoords="offset points", xytext=(6, -10),
                            fontsize=7, color=colour)  # fmt: skip
        if search.get("refined_px"):
            ax.axvline(search["refined_px"], color="k", ls="--", lw=1, label=f"chosen {search['refined_px']} px")
        ax.set(xscale="log", yscale="log", xlim=(lo, hi), ylim=(lo, hi), xlabel="scale segmented with (px)",
               ylabel="segments' median diameter (px)",
               title="particle scale search (circles: fixed points, number: scales holding their size)")  # fmt: skip
        ax.title.set_fontsize(9)
        ax.legend(fontsize=7, loc="upper left")
        return fig

    write_bytes(out / "scale_search.png", figure_png(plot))


def write_figures(out, images, labels, diameters, fits, chosen, noise, foregrounds, counts, polarity) -> None:
    def sizes(plt):
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.hist(diameters, bins=40, density=True, color="0.8", label=f"{diameters.size} particles")
        x = np.linspace(max(diameters.min() * 0.8, 0.1), diameters.max() * 1.1, 400)
        for f in fits:
            best = f.kind == chosen.kind
            ax.plot(x, f.pdf(x), lw=3 if best else 1.2, label=f"{f.kind} (BIC {f.bic:.0f}){' chosen' if best else ''}")
        ax.set_xlabel("equivalent diameter (px)")
        ax.set_ylabel("density")
        ax.legend()
        return fig

    def background(plt):
        fig, axes = plt.subplots(1, 3, figsize=(14, 3.5))
        grey = np.concatenate(
            [np.asarray(im)[measurements.background_mask(fg)] for im, fg in zip(images[:8], foregrounds[:8])]
        )
        axes[0].hist(grey, bins=100, color="0.5")
        axes[0].axvline(noise.background_grey, color="r", label=f"median {noise.background_grey:.3f}")
        axes[0].set_xlabel("background grey")
        axes[0].legend()
        residual = np.concatenate(
            [measurements.highpass(im)[measurements.background_mask(fg)] for im, fg in zip(images[:8], foregrounds[:8])]
        )
        lim = 6 * max(noise.residual_sigma, 1e-6)
        axes[1].hist(residual, bins=100, range=(-lim, lim), density=True, color="0.5")
        x = np.linspace(-lim, lim, 200)
        gauss = np.exp(-0.5 * (x / noise.residual_sigma) ** 2) / (noise.residual_sigma * math.sqrt(2 * math.pi))
        axes[1].plot(x, gauss, "r", label=f"MAD sigma {noise.residual_sigma:.4f}")
        axes[1].set_xlabel(
            f"high-pass residual (lag-1 r {noise.lag1_autocorrelation:.2f}, grain {noise.grain_px:.2f} px)"
        )
        axes[1].legend()
        axes[2].hist(counts, bins=np.arange(counts.max() + 2) - 0.5, color="0.5")
        axes[2].set_xlabel("particles per patch (centroid inside)")
        return fig

    write_bytes(out / "sizes.png", figure_png(sizes))
    outline_figure(out, images, labels, polarity)
    write_bytes(out / "background_noise.png", figure_png(background))


def edge_figure(out: Path, edge) -> None:
    """edge_profile.png: the mean edge profile with its errors, the fitted edge and fringe, and the ring found."""

    def plot(plt):
        fig, ax = plt.subplots(figsize=(7, 4))
        if edge is None:
            ax.text(0.5, 0.5, "too few isolated particles for an edge profile", ha="center", transform=ax.transAxes)
            return fig
        d, p, e, used = edge.distance_px, edge.profile, edge.standard_error, edge.usable
        ax.errorbar(d[used], p[used], yerr=2 * e[used], fmt="o", color="k", ms=4, label="mean edge (2 standard errors)")
        skipped = ~used & np.isfinite(p)
        if skipped.any():
            ax.plot(d[skipped], p[skipped], "o", mfc="none", color="0.5", label="not used (saturated or few particles)")
        if edge.fringe is not None:
            f = edge.fringe
            x = np.linspace(d[np.isfinite(d)].min(), d[np.isfinite(d)].max(), 300)
            args = (f.contrast_scale, f.interior_slope, f.edge_offset_px, f.edge_blur_px)
            ax.plot(x, edge_model(x, *args, f.amplitude, f.width_px, edge.radius_px), "r",
                    label=f"fit: fringe amplitude {f.amplitude:+.3f}, width {f.width_px:.2f} px")  # fmt: skip
            ax.plot(x, edge_model(x, *args, 0.0, f.width_px, edge.radius_px), "r:", lw=1, label="fit, no fringe")
        if edge.ring.kind != "none":
            ax.plot([edge.ring.distance_px], [-edge.ring.height], "v", color="tab:blue", ms=10,
                    label=f"ring ({edge.ring.kind}): {edge.ring.height:+.3f}")  # fmt: skip
        ax.axhline(0, color="0.6", lw=0.8)
        ax.axhline(1, color="0.6", lw=0.8, ls="--")
        ax.axvline(0, color="0.6", lw=0.8)
        ax.set_xlabel("signed distance to the segmented edge (px; < 0 inside)")
        ax.set_ylabel("grey, particle contrast (0 background, 1 interior)")
        ring = {"opposite": "a ring of the opposite grey", "like": "a ring like the particles"}.get(edge.ring.kind)
        ax.set_title(f"mean edge of {edge.particles} isolated particles: {ring or 'no ring'}")
        ax.legend(fontsize=8)
        return fig

    write_bytes(out / "edge_profile.png", figure_png(plot))


def outline_figure(out: Path, images, labels, polarity: str) -> None:
    from skimage.segmentation import find_boundaries

    def outlines(plt):
        shown = [(im, lab) for im, lab in zip(images, labels) if lab is not None][:4]
        fig, axes = plt.subplots(1, len(shown), figsize=(5 * len(shown), 4), squeeze=False)
        for ax, (im, lab) in zip(axes[0], shown):
            rgb = np.repeat(im[..., None], 3, axis=2)
            rgb[find_boundaries(lab, mode="outer")] = (1.0, 0.2, 0.1)
            ax.imshow(rgb)
            ax.set_title(f"{int(lab.max() and len(np.unique(lab)) - 1)} segments ({polarity})")
            ax.axis("off")
        return fig

    write_bytes(out / "particles.png", figure_png(outlines))
