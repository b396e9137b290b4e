"""Size distributions of a layout (drgan.scene.layout): particle diameters, the ``scale`` column of Phi, in px.

Each is a frozen dataclass checked at construction, built from a ``conf/gan/size/*.yaml`` config whose ``_target_``
names it (`drgan.scene.layout.size_from_config`); ``sample`` draws the diameters, ``moments`` gives their mean and
std. numpy only.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

from drgan.core.errors import ConfigError, check_non_negative, check_positive, finite_field

__all__ = ["NormalSize", "LognormalSize", "BimodalSize", "SizeDistribution"]


def _normal_pdf(x: float) -> float:
    return math.exp(-0.5 * x * x) / math.sqrt(2.0 * math.pi)


def _normal_cdf(x: float) -> float:
    return 0.5 * (1.0 + math.erf(x / math.sqrt(2.0)))


def _truncated_normal_moments(mean: float, std: float, min_size: float) -> tuple[float, float]:
    """Mean and std of N(mean, std^2) restricted to [min_size, inf) (standard closed form)."""
    if std == 0.0:
        return mean, 0.0
    alpha = (min_size - mean) / std
    kept = 1.0 - _normal_cdf(alpha)  # > 0.5 because mean > min_size is enforced
    ratio = _normal_pdf(alpha) / kept
    truncated_mean = mean + std * ratio
    truncated_var = std * std * (1.0 + alpha * ratio - ratio * ratio)
    return truncated_mean, math.sqrt(max(truncated_var, 0.0))


def _sample_truncated_normal(
    rng: np.random.Generator, mean: np.ndarray | float, std: np.ndarray | float, shape: tuple[int, ...], min_size: float
) -> np.ndarray:
    """Normal draws below min_size are drawn again (rejection), so the density above min_size keeps its shape.

    Clipping would instead pile probability mass exactly at min_size. mean > min_size is enforced by the
    callers, so each round keeps more than half of the redrawn values and the loop ends after a few rounds.
    """
    mean_arr = np.broadcast_to(np.asarray(mean, dtype=np.float64), shape)
    std_arr = np.broadcast_to(np.asarray(std, dtype=np.float64), shape)
    values = rng.normal(mean_arr, std_arr)
    too_small = values < min_size
    while too_small.any():
        values[too_small] = rng.normal(mean_arr[too_small], std_arr[too_small])
        too_small = values < min_size
    return values


def _as_shape(shape: int | tuple[int, ...]) -> tuple[int, ...]:
    return (int(shape),) if isinstance(shape, numbers.Integral) else tuple(int(side) for side in shape)


@dataclass(frozen=True)
class NormalSize:
    """Normal diameters in px, truncated below at ``min_size`` by resampling (not clipping).

    mean, std: of the untruncated normal, px (mean > min_size, std >= 0).
    min_size: smallest diameter allowed, px (> 0); draws below it are drawn again.
    """

    mean: float
    std: float
    min_size: float = 1.0

    def __post_init__(self) -> None:
        check_positive("NormalSize", "mean", self.mean)
        check_non_negative("NormalSize", "std", self.std)
        check_positive("NormalSize", "min_size", self.min_size)
        if self.mean <= self.min_size:
            raise ConfigError(
                f"NormalSize.mean must be > min_size ({self.min_size}) so truncation keeps most draws, got {self.mean}"
            )

    def sample(self, rng: np.random.Generator, shape: int | tuple[int, ...]) -> np.ndarray:
        """Diameters in px, float64 array of ``shape``, all >= min_size."""
        return _sample_truncated_normal(rng, self.mean, self.std, _as_shape(shape), self.min_size)

    def moments(self) -> tuple[float, float]:
        """(mean, std) in px of the truncated distribution (equal to mean, std when truncation is negligible)."""
        return _truncated_normal_moments(float(self.mean), float(self.std), float(self.min_size))


@dataclass(frozen=True)
class LognormalSize:
    """Lognormal diameters in px: log(diameter) ~ N(log(median), sigma^2).

    median: median diameter, px (> 0).
    sigma: standard deviation of log(diameter), dimensionless (> 0); 0.2 means a spread of about 20 %.
    """

    median: float
    sigma: float

    def __post_init__(self) -> None:
        check_positive("LognormalSize", "median", self.median)
        check_positive("LognormalSize", "sigma", self.sigma)

    def sample(self, rng: np.random.Generator, shape: int | tuple[int, ...]) -> np.ndarray:
        """Diameters in px, float64 array of ``shape``, all > 0."""
        return rng.lognormal(math.log(self.median), self.sigma, _as_shape(shape))

    def moments(self) -> tuple[float, float]:
        """(mean, std) in px: median * exp(sigma^2 / 2) and mean * sqrt(exp(sigma^2) - 1)."""
        mean = self.median * math.exp(0.5 * self.sigma**2)
        return mean, mean * math.sqrt(math.expm1(self.sigma**2))


@dataclass(frozen=True)
class BimodalSize:
    """Mixture of two normals in px, each truncated below at ``min_size`` by resampling.

    mean1, std1 / mean2, std2: the two untruncated modes, px (mean > min_size, std >= 0).
    weight1: probability of the first mode, in [0, 1].
    min_size: smallest diameter allowed, px (> 0).
    """

    mean1: float
    std1: float
    mean2: float
    std2: float
    weight1: float
    min_size: float = 1.0

    def __post_init__(self) -> None:
        for name in ("mean1", "mean2", "min_size"):
            check_positive("BimodalSize", name, getattr(self, name))
        for name in ("std1", "std2"):
            check_non_negative("BimodalSize", name, getattr(self, name))
        if not 0.0 <= finite_field("BimodalSize", "weight1", self.weight1) <= 1.0:
            raise ConfigError(f"BimodalSize.weight1 must be in [0, 1], got {self.weight1!r}")
        for name in ("mean1", "mean2"):
            if getattr(self, name) <= self.min_size:
                raise ConfigError(f"BimodalSize.{name} must be > min_size ({self.min_size}), got {getattr(self, name)}")

    def sample(self, rng: np.random.Generator, shape: int | tuple[int, ...]) -> np.ndarray:
        """Diameters in px, float64 array of ``shape``, all >= min_size."""
        shape = _as_shape(shape)
        first_mode = rng.random(shape) < self.weight1
        mean = np.where(first_mode, self.mean1, self.mean2)
        std = np.where(first_mode, self.std1, self.std2)
        return _sample_truncated_normal(rng, mean, std, shape, self.min_size)

    def moments(self) -> tuple[float, float]:
        """(mean, std) in px of the mixture of the two truncated modes."""
        mean1, std1 = _truncated_normal_moments(float(self.mean1), float(self.std1), float(self.min_size))
        mean2, std2 = _truncated_normal_moments(float(self.mean2), float(self.std2), float(self.min_size))
        w1, w2 = float(self.weight1), 1.0 - float(self.weight1)
        mean = w1 * mean1 + w2 * mean2
        second_moment = w1 * (std1**2 + mean1**2) + w2 * (std2**2 + mean2**2)
        return mean, math.sqrt(max(second_moment - mean**2, 0.0))


SizeDistribution = NormalSize | LognormalSize | BimodalSize
