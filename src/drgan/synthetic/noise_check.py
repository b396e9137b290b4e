"""How noisy a generated set is against the real images it imitates (`generate`'s noise_check.json).

The FID and the grey checks hardly see pixel noise, and a segmenter trained on images much noisier than the real ones
learns from speckle the real images do not have: a GAN can learn a noise level several times the real one, and
renders at a low spp add their own grain on top (experiments/pipeline/README.md). This module
measures that ratio where generate can: the fine-scale noise (the image minus its Gaussian blur of HIGHPASS_PX, its
standard deviation) of the background beyond MARGIN px from any particle and of the particles' cores MARGIN px
inside, on up to SAMPLE generated images (their labels) and on the run's real train patches (drgan's classical
segmentation with the patch set's settings, at the render's px), each side's median over its images.
"""

from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)

HIGHPASS_PX = 1.0  # Gaussian sigma (px) of the blur subtracted: what remains is pixel-scale noise and grain
MARGIN = 3  # px kept from every outline on both sides (edges are not noise)
SAMPLE = 64  # images measured on each side (the first ones)
WARN_RATIO = 2.0  # a generated set this many times as noisy as the real patches, or this many times less, is named
MIN_PIXELS = 50  # a class needs this many pixels in an image to be measured there


def fine_detail(image: np.ndarray) -> np.ndarray:
    """``image`` (float grey) minus its Gaussian blur of HIGHPASS_PX, as float64: its pixel-scale noise and grain (and
    its edges); drgan.segmenters.noise_match reads its noise level from the same."""
    from scipy import ndimage as ndi

    image = np.asarray(image, dtype=np.float64)
    return image - ndi.gaussian_filter(image, HIGHPASS_PX)


def fine_noise(image: np.ndarray, particle: np.ndarray, margin: int = MARGIN) -> tuple[float, float]:
    """(background, particle) fine-scale noise of ``image`` (float grey): the standard deviation of `fine_detail`
    over the background beyond ``margin`` px from any ``particle`` pixel and over the particles ``margin`` px inside
    their outline (`away_from_edges`); NaN for a class with fewer than MIN_PIXELS such pixels."""
    from drgan.synthetic.grey_spread import away_from_edges

    detail = fine_detail(image)
    background, core = away_from_edges(particle, margin)

    def spread(where: np.ndarray) -> float:
        return float(detail[where].std()) if where.sum() >= MIN_PIXELS else float("nan")

    return spread(background), spread(core)


def _medians(rows: list[tuple[float, float]]) -> tuple[float | None, float | None]:
    values = np.asarray(rows, dtype=np.float64).reshape(-1, 2)
    out = []
    for column in values.T:
        column = column[np.isfinite(column)]
        out.append(round(float(np.median(column)), 5) if column.size else None)
    return out[0], out[1]


def compare(generated: list[tuple[float, float]], real: list[tuple[float, float]]) -> dict:
    """{"background": {...}, "particles": {...}}, each with the real and generated medians of `fine_noise` rows and
    their ratio (generated / real; None where either side has no measurement)."""
    gen_bg, gen_p = _medians(generated)
    real_bg, real_p = _medians(real)
    out = {}
    for name, g, r in (("background", gen_bg, real_bg), ("particles", gen_p, real_p)):
        ratio = round(g / r, 3) if g is not None and r else None
        out[name] = {"real": r, "generated": g, "ratio": ratio}
    return out


def real_noise(patches: np.ndarray, segment: dict, polarity: str) -> list[tuple[float, float]]:
    """`fine_noise` of the first SAMPLE real patches (already at the render's px), particles by drgan's classical
    segmentation with ``segment`` (the patch set's settings scaled to these px)."""
    from drgan.synthetic.grey_spread import classical_particles

    rows = []
    for patch in np.asarray(patches, dtype=np.float32)[:SAMPLE]:
        particle = classical_particles(patch, segment, polarity)
        if particle is not None:
            rows.append(fine_noise(patch, particle))
    return rows


def generated_noise(images: list[np.ndarray], labels: list[np.ndarray]) -> list[tuple[float, float]]:
    """`fine_noise` of generated images (float grey) by their exact labels."""
    return [fine_noise(image, np.asarray(label) > 0) for image, label in zip(images, labels)]


def summary_line(result: dict) -> str:
    """One line: "fine noise, generated / real: background 5.5 x, particles 3.6 x"."""

    def part(name: str) -> str:
        ratio = result[name]["ratio"]
        return f"{name} {ratio:.2g} x" if ratio is not None else f"{name} not measured"

    return f"fine noise, generated / real train patches: {part('background')}, {part('particles')}"


def off_by(result: dict) -> list[str]:
    """The classes whose ratio is WARN_RATIO or more away from 1, described."""
    found = []
    for name in ("background", "particles"):
        ratio = result[name]["ratio"]
        if ratio is not None and not 1 / WARN_RATIO < ratio < WARN_RATIO:
            found.append(f"{name} {ratio:.2g} x as noisy as the real train patches")
    return found


def log_result(result: dict) -> None:
    """The summary line, as a warning naming the classes WARN_RATIO or more off."""
    off = off_by(result)
    if off:
        log.warning(
            "%s: %s. A segmenter learns from the generated speckle; the GAN's learned noise is bounded by "
            "material.noise_sigma (the profile writes its maximum from the measured noise), and renderer.spp adds "
            "sampling noise on the particles", summary_line(result), "; ".join(off),
        )  # fmt: skip
    else:
        log.info("%s", summary_line(result))


def sample_sides(root, manifest: dict, backgrounds, polarity: str, resolution: int):
    """What a check of a complete generated set compares, or None without real train patches (``backgrounds``: a
    PatchSet or its folder): (the first SAMPLE real train patches area-averaged to the render's ``resolution`` as
    training saw them, the patch set's segmentation settings resolved on them at their own px and scaled to the render
    (as `GreySpread` does), the first SAMPLE synthetic images of ``manifest`` in folder ``root`` as float grey, and
    their exact labels)."""
    from pathlib import Path

    from skimage import io

    from drgan.data.classical import resolve_params
    from drgan.data.patches import PatchSet, resample_patches

    if backgrounds is None:
        return None
    patches = backgrounds if isinstance(backgrounds, PatchSet) else PatchSet.load(backgrounds)
    if not len(patches.train):
        return None
    size = int(np.shape(patches.train)[-1])
    own = list(np.asarray(patches.train, dtype=np.float32)[:SAMPLE])
    params, _ = resolve_params(own, patches.params.get("segment") or {}, polarity)
    seen = resample_patches(patches, resolution).train if size != resolution else np.asarray(own)
    root = Path(root)
    items = [e for e in manifest["entries"] if e["kind"] == "synthetic"][:SAMPLE]
    images = [io.imread(root / e["files"]["image"]).astype(np.float64) / 255.0 for e in items]
    labels = [np.asarray(io.imread(root / e["files"]["label"])) for e in items]
    return np.asarray(seen)[:SAMPLE], params.scaled(resolution / size), images, labels


def check_dataset(root, manifest: dict, backgrounds, polarity: str, resolution: int) -> dict | None:
    """The noise check of a complete generated set (``manifest``, in folder ``root``) against the real train patches
    of ``backgrounds`` (`sample_sides`; None, or a set without train patches: None returned): `compare`'s result with
    the sample sizes."""
    sides = sample_sides(root, manifest, backgrounds, polarity, resolution)
    if sides is None:
        return None
    seen, params, images, labels = sides
    real = real_noise(seen, params, polarity)
    result = compare(generated_noise(images, labels), real)
    return {**result, "images": {"generated": len(images), "real": len(real)}, "highpass_px": HIGHPASS_PX}
