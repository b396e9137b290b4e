"""Particle statistics of a segmentation against the truth: what a materials scientist reports, not DSC.

Per image, from an instance label image (0 background, k particle k): each particle's area (px), equivalent
diameter 2 sqrt(area / pi) (px; nm with a pixel size), axis ratio (major / minor axis of the ellipse with the same
second moments), and whether it touches the image border; and the image's particle count.

**Particles cut by the border** are treated alike on both sides: they count (a cut particle is still a particle in
the field of view, and both the prediction and the mask see the same cut), but they are left out of every size and
shape statistic (a cut particle's area is not its size).

**Specks** (`Particles.at_least`): components under a minimum area are left out of counts and sizes, on both sides
alike. Annotated masks hold them too (single pixels, brush strokes): the train masks of both TiO2 sets have a mode at
1 px^2 (6 % and 4.5 % of their components) and their log-area histogram's valley at 4-8 px^2 before the particles'
mode, so drgan.evaluate leaves out components under 8 px^2 (equivalent diameter < 3.2 px;
experiments/statistics/merges.md, "Specks are not particles: a minimum area on both sides, chosen on train
masks").

Comparisons (`compare_sizes`): median and mean diameter with their relative errors (prediction / truth - 1), the
total count's relative error and the per-image count errors, the two-sample Kolmogorov-Smirnov statistic (largest
gap between the two empirical CDFs) and the first Wasserstein distance (area between them, px), each with a
percentile bootstrap interval over images: images are resampled with replacement and both sides keep the same
images, because the images, not the particles, are the independent samples (particles of one image share its
sample, preparation and microscope settings).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drgan.core.errors import ConfigError, DataError

# Components under this many px^2 are specks: neither counted nor sized (drgan.evaluate's and drgan.analyze's
# min_area_px default, chosen on train masks: experiments/statistics/merges.md, "Specks are not particles"), and the
# U-Net's split leaves none of its own (drgan.segmenters.inference.split_touching)
SPECK_PX = 8.0


@dataclass(frozen=True)
class Particles:
    """The particles of one image: arrays of one value per particle."""

    area: np.ndarray  # px
    diameter: np.ndarray  # equivalent diameter, px
    axis_ratio: np.ndarray  # major / minor axis, >= 1
    border: np.ndarray  # bool: touches the image border

    @property
    def count(self) -> int:
        return len(self.area)

    def whole(self) -> Particles:
        """The particles that do not touch the image border (those whose size is measured)."""
        return self._subset(~self.border)

    def at_least(self, min_area: float) -> Particles:
        """The particles of at least ``min_area`` px^2: smaller components are specks, neither counted nor sized."""
        return self._subset(self.area >= min_area)

    def _subset(self, keep: np.ndarray) -> Particles:
        return Particles(self.area[keep], self.diameter[keep], self.axis_ratio[keep], self.border[keep])


def no_particles() -> Particles:
    """An image without particles."""
    return Particles(np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0, dtype=bool))


def read_particle_table(path: Path, diameter: str = "equivalent_diameter_px") -> dict[str, Particles]:
    """A particle table of drgan.analyze (particles.csv, particles_classical.csv: one row per particle, its image's
    id in ``image``) read back per image, in the file's order: the ``diameter`` column's sizes (an area of pi/4 d^2
    with them, so that a table sized at half contrast reads as its own sizes; an empty cell, e.g. nm without a pixel
    size, reads NaN), the axis ratios and the border flags. {} when there is no file or no particle; a DataError
    naming the file and the column when a table with particles lacks one."""
    from drgan.core.io import read_csv

    rows, columns = read_csv(path)
    found: dict[str, list[tuple[float, float, bool]]] = {}
    missing = [c for c in ("image", diameter, "axis_ratio", "touches_border") if c not in columns]
    if rows and missing:  # a table without particles has nothing to read, whatever its header
        raise DataError(f"{path}: expected the columns {', '.join(missing)} of an analyze particle table")
    for row in rows:
        cell = row[diameter]
        found.setdefault(row["image"], []).append(
            (float(cell) if cell else np.nan, float(row["axis_ratio"]), row["touches_border"] == "True")
        )
    tables = {}
    for image_id, values in found.items():
        d, ratio, border = (np.asarray(v) for v in zip(*values))
        tables[image_id] = Particles(
            np.pi / 4.0 * d**2, d.astype(np.float64), ratio.astype(np.float64), border.astype(bool)
        )
    return tables


def particles(labels: np.ndarray) -> Particles:
    """The particles of an instance label image (0 background, k > 0 one particle each; ids need not be dense)."""
    from skimage.measure import regionprops

    labels = np.asarray(labels)
    if labels.ndim != 2 or not np.issubdtype(labels.dtype, np.integer) or (labels.size and labels.min() < 0):
        raise ConfigError(
            f"labels: expected a 2-D image of integer instance ids >= 0, got {labels.dtype} {labels.shape}"
        )
    h, w = labels.shape
    area, diameter, ratio, border = [], [], [], []
    for region in regionprops(labels):
        a = float(region.area)
        r0, c0, r1, c1 = region.bbox
        major, minor = float(region.axis_major_length), float(region.axis_minor_length)
        area.append(a)
        diameter.append(2.0 * np.sqrt(a / np.pi))
        ratio.append(major / minor if minor > 0 else np.inf)
        border.append(r0 == 0 or c0 == 0 or r1 == h or c1 == w)
    return Particles(np.array(area), np.array(diameter), np.array(ratio), np.array(border, dtype=bool))


def diameters_of(labels: Sequence[np.ndarray]) -> np.ndarray:
    """Equivalent-circle diameters (px) of the instances of ``labels`` (label images, sized by `particles`,
    border-cut ones included), pooled."""
    return np.concatenate([particles(label).diameter for label in labels] or [np.zeros(0)])


def median_diameter(labels: Sequence[np.ndarray]) -> float:
    """Median of `diameters_of` ``labels``; nan without any. The segmenter's split calibration and working scale
    compare it."""
    diameters = diameters_of(labels)
    return float(np.median(diameters)) if diameters.size else float("nan")


def area_median(diameters: np.ndarray) -> float:
    """The smallest diameter d such that the particles of diameter <= d hold at least half of the particles' area
    (the area-weighted median, as a D50 by volume is for sieves): one large particle among specks keeps its size."""
    d = np.sort(np.asarray(diameters, float))
    if not d.size:
        return float("nan")
    share = np.cumsum(d**2) / np.sum(d**2)
    return float(d[np.searchsorted(share, 0.5)])


def ks_statistic(a: np.ndarray, b: np.ndarray) -> float:
    """Two-sample Kolmogorov-Smirnov statistic: the largest gap between the empirical CDFs of ``a`` and ``b``."""
    a, b = np.sort(np.asarray(a, float)), np.sort(np.asarray(b, float))
    if not len(a) or not len(b):
        return float("nan")
    grid = np.concatenate([a, b])
    gap = np.searchsorted(a, grid, side="right") / len(a) - np.searchsorted(b, grid, side="right") / len(b)
    return float(np.abs(gap).max())


def wasserstein1(a: np.ndarray, b: np.ndarray) -> float:
    """First Wasserstein distance between the empirical distributions of ``a`` and ``b``: the area between their
    CDFs (in the values' unit)."""
    a, b = np.sort(np.asarray(a, float)), np.sort(np.asarray(b, float))
    if not len(a) or not len(b):
        return float("nan")
    grid = np.sort(np.concatenate([a, b]))
    widths = np.diff(grid)
    cdf_a = np.searchsorted(a, grid[:-1], side="right") / len(a)
    cdf_b = np.searchsorted(b, grid[:-1], side="right") / len(b)
    return float(np.sum(np.abs(cdf_a - cdf_b) * widths))


def _point(pred: Sequence[Particles], true: Sequence[Particles]) -> dict[str, float]:
    """The statistics of one set of images (pred[i] and true[i] are image i)."""
    d_pred = np.concatenate([p.whole().diameter for p in pred] or [np.zeros(0)])
    d_true = np.concatenate([t.whole().diameter for t in true] or [np.zeros(0)])
    n_pred, n_true = sum(p.count for p in pred), sum(t.count for t in true)
    nan = float("nan")
    median_p, median_t = (float(np.median(d)) if len(d) else nan for d in (d_pred, d_true))
    mean_p, mean_t = (float(np.mean(d)) if len(d) else nan for d in (d_pred, d_true))
    return {
        "median_diameter": median_p,
        "median_diameter_true": median_t,
        "mean_diameter": mean_p,
        "mean_diameter_true": mean_t,
        "median_error": median_p / median_t - 1.0 if median_t else nan,
        "mean_error": mean_p / mean_t - 1.0 if mean_t else nan,
        "count": float(n_pred),
        "count_true": float(n_true),
        "count_error": n_pred / n_true - 1.0 if n_true else nan,
        "ks": ks_statistic(d_pred, d_true),
        "w1": wasserstein1(d_pred, d_true),
    }


def bootstrap(
    n_images: int, statistic, n_boot: int = 1000, seed: int = 0, level: float = 0.95
) -> dict[str, dict[str, float]]:
    """{key: {"value", "low", "high"}}: ``statistic(indices)`` -> {key: number} of the images 0 .. n_images - 1, with
    percentile intervals (``level``) over ``n_boot`` resamples of the images with replacement (0: no intervals)."""
    value = statistic(np.arange(n_images))
    result = {key: {"value": v, "low": float("nan"), "high": float("nan")} for key, v in value.items()}
    if n_boot > 0:
        rng = np.random.default_rng(seed)
        draws = {key: [] for key in value}
        for _ in range(int(n_boot)):
            for key, v in statistic(rng.integers(n_images, size=n_images)).items():
                draws[key].append(v)
        tail = 100.0 * (1.0 - level) / 2.0
        for key, values in draws.items():
            values = np.asarray(values, float)
            values = values[np.isfinite(values)]
            if len(values):
                result[key]["low"], result[key]["high"] = (float(x) for x in np.percentile(values, [tail, 100 - tail]))
    return result


def interval_text(cell: Mapping, render) -> str:
    """A `bootstrap` cell as text: ``render(value)``, then `` [render(low), render(high)]`` where the interval is
    finite (analyze's and evaluate's tables; each passes its own number format)."""
    text = render(cell["value"])
    low = cell.get("low")
    if low is not None and np.isfinite(low):
        text += f" [{render(low)}, {render(cell['high'])}]"
    return text


def compare_sizes(
    pred: Sequence[Particles], true: Sequence[Particles], n_boot: int = 1000, seed: int = 0, level: float = 0.95
) -> dict[str, dict[str, float]]:
    """{statistic: {"value", "low", "high"}}: the statistics of the predicted particles against the true ones over
    all images, with percentile bootstrap intervals (``level``) over images (``n_boot`` resamples; 0: none)."""
    if len(pred) != len(true) or not len(true):
        raise ConfigError(f"compare_sizes: expected the same images on both sides, got {len(pred)} and {len(true)}")
    return bootstrap(
        len(true), lambda pick: _point([pred[i] for i in pick], [true[i] for i in pick]), n_boot, seed, level
    )


def count_errors(pred: Sequence[Particles], true: Sequence[Particles]) -> np.ndarray:
    """Per image: predicted count minus true count."""
    return np.array([p.count - t.count for p, t in zip(pred, true)], dtype=float)


def pooled(images: Mapping[str, Particles] | Sequence[Particles], field: str = "diameter") -> np.ndarray:
    """One value per whole particle (not touching the border) over all images: for histograms."""
    items = images.values() if isinstance(images, Mapping) else images
    return np.concatenate([getattr(p.whole(), field) for p in items] or [np.zeros(0)])
