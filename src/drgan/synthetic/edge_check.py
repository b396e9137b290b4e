"""Where a generated set puts its particles' edges against the real images (`generate`'s edge_check.json).

A segmenter learns the outline from the generated pairs: where their exact masks end relative to the grey ramp the
renderer draws. If the real particles' ramp is sharper (or wider, or ringed) than the rendered one, the segmenter puts
the real outline elsewhere, and every reported size moves with it. This module measures the mean particle edge the
way drgan.profile measures it on the real images (drgan.data.particle_edge: the grey of isolated particles against
the signed distance to the edge, in units of the particle contrast, 1 inside and 0 on the background), on both sides
with the same reference edge (drgan's classical segmentation with the patch set's settings), and on the generated
images also against their exact masks:

- ``half_px``: where the profile crosses half contrast, px from the reference edge (> 0 outside). Static image analysis
  puts a particle's boundary at half contrast between particle and background (ISO 13322-1);
- ``width_px``: the 10-90 % rise of the ramp (a blur's width: 2.56 sigma for a Gaussian blur of a straight edge);
- on the generated images against their masks: ``mask_half_px``, where half contrast lies from the true (mask) edge:
  0 when drgan's masks follow the half-contrast convention, > 0 when the masks end inside the visible half-contrast
  outline.
``compare``: generated minus real ``half_px`` and ``width_px`` (their ratio): a rendered ramp wider than the real one
makes the segmenter draw real outlines too wide (its learnt edge lies further out on the ramp).
"""

from __future__ import annotations

import logging
import math

import numpy as np

from drgan.data.particle_edge import crossing

log = logging.getLogger(__name__)

SAMPLE = 64  # images measured on each side (the first ones)
WARN_WIDTH = 1.5  # a generated ramp this many times as wide as the real one (or narrower by as much) is named


def ramp(edge) -> dict | None:
    """The half-contrast position and the 10-90 % width of an EdgeProfile (drgan.data.particle_edge), with the profile
    itself (for figures); None without a profile."""
    if edge is None:
        return None
    d, p = edge.ramp_bins
    half, inner, outer = (crossing(d, p, level) for level in (0.5, 0.9, 0.1))
    return {
        "particles": int(edge.particles),
        "half_px": _round(half),
        "width_px": _round(outer - inner),
        "ring": edge.ring.kind,
        "distance_px": [_round(x) for x in d],
        "profile": [_round(x) for x in p],
    }


def _round(value: float) -> float | None:
    return round(float(value), 3) if math.isfinite(value) else None


def edge_of(images, labels_of, foregrounds_of) -> dict | None:
    """`ramp` of the mean edge of ``images`` with each image's particle labels and foreground (callables of the image
    index, returning None to skip the image)."""
    from drgan.data.particle_edge import edge_profile, edge_samples

    samples = []
    for k, image in enumerate(images):
        labels, foreground = labels_of(k), foregrounds_of(k)
        if labels is not None:
            samples.append(edge_samples(image, labels, foreground))
    return ramp(edge_profile(samples))


def classical_edges(images, params, polarity: str) -> dict | None:
    """The mean edge of ``images`` against drgan's classical segmentation with ``params`` (resolved SegmentParams), as
    drgan.profile measures the real images."""
    from drgan.data.measurements import segment_image

    found = [segment_image(np.asarray(image, np.float32), params, polarity) for image in images]
    return edge_of(images, lambda k: found[k].labels, lambda k: found[k].labels > 0)


def compare(real: dict | None, generated: dict | None) -> dict:
    """Generated minus real half-contrast position and the ratio of the ramps' widths (None where either is missing)."""

    def get(side, key):
        return None if side is None else side.get(key)

    half_r, half_g = get(real, "half_px"), get(generated, "half_px")
    width_r, width_g = get(real, "width_px"), get(generated, "width_px")
    return {
        "half_px_difference": _round(half_g - half_r) if half_r is not None and half_g is not None else None,
        "width_ratio": _round(width_g / width_r) if width_r and width_g is not None else None,
    }


def summary_line(result: dict) -> str:
    real, generated, exact = (result.get(k) or {} for k in ("real", "generated", "generated_mask"))

    def px(value):
        return "n/a" if value is None else f"{value:.2f} px"

    return (
        f"particle edge, 10-90 % ramp: generated {px(generated.get('width_px'))}, real {px(real.get('width_px'))}; "
        f"half contrast from the classical edge: generated {px(generated.get('half_px'))}, real "
        f"{px(real.get('half_px'))}; the generated masks end {px(exact.get('half_px'))} from half contrast"
    )


def log_result(result: dict) -> None:
    """The summary line, as a warning when the rendered ramp is WARN_WIDTH times as wide (or narrow) as the real one."""
    ratio = result.get("width_ratio")
    if ratio is not None and not 1 / WARN_WIDTH < ratio < WARN_WIDTH:
        log.warning(
            "%s: the rendered edge ramp is %.2g x the real one; a segmenter trained on it draws real outlines off the "
            "edge (material.filter_stddev sets the render's blur)", summary_line(result), ratio,
        )  # fmt: skip
    else:
        log.info("%s", summary_line(result))


def check_dataset(root, manifest: dict, backgrounds, polarity: str, resolution: int) -> dict | None:
    """The edge check of a complete generated set against the real train patches of ``backgrounds`` (a PatchSet or
    its folder; None, or a set without train patches: None), both at the render's ``resolution`` and segmented with
    the patch set's settings resolved on the real patches (drgan.synthetic.noise_check.sample_sides)."""
    from drgan.synthetic.noise_check import sample_sides

    sides = sample_sides(root, manifest, backgrounds, polarity, resolution)
    if sides is None:
        return None
    seen, params, images, labels = sides
    labels = [label.astype(np.int32) for label in labels]
    real = classical_edges(list(np.asarray(seen, np.float64)), params, polarity)
    generated = classical_edges(images, params, polarity)
    exact = edge_of(images, lambda k: labels[k], lambda k: labels[k] > 0)
    return {
        "real": real,
        "generated": generated,
        "generated_mask": exact,
        **compare(real, generated),
        "images": {"generated": len(images), "real": len(seen)},
    }


def figure(result: dict) -> bytes:
    """PNG: the mean edge profiles (real, generated against the classical edge, generated against its masks)."""
    from drgan.core.io import figure_png

    def draw(plt):
        fig, axis = plt.subplots(figsize=(6, 4))
        for key, label, style in (
            ("real", "real patches (classical edge)", {"color": "black", "linewidth": 2}),
            ("generated", "generated (classical edge)", {"color": "tab:orange"}),
            ("generated_mask", "generated (its exact masks' edge)", {"color": "tab:blue", "linestyle": "--"}),
        ):
            side = result.get(key)
            if side:
                axis.plot(
                    side["distance_px"], side["profile"], label=f"{label}, {side['particles']} particles", **style
                )
        axis.axhline(0.5, color="grey", linewidth=0.5)
        axis.axvline(0.0, color="grey", linewidth=0.5)
        axis.set_xlabel("signed distance to the edge (px, > 0 outside)")
        axis.set_ylabel("grey (particle contrast units)")
        axis.legend(fontsize=8)
        axis.set_title("Mean particle edge: generated against real")
        fig.tight_layout()
        return fig

    return figure_png(draw)
