"""FID and KID of grey microscope images from their features (drgan.metrics.inception), offline and without
clean-fid.

Two ideas are taken from clean-fid (Parmar et al., 2022): the "clean" resize (drgan.metrics.inception.clean_resize)
and a numerically robust Frechet distance; plus its cached reference statistics, keyed by dataset, mode and
resolution. clean-fid itself is not used: it downloads its Inception weights at run time and imports torchvision.

KID's spread: ``kid`` draws its subsets at half the smaller sample by default, so that they differ and the std
over subsets says how much the estimate moves with the sample (a subset as large as the sample is the whole set
each time, and its std is 0 whatever the data).

The FID's own spread: ``fid_bootstrap_std`` resamples the generated features' rows with replacement and recomputes
the FID against the same real statistics (``ResampledFID``: what depends only on the real features and the full
generated set is computed once, each resample costs one symmetric eigendecomposition of min(N, D)), 10 resamples
by default. It is the spread that comes from drawing the generated sample; the real sample is the same for every
epoch of a run. The best-epoch rule (drgan.callbacks.best_epoch) compares two epochs' FIDs against it. Measured on
the mined TiO2 patches split in halves (67 against 67 SEM, 63 against 63 TSEM): FID 52.7 +- 2.1 and 78.9 +- 2.9
(100 resamples; 10 give 2.4 and 2.7), 0.2 s for 10 resamples at 2048 features; on random-projection features the
mean of 10-resample estimates is the std over independent samples within 4 % (tests/test_callbacks.py).

Data flow: features (N, D) (drgan.metrics.inception.InceptionFeatures: images (N, H, W) in [0, 1] -> (N, 2048))
-> ``FeatureStats`` (mean, covariance) -> ``frechet_distance`` / ``kid``.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from drgan.core.errors import ConfigError, DataError
from drgan.core.io import write_with
from drgan.metrics.inception import MODE, InceptionFeatures, check_images

__all__ = [
    "FeatureStats",
    "frechet_distance",
    "ResampledFID",
    "fid_bootstrap_std",
    "kid",
    "cached_reference_stats",
    "fid_from_images",
]

logger = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------------
# Distances


def _rank_floor(w: np.ndarray) -> float:
    """Eigenvalues below this are rounding noise of a zero eigenvalue (numpy's matrix_rank tolerance)."""
    return float(np.abs(w).max(initial=0.0)) * w.size * np.finfo(np.float64).eps


def _psd_factor(sigma: np.ndarray, name: str) -> np.ndarray:
    """C (D, r) with C C^T = sigma: C = V W^1/2 over the r eigenvalues of sigma above rounding level."""
    w, v = np.linalg.eigh(sigma)
    floor = _rank_floor(w)
    if w.size and w.min() < -max(1e-6 * float(np.abs(w).max()), floor):
        raise DataError(f"frechet_distance: {name} is not positive semi-definite (eigenvalue {w.min():.3g})")
    keep = w > floor
    return v[:, keep] * np.sqrt(w[keep])


def frechet_distance(mu1: np.ndarray, sigma1: np.ndarray, mu2: np.ndarray, sigma2: np.ndarray) -> float:
    """Frechet distance between N(mu1, sigma1) and N(mu2, sigma2).

    d^2 = ||mu1 - mu2||^2 + tr(sigma1) + tr(sigma2) - 2 tr(sqrtm(sigma1 sigma2)).

    The trace term is computed without the non-symmetric ``scipy.linalg.sqrtm(sigma1 @ sigma2)`` that
    clean-fid uses: sigma1 sigma2 = R (R sigma2) and (R sigma2) R = R sigma2 R with R = sigma1^(1/2) share
    their eigenvalues, so tr(sqrtm(sigma1 sigma2)) = sum of sqrt(eigenvalues of the symmetric positive
    semi-definite R sigma2 R). With sigma1 = C C^T (C = V W^1/2 over its r nonzero eigenvalues) these are
    the eigenvalues of the r x r matrix C^T sigma2 C. Symmetric eigendecompositions are exact for singular
    covariances (fewer samples than the 2048 feature dimensions) without clean-fid's eps * I offset, give no
    imaginary parts to drop, and take seconds at D = 2048 where sqrtm takes about 40 s on two cores.
    Eigenvalues at rounding level (below max * D * machine eps) count as 0; clearly negative ones raise
    DataError (not a covariance).
    """
    mu1 = np.atleast_1d(np.asarray(mu1, dtype=np.float64))
    mu2 = np.atleast_1d(np.asarray(mu2, dtype=np.float64))
    sigma1 = np.atleast_2d(np.asarray(sigma1, dtype=np.float64))
    sigma2 = np.atleast_2d(np.asarray(sigma2, dtype=np.float64))
    d = mu1.shape[0]
    if mu1.ndim != 1 or mu2.shape != mu1.shape:
        raise DataError(f"frechet_distance: means must be vectors of one length, got {mu1.shape} and {mu2.shape}")
    if sigma1.shape != (d, d) or sigma2.shape != (d, d):
        raise DataError(
            f"frechet_distance: covariances must be ({d}, {d}) for means of length {d}, "
            f"got {sigma1.shape} and {sigma2.shape}"
        )
    for name, a in (("mu1", mu1), ("sigma1", sigma1), ("mu2", mu2), ("sigma2", sigma2)):
        if not np.isfinite(a).all():
            raise DataError(f"frechet_distance: {name} contains NaN or inf")
    for name, a in (("sigma1", sigma1), ("sigma2", sigma2)):
        if not np.allclose(a, a.T, rtol=1e-6, atol=1e-9 * max(float(np.abs(a).max()), 1.0)):
            raise DataError(f"frechet_distance: {name} is not symmetric; expected a covariance matrix")
    sigma1 = 0.5 * (sigma1 + sigma1.T)
    sigma2 = 0.5 * (sigma2 + sigma2.T)

    return _frechet_from_factor(mu1, _psd_factor(sigma1, "sigma1"), float(np.trace(sigma1)), mu2, sigma2)


def _frechet_from_factor(mu1: np.ndarray, c1: np.ndarray, trace1: float, mu2: np.ndarray, sigma2: np.ndarray) -> float:
    """Frechet distance given any factor C1 (D, r) with sigma1 = C1 C1^T (see ``frechet_distance``)."""
    inner = c1.T @ sigma2 @ c1  # (r, r): same nonzero eigenvalues as R sigma2 R, R = sigma1^(1/2)
    eig = np.linalg.eigvalsh(0.5 * (inner + inner.T))
    if eig.size and eig.min() < -max(1e-6 * float(np.abs(eig).max()), _rank_floor(eig)):
        # sigma2 is only seen through sigma1's span here: a full check would cost another eigh
        raise DataError(f"frechet_distance: sigma2 is not positive semi-definite (C^T sigma2 C has {eig.min():.3g})")
    # Zeroing rounding-level eigenvalues matters: with fewer samples than dimensions about 2000 of them
    # are ~1e-16 * max, and their square roots (~1e-8 * sqrt(max) each) would add up to a visible bias.
    tr_covmean = float(np.sqrt(np.where(eig > _rank_floor(eig), eig, 0.0)).sum())
    diff = mu1 - mu2
    return float(diff @ diff + trace1 + np.trace(sigma2) - 2.0 * tr_covmean)


def _check_features(feats: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(feats, dtype=np.float64)
    if arr.ndim != 2:
        raise DataError(f"{name}: expected features (N, D), got shape {arr.shape}")
    if arr.shape[0] < 2:
        raise DataError(f"{name}: need at least 2 feature vectors, got {arr.shape[0]}")
    if not np.isfinite(arr).all():
        raise DataError(f"{name}: features contain NaN or inf")
    return arr


def kid(
    feats1: np.ndarray,
    feats2: np.ndarray,
    subsets: int = 100,
    subset_size: int | None = None,
    seed: int | None = 0,
) -> tuple[float, float]:
    """Kernel Inception Distance (Binkowski et al., 2018): mean and std over random subsets.

    Each subset draws m vectors from each set without replacement and computes the unbiased MMD^2 with the
    cubic polynomial kernel k(x, y) = (x.y / d + 1)^3:

        sum_{i!=j} k(x_i, x_j) / (m(m-1)) + sum_{i!=j} k(y_i, y_j) / (m(m-1)) - 2 sum_{i,j} k(x_i, y_j) / m^2.

    Being unbiased, it scatters around 0 (and can be negative) for two samples of one distribution.

    subset_size m: None (default) takes max(2, n // 2) with n = min(n1, n2), so that the subsets differ and the
    std says how much the estimate moves with the sample: it is the spread of m-vector estimates, somewhat larger
    than the uncertainty of the mean over subsets. The mean is unbiased whatever m. (clean-fid takes
    min(n, 1000) and torch-fidelity 1000: with the ~130 real patches of a case the former is the whole sample
    every time, std 0.) An explicit m larger than n is refused (ConfigError): clipping it to n would silently
    give that std of 0; m = n gives the one whole-sample value (std 0), e.g. to compare with a direct computation.
    """
    x_all = _check_features(feats1, "kid feats1")
    y_all = _check_features(feats2, "kid feats2")
    if x_all.shape[1] != y_all.shape[1]:
        raise DataError(f"kid: feature lengths differ, {x_all.shape} vs {y_all.shape}")
    if int(subsets) < 1:
        raise ConfigError(f"kid: subsets must be >= 1, got {subsets}")
    n = min(x_all.shape[0], y_all.shape[0])
    if subset_size is None:
        subset_size = max(2, n // 2)
    if int(subset_size) < 2:
        raise ConfigError(f"kid: subset_size must be >= 2, got {subset_size}")
    if int(subset_size) > n:
        raise ConfigError(
            f"kid: subset_size={subset_size} is larger than the smaller sample ({x_all.shape[0]} and {y_all.shape[0]} "
            "vectors): every subset would be the whole sample and the std 0; give at most that many, or None (half)"
        )
    d = x_all.shape[1]
    m = int(subset_size)
    rng = np.random.default_rng(seed)
    values = np.empty(int(subsets))
    for s in range(int(subsets)):
        x = x_all[rng.choice(x_all.shape[0], m, replace=False)]
        y = y_all[rng.choice(y_all.shape[0], m, replace=False)]
        kxx = (x @ x.T / d + 1.0) ** 3
        kyy = (y @ y.T / d + 1.0) ** 3
        kxy = (x @ y.T / d + 1.0) ** 3
        within = (kxx.sum() - np.trace(kxx) + kyy.sum() - np.trace(kyy)) / (m * (m - 1))
        values[s] = within - 2.0 * kxy.sum() / (m * m)
    return float(values.mean()), float(values.std())


# --------------------------------------------------------------------------------------------------
# Statistics and their cache


@dataclass(frozen=True)
class FeatureStats:
    """Mean (D,), covariance (D, D) and the features (N, D) they came from (kept for KID)."""

    mu: np.ndarray
    sigma: np.ndarray
    features: np.ndarray

    @property
    def n(self) -> int:
        return int(self.features.shape[0])

    @cached_property
    def factor(self) -> np.ndarray:
        """C (D, r) with C C^T = sigma (`_psd_factor`: one D x D eigendecomposition, computed once per object)."""
        return _psd_factor(0.5 * (self.sigma + self.sigma.T), "sigma")

    def fid(self, other: FeatureStats) -> float:
        """Frechet distance between these statistics and ``other``'s.

        Same value as ``frechet_distance(self.mu, self.sigma, other.mu, other.sigma)``, but when this set has
        no more vectors than dimensions (N <= D: typical for generated samples) its centred features
        / sqrt(N - 1) are used as the factor C of sigma = C C^T, which skips the D x D eigendecomposition
        (seconds to tens of seconds at D = 2048 on a busy 2-core machine).
        """
        if self.mu.shape != other.mu.shape:
            raise DataError(f"FeatureStats.fid: feature lengths differ, {self.mu.shape} vs {other.mu.shape}")
        if self.n > self.mu.shape[0]:
            return frechet_distance(self.mu, self.sigma, other.mu, other.sigma)
        c1 = (self.features - self.mu).T / np.sqrt(self.n - 1)
        return _frechet_from_factor(self.mu, c1, float(np.trace(self.sigma)), other.mu, other.sigma)

    @classmethod
    def from_features(cls, features: np.ndarray) -> FeatureStats:
        feats = _check_features(features, "FeatureStats features")
        return cls(mu=feats.mean(axis=0), sigma=np.cov(feats, rowvar=False), features=feats)

    def save(self, path: str | os.PathLike) -> None:
        """Write an .npz atomically (temp file in the same directory, then os.replace)."""
        write_with(path, lambda handle: np.savez(handle, mu=self.mu, sigma=self.sigma, features=self.features))

    @classmethod
    def load(cls, path: str | os.PathLike) -> FeatureStats:
        path = Path(path)
        if not path.is_file():
            raise DataError(f"feature statistics file {str(path)!r} does not exist")
        try:
            with np.load(path, allow_pickle=False) as data:
                mu, sigma, features = data["mu"], data["sigma"], data["features"]
        except Exception as exc:
            raise DataError(
                f"feature statistics file {str(path)!r} is unreadable or lacks mu/sigma/features ({exc})"
            ) from exc
        d = mu.shape[0] if mu.ndim == 1 else -1
        if d < 1 or sigma.shape != (d, d) or features.ndim != 2 or features.shape[1] != d:
            raise DataError(
                f"feature statistics file {str(path)!r} has inconsistent shapes: mu {mu.shape}, "
                f"sigma {sigma.shape}, features {features.shape}"
            )
        return cls(mu=mu, sigma=sigma, features=features)


class ResampledFID:
    """FID against fixed real statistics of row selections (e.g. bootstrap resamples) of one generated feature set.

    ``ResampledFID(features, real)(np.arange(N))`` is ``FeatureStats.from_features(features).fid(real)``. The trace
    term tr(sqrtm(sigma_r sigma_g)) is the sum of square roots of the eigenvalues of a symmetric matrix
    (see ``frechet_distance``); what depends only on the real statistics and the full generated set is computed
    once, so each selection ``idx`` costs one symmetric eigendecomposition of min(N, D):

    - N <= D (the usual case: ~130 generated images, 2048 features): with G = centred(X[idx])^T / sqrt(N - 1),
      sigma_g = G G^T and the nonzero eigenvalues of sigma_r^1/2 sigma_g sigma_r^1/2 are those of the N x N
      G^T sigma_r G = H K[idx, idx] H / (N - 1), K = X sigma_r X^T computed once (N D^2), H the centring matrix;
    - N > D: with sigma_r = C C^T (``FeatureStats.factor``, one D x D eigendecomposition, kept on ``real``) they
      are those of the r x r C^T sigma_g C = cov(X[idx] C), X C computed once.
    """

    def __init__(self, features: np.ndarray, real: FeatureStats):
        x = _check_features(features, "ResampledFID features")
        if x.shape[1] != real.mu.shape[0]:
            raise DataError(f"ResampledFID: feature lengths differ, {x.shape[1]} vs {real.mu.shape[0]}")
        self.real = real
        self.x = x - x.mean(axis=0)  # centring by a constant changes no covariance; keeps the Gram matrix exact
        self.offset = x.mean(axis=0) - real.mu  # mean(X[idx]) - mu_r = mean(self.x[idx]) + offset
        self.trace_real = float(np.trace(real.sigma))
        n, d = x.shape
        if n <= d:
            self.gram, self.projected = self.x @ real.sigma @ self.x.T, None
        else:
            self.gram, self.projected = None, self.x @ real.factor

    def __call__(self, idx: np.ndarray) -> float:
        idx = np.asarray(idx, dtype=np.intp)
        m = idx.shape[0]
        if idx.ndim != 1 or m < 2:
            raise DataError(f"ResampledFID: expected a 1-d selection of at least 2 rows, got shape {idx.shape}")
        rows = self.x[idx]
        mean = rows.mean(axis=0)
        diff = mean + self.offset
        trace_fake = float(((rows - mean) ** 2).sum()) / (m - 1)
        if self.gram is not None:
            k = self.gram[np.ix_(idx, idx)]
            inner = (k - k.mean(axis=0, keepdims=True) - k.mean(axis=1, keepdims=True) + k.mean()) / (m - 1)
        else:
            inner = np.atleast_2d(np.cov(self.projected[idx], rowvar=False))
        eig = np.linalg.eigvalsh(0.5 * (inner + inner.T))
        tr_covmean = float(np.sqrt(np.where(eig > _rank_floor(eig), eig, 0.0)).sum())
        return float(diff @ diff + trace_fake + self.trace_real - 2.0 * tr_covmean)


def fid_bootstrap_std(features: np.ndarray, real: FeatureStats, resamples: int = 10, seed: int | None = 0) -> float:
    """Standard error of the FID of ``features`` against ``real`` from the generated side: the std (ddof=1) of
    the FIDs of ``resamples`` bootstrap resamples of the generated rows (N drawn with replacement, seeded).
    Resampled FIDs sit above the FID (a resample holds ~63 % distinct rows, and FID's bias grows as the sample
    shrinks); their spread is what is used. It shrinks about as 1 / sqrt(N)."""
    if int(resamples) < 2:
        raise ConfigError(f"fid_bootstrap_std: resamples={resamples}; expected >= 2 (a std needs two values)")
    fid = ResampledFID(features, real)
    n = fid.x.shape[0]
    rng = np.random.default_rng(seed)
    values = [fid(rng.integers(0, n, n)) for _ in range(int(resamples))]
    return float(np.std(values, ddof=1))


_KEY_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


def cached_reference_stats(
    images: np.ndarray | Callable[[], np.ndarray],
    cache_dir: str | os.PathLike,
    key: str,
    extractor: InceptionFeatures | None = None,
    resolution: tuple[int, int] | None = None,
) -> FeatureStats:
    """Statistics of the real images, computed once and cached as ``{key}_{MODE}_{H}x{W}.npz``.

    ``images`` is an array (N, H, W) in [0, 1], or a function returning one, so that on a cache hit the
    data set is not even loaded; then ``resolution`` (H, W) of the source images must be given, as it is
    part of the cache file name. ``key`` names the data set and split (e.g. ``"tio2_sem_train"``).
    """
    if not isinstance(key, str) or not _KEY_RE.match(key):
        raise ConfigError(f"cache key must be a simple name of letters, digits, '_', '.', '-', got {key!r}")
    arr = None
    if callable(images):
        if resolution is None:
            raise ConfigError("cached_reference_stats: give resolution=(H, W) when images is a function")
    else:
        arr = check_images(images, f"reference images {key!r}", min_count=2)
        if resolution is not None and tuple(resolution) != arr.shape[1:]:
            raise DataError(
                f"reference images {key!r}: resolution={tuple(resolution)} but the images are {arr.shape[1:]}"
            )
        resolution = arr.shape[1:]
    h, w = (int(v) for v in resolution)
    path = Path(cache_dir) / f"{key}_{MODE}_{h}x{w}.npz"
    if path.is_file():
        logger.info("reference statistics %r: cache hit %s", key, path)
        return FeatureStats.load(path)

    if arr is None:
        arr = check_images(images(), f"reference images {key!r}", min_count=2)
        if arr.shape[1:] != (h, w):
            raise DataError(f"reference images {key!r}: resolution={(h, w)} but the images are {arr.shape[1:]}")
    logger.info("reference statistics %r: computing from %d images -> %s", key, arr.shape[0], path)
    extractor = extractor if extractor is not None else InceptionFeatures()
    stats = FeatureStats.from_features(extractor.features(arr))
    stats.save(path)
    return stats


def fid_from_images(fake: np.ndarray, real_stats: FeatureStats, extractor: InceptionFeatures | None = None) -> float:
    """FID of generated images (N, H, W) in [0, 1], N >= 2, against precomputed real statistics."""
    arr = check_images(fake, "fake images", min_count=2)
    extractor = extractor if extractor is not None else InceptionFeatures()
    return FeatureStats.from_features(extractor.features(arr)).fid(real_stats)
