"""Measuring unannotated particle images: the numbers a material config needs, measured without masks.

Every estimator works on grey images in [0, 1] (drgan.data.images.read_grey) and the particles' polarity
(drgan.data.polarity). The pieces, in the order `python -m drgan.profile` runs them (the mean particle edge and its
fringe are drgan.data.particle_edge's):

- `segment_image`: drgan.data.classical (the particle scale measured first, every length set from it), keeping the
  segments of plausible area;
- `particle_table`: equivalent diameter, centroid, axis ratio, border contact, contact with another segment;
- `background_noise`: background grey (median of background pixels), noise sigma (robust MAD of the
  high-pass residual on background pixels, corrected for what the high-pass removes) and grain (the stddev
  of the Gaussian whose blurred white noise, through the same high-pass, has the same lag-1 autocorrelation);
- `fit_sizes`: normal, lognormal and two-component lognormal mixture fitted to the diameters, chosen by BIC;
- `patch_counts`: particles whose centroid lies inside each 256 px window of a grid;
- `clark_evans`: nearest-neighbour ratio of the centroids (< 1 clustered, 1 random, > 1 regular);
- `pixel_size_nm`: TIFF resolution tags, or the Zeiss CZ_SEM tag's image pixel size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from drgan.core.errors import DataError
from drgan.data.classical import Segmentation, SegmentParams, segment_with_report
from drgan.data.patches import STRIDE, full_particle_counts, window_starts

# The high-pass that isolates noise from the background's slow shading: image minus its Gaussian blur.
HIGHPASS_SIGMA = 3.0  # px
# Background pixels: outside the particle foreground grown by this many px (the high-pass spreads edges).
BACKGROUND_MARGIN = 6  # px

# --- segmentation -----------------------------------------------------------------------------------------


def segment_image(image: np.ndarray, params: SegmentParams, polarity: str) -> Segmentation:
    """drgan.data.classical's segmentation with resolved ``params`` (`Segmentation`), keeping only segments of
    plausible area."""
    found = segment_with_report(image, params, polarity)
    areas = np.bincount(found.labels.ravel())
    keep = (areas >= params.min_area) & (areas <= params.max_area)
    keep[0] = False
    return found._replace(labels=np.where(keep[found.labels], found.labels, 0).astype(np.int32))


PARTICLE_COLUMNS = ("area_px", "diameter_px", "row", "col", "axis_ratio", "touches_border", "touches_other")


def particle_table(labels: np.ndarray) -> dict[str, np.ndarray]:
    """Per segment: area, equivalent diameter 2 sqrt(area / pi), centroid, major/minor axis ratio, and whether
    it touches the image border or another segment (8-neighbourhood)."""
    from skimage.measure import regionprops

    h, w = labels.shape
    # A segment touches another when a pixel of it has an 8-neighbour of a different non-zero label.
    grown_max = ndi.grey_dilation(labels, size=3)
    grown_min = -ndi.grey_dilation(-np.where(labels > 0, labels, labels.max() + 1), size=3)
    contact = (labels > 0) & ((grown_max != labels) | (grown_min != labels))
    touching = set(np.unique(labels[contact]).tolist())
    rows = {c: [] for c in PARTICLE_COLUMNS}
    for region in regionprops(labels):
        r0, c0, r1, c1 = region.bbox
        minor = region.axis_minor_length
        rows["area_px"].append(region.area)
        rows["diameter_px"].append(2.0 * math.sqrt(region.area / math.pi))
        rows["row"].append(region.centroid[0])
        rows["col"].append(region.centroid[1])
        rows["axis_ratio"].append(region.axis_major_length / minor if minor > 0 else np.inf)
        rows["touches_border"].append(r0 == 0 or c0 == 0 or r1 == h or c1 == w)
        rows["touches_other"].append(region.label in touching)
    return {c: np.asarray(v, dtype=bool if c.startswith("touches") else np.float64) for c, v in rows.items()}


def component_table(mask: np.ndarray, min_area: int = 1, max_area: int | None = None) -> dict[str, np.ndarray]:
    """`particle_table` of a binary mask's 4-connected components of plausible area (the masks' side of the check)."""
    labels, _ = ndi.label(np.asarray(mask, bool))
    areas = np.bincount(labels.ravel())
    keep = (areas >= min_area) & (areas <= (max_area if max_area is not None else areas.max()))
    keep[0] = False
    return particle_table(np.where(keep[labels], labels, 0).astype(np.int32))


# --- particles per window ---------------------------------------------------------------------------------


def patch_counts(
    rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int], size: int = 256, stride: int | None = None
) -> np.ndarray:
    """Particles whose centroid lies inside each size x size window of the grid (stride size // 2): a flat array."""
    stride = stride or size // 2
    r0 = window_starts(shape[0], size, stride)[:, None]
    c0 = window_starts(shape[1], size, stride)[:, None]
    rows, cols = np.asarray(rows)[None, :], np.asarray(cols)[None, :]
    in_rows = ((rows >= r0) & (rows < r0 + size)).astype(np.int64)  # (R, K)
    in_cols = ((cols >= c0) & (cols < c0 + size)).astype(np.int64)  # (C, K)
    return (in_rows @ in_cols.T).ravel()


def whole_particle_counts(boxes: np.ndarray, shape: tuple[int, int], size: int, stride: int = STRIDE):
    """Particles fully displayed (bounding box off every window edge, as training mines: drgan.data.patches) in each
    ``size`` px window of the training grid of one image: a flat array. ``boxes``: particle_boxes of its segments."""
    rows, cols = window_starts(shape[0], size, stride), window_starts(shape[1], size, stride)
    if not len(rows) or not len(cols):
        return np.zeros(0, np.int64)
    return full_particle_counts(boxes, rows, cols, size, size).ravel()


VIEW_EXTENT_FRACTION = 0.6  # a particle's median extent may fill at most this much of a training window's width


def view_window(extent_px: float, patch: int, shortest_side: int) -> int:
    """Real px a training window covers so that a particle of ``extent_px`` (largest extent) fits in one with room
    around it: ``patch`` (the render size), doubled while the particle fills more than VIEW_EXTENT_FRACTION of it
    and the doubled window still fits in the shortest image side. Windows wider than the render are area-averaged
    to it (the GAN sees large particles smaller; drgan.data.patches.resample_patches)."""
    window = int(patch)
    while extent_px > VIEW_EXTENT_FRACTION * window and 2 * window <= shortest_side:
        window *= 2
    return window


EDGE_SMOOTH_PX = 0.7  # Gaussian smoothing before the edge gradient (noise), taken out of the result in quadrature
EDGE_RANGE_PX = 13  # window whose grey range is an edge's contrast (+-6 px: +-2 sigma of a 3 px blur)


def edge_blur(image: np.ndarray, foreground: np.ndarray, exclude: np.ndarray | None = None) -> float | None:
    """How blurred the particles' outlines are: the standard deviation (px) of the Gaussian that, applied to a step
    of the same contrast, gives the same steepest slope. At each outline pixel (foreground pixels with a background
    neighbour, away from the border and ``exclude``d pixels) the contrast is the grey range within EDGE_RANGE_PX and
    the slope the largest gradient within 2 px; a blurred step of contrast C and sigma s has slope C / (s sqrt(2 pi)).
    The range rather than particle-minus-background grey, so that a bright rim (SEM edge effect) or a dark centre
    counts as the edge's own contrast. Median over the outline pixels; None without 50 of them."""
    fg = np.asarray(foreground, bool)
    smooth = ndi.gaussian_filter(np.asarray(image, np.float64), EDGE_SMOOTH_PX)
    slope = ndi.maximum_filter(np.hypot(ndi.sobel(smooth, 0), ndi.sobel(smooth, 1)) / 8.0, size=5)
    contrast = ndi.maximum_filter(smooth, size=EDGE_RANGE_PX) - ndi.minimum_filter(smooth, size=EDGE_RANGE_PX)
    outline = fg & ~ndi.binary_erosion(fg)
    band = EDGE_RANGE_PX // 2
    outline[:band], outline[-band:], outline[:, :band], outline[:, -band:] = False, False, False, False
    if exclude is not None:
        outline &= ~ndi.binary_dilation(np.asarray(exclude, bool), iterations=band)
    outline &= slope > 0
    if outline.sum() < 50:
        return None
    measured = float(np.median(contrast[outline] / (np.sqrt(2 * np.pi) * slope[outline])))
    return float(np.sqrt(max(measured**2 - EDGE_SMOOTH_PX**2, 0.0)))


def clark_evans(rows: np.ndarray, cols: np.ndarray, area: float) -> float | None:
    """Clark-Evans ratio: mean nearest-neighbour distance over its value for a Poisson pattern, 0.5 / sqrt(density).

    < 1: clustered (agglomerates), ~1: random, > 1: regular. None with fewer than 3 points. No edge correction:
    edges lengthen nearest-neighbour distances slightly (the ratio reads a little high)."""
    points = np.column_stack([rows, cols])
    if len(points) < 3:
        return None
    distances, _ = cKDTree(points).query(points, k=2)
    return float(distances[:, 1].mean() / (0.5 / math.sqrt(len(points) / area)))


# --- background and noise ---------------------------------------------------------------------------------


def highpass(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image, np.float64)
    return image - ndi.gaussian_filter(image, HIGHPASS_SIGMA, mode="reflect")


def background_mask(foreground: np.ndarray, margin: int = BACKGROUND_MARGIN) -> np.ndarray:
    """Pixels farther than ``margin`` px from any foreground pixel, and from the image border."""
    far = ndi.distance_transform_edt(~np.asarray(foreground, bool)) > margin
    border = np.zeros_like(far)
    m = int(2 * HIGHPASS_SIGMA)
    border[m:-m, m:-m] = True
    return far & border


def lag1_autocorrelation(residual: np.ndarray, mask: np.ndarray) -> float:
    """Correlation of horizontally and vertically adjacent residual values, both pixels in mask, outliers clipped."""
    mad = _mad(residual[mask])
    r = np.clip(residual - np.median(residual[mask]), -5 * mad, 5 * mad) if mad > 0 else residual
    num, den = 0.0, 0.0
    for a, b, ma, mb in ((r[:, :-1], r[:, 1:], mask[:, :-1], mask[:, 1:]), (r[:-1], r[1:], mask[:-1], mask[1:])):
        both = ma & mb
        num += float((a[both] * b[both]).sum())
        den += 0.5 * float((a[both] ** 2).sum() + (b[both] ** 2).sum())
    return num / den if den > 0 else 0.0


def _mad(values: np.ndarray) -> float:
    values = np.asarray(values, np.float64)
    return float(1.4826 * np.median(np.abs(values - np.median(values)))) if values.size else 0.0


GRAIN_GRID = np.round(np.arange(0.0, 4.01, 0.1), 2)  # px


@lru_cache(maxsize=1)
def _grain_calibration() -> tuple[np.ndarray, np.ndarray]:
    """(lag-1 autocorrelation, residual std / noise std) of Gaussian-blurred white noise through `highpass`,
    per grain in GRAIN_GRID (fixed seed: the same table every run)."""
    rng = np.random.default_rng(0)
    white = rng.standard_normal((384, 384))
    mask = np.zeros(white.shape, bool)
    mask[16:-16, 16:-16] = True
    rho, ratio = [], []
    for grain in GRAIN_GRID:
        noise = ndi.gaussian_filter(white, grain, mode="wrap") if grain > 0 else white
        noise = noise / noise[mask].std()
        residual = highpass(noise)
        rho.append(lag1_autocorrelation(residual, mask))
        ratio.append(_mad(residual[mask]))
    # Below ~0.3 px a sampled Gaussian barely correlates neighbours; keep the table increasing for interpolation.
    return np.maximum.accumulate(np.asarray(rho)), np.asarray(ratio)


@dataclass(frozen=True)
class NoiseEstimate:
    background_grey: float  # median of background pixels, in the image's own polarity, [0, 1]
    noise_sigma: float  # std of the noise, grey levels in [0, 1]
    residual_sigma: float  # robust std (MAD) of the high-pass residual, before the correction
    lag1_autocorrelation: float  # of the residual on background pixels
    grain_px: float  # stddev of the Gaussian that correlates white noise the same way, px (0 = white)
    background_fraction: float  # share of the pixels used as background

    def as_dict(self) -> dict:
        return {k: round(float(v), 6) for k, v in self.__dict__.items()}


def background_noise(
    images: list[np.ndarray], foregrounds: list[np.ndarray], margin: int = BACKGROUND_MARGIN
) -> NoiseEstimate:
    """Background grey level, noise sigma and grain from the background pixels of all images (see module doc)."""
    grey, residual, used, total = [], [], 0, 0
    rhos, weights = [], []
    for image, foreground in zip(images, foregrounds):
        mask = background_mask(foreground, margin)
        total += mask.size
        if mask.sum() < 100:
            continue
        used += int(mask.sum())
        grey.append(np.asarray(image)[mask])
        r = highpass(image)
        residual.append(r[mask] - np.median(r[mask]))
        rhos.append(lag1_autocorrelation(r, mask))
        weights.append(float(mask.sum()))
    if not grey and margin > 1:  # particles cover nearly everything: take the background closer to them
        return background_noise(images, foregrounds, margin=1)
    if not grey:
        raise DataError(
            "profile: no image has background pixels (at least 100 farther than "
            f"{BACKGROUND_MARGIN} px from every particle): cannot measure the background and noise"
        )
    rho = float(np.average(rhos, weights=weights))
    table_rho, table_ratio = _grain_calibration()
    # The autocorrelation grows with the grain; interpolate the grain (clamped to the table's range).
    grain = float(np.interp(rho, table_rho, GRAIN_GRID))
    ratio = float(np.interp(grain, GRAIN_GRID, table_ratio))
    residual_sigma = _mad(np.concatenate(residual))
    return NoiseEstimate(
        float(np.median(np.concatenate(grey))), residual_sigma / ratio, residual_sigma, rho, grain, used / total
    )


# --- size distribution ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SizeFit:
    kind: str  # normal | lognormal | bimodal
    params: dict  # normal: mean, std; lognormal: median, sigma; bimodal: weight1, median1, sigma1, median2, sigma2
    log_likelihood: float
    n_params: int
    bic: float

    def pdf(self, d: np.ndarray) -> np.ndarray:
        d = np.asarray(d, np.float64)
        p = self.params
        if self.kind == "normal":
            return _normal_pdf(d, p["mean"], p["std"])
        with np.errstate(divide="ignore", invalid="ignore"):
            logd = np.log(np.where(d > 0, d, np.nan))
            if self.kind == "lognormal":
                out = _normal_pdf(logd, math.log(p["median"]), p["sigma"]) / d
            else:
                out = (
                    p["weight1"] * _normal_pdf(logd, math.log(p["median1"]), p["sigma1"])
                    + (1 - p["weight1"]) * _normal_pdf(logd, math.log(p["median2"]), p["sigma2"])
                ) / d
        return np.nan_to_num(out)

    def as_dict(self) -> dict:
        return {
            "kind": self.kind,
            "params": {k: round(float(v), 5) for k, v in self.params.items()},
            "log_likelihood": round(self.log_likelihood, 3),
            "n_params": self.n_params,
            "bic": round(self.bic, 3),
        }


def _normal_pdf(x, mean, std):
    return np.exp(-0.5 * ((x - mean) / std) ** 2) / (std * math.sqrt(2 * math.pi))


MIN_SPREAD = 0.05  # least relative spread of a fit (std / mean, sigma of log d)
MIN_MIXTURE = 20  # fewer diameters than this: no two-component fit


def fit_sizes(diameters: np.ndarray, seed: int = 0) -> tuple[list[SizeFit], SizeFit]:
    """Fit normal, lognormal and (from MIN_MIXTURE diameters) a two-lognormal mixture to the diameters (px) by
    maximum likelihood; pick the lowest BIC = k ln(n) - 2 ln(L), all likelihoods in diameter space (so they
    compare)."""
    d = np.asarray(diameters, np.float64)
    d = d[np.isfinite(d) & (d > 0)]
    if d.size == 0:
        raise DataError("profile: no particle diameter measured: nothing to fit a size distribution to")
    n, logd = d.size, np.log(d)

    def make(kind, params, loglik, k):
        return SizeFit(kind, params, float(loglik), k, float(k * math.log(n) - 2 * loglik))

    # A few particles (one image of a user's) may all measure alike: spreads below MIN_SPREAD are kept at it.
    mean = float(d.mean())
    std = max(float(d.std()), MIN_SPREAD * mean)
    normal = make("normal", {"mean": mean, "std": std}, np.log(_normal_pdf(d, mean, std)).sum(), 2)
    mu, sigma = float(logd.mean()), max(float(logd.std()), MIN_SPREAD)
    lognormal = make(
        "lognormal", {"median": math.exp(mu), "sigma": sigma}, (np.log(_normal_pdf(logd, mu, sigma)) - logd).sum(), 2
    )
    fits = [normal, lognormal] + ([_fit_mixture(logd, seed, make)] if n >= MIN_MIXTURE else [])
    return fits, min(fits, key=lambda f: f.bic)


def _fit_mixture(logd: np.ndarray, seed: int, make) -> SizeFit:
    from sklearn.mixture import GaussianMixture

    gm = GaussianMixture(2, covariance_type="full", n_init=5, random_state=seed, reg_covar=1e-6).fit(logd[:, None])
    order = np.argsort(gm.means_.ravel())
    w = gm.weights_[order]
    m = gm.means_.ravel()[order]
    s = np.sqrt(gm.covariances_.ravel()[order])
    loglik = float(gm.score(logd[:, None]) * logd.size - logd.sum())
    return make(
        "bimodal",
        {
            "weight1": float(w[0]),
            "median1": float(math.exp(m[0])),
            "sigma1": float(s[0]),
            "median2": float(math.exp(m[1])),
            "sigma2": float(s[1]),
        },
        loglik,
        5,
    )


def lognormal_to_normal(median: float, sigma: float) -> tuple[float, float]:
    """Mean and std of a lognormal given its median and log-sigma (the size group's bimodal is a normal mixture)."""
    mean = median * math.exp(sigma**2 / 2)
    return mean, mean * math.sqrt(math.exp(sigma**2) - 1)


# --- shape, placement, pixel size -------------------------------------------------------------------------


def mesh_kind(axis_ratio: float) -> str:
    """sphere below 1.3, rod above 2.5 (wires, needles), potato between (rounded, irregular)."""
    if axis_ratio < 1.3:
        return "sphere"
    return "rod" if axis_ratio > 2.5 else "potato"


def placement_kind(touching_fraction: float, clark_evans_ratio: float | None) -> str:
    """poisson (3-D agglomerates) when particles cluster: over 30 % touch another, or Clark-Evans < 0.9."""
    clustered = touching_fraction > 0.3 or (clark_evans_ratio is not None and clark_evans_ratio < 0.9)
    return "poisson" if clustered else "random_2d"


_INCH_NM, _CM_NM = 2.54e7, 1e7


def pixel_size_nm(path: str | Path) -> tuple[float | None, str]:
    """(pixel size in nm or None, where it came from) from a TIFF's Zeiss CZ_SEM tag or resolution tags."""
    path = Path(path)
    if path.suffix.lower() not in (".tif", ".tiff"):
        return None, "unknown (not a TIFF)"
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            tags = tif.pages[0].tags
            cz = tags.get(34118)
            if cz is not None and isinstance(cz.value, dict) and "ap_image_pixel_size" in cz.value:
                _, value, unit = cz.value["ap_image_pixel_size"]
                factor = {"pm": 1e-3, "nm": 1.0, "µm": 1e3, "um": 1e3, "mm": 1e6}.get(unit)
                if factor and float(value) > 0:
                    return float(value) * factor, "CZ_SEM ap_image_pixel_size"
            res, unit = tags.get(282), tags.get(296)
            if res is not None and unit is not None and int(unit.value) in (2, 3):
                num, den = res.value
                per_unit = num / den if den else 0.0
                # 72/96/150/300 per inch are display or print resolutions, not the microscope's pixel.
                if per_unit > 0 and not (int(unit.value) == 2 and per_unit in (72, 96, 150, 300)):
                    return (_INCH_NM if int(unit.value) == 2 else _CM_NM) / per_unit, "XResolution/ResolutionUnit"
    except Exception as exc:  # metadata is optional: an unreadable tag must not stop the profile
        return None, f"unknown ({type(exc).__name__} reading TIFF tags)"
    return None, "unknown"
