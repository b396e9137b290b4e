"""The particle scale: the Laplacian-of-Gaussian estimate, blob centres, and what the scale search records.

The scale-normalised Laplacian of Gaussian, ``-s^2 LoG_s``, peaks at ``s = d / (2 sqrt 2)`` on a disc of diameter
``d`` whatever its contrast (Lindeberg's scale selection). Its maxima over position and scale, from
``Calibration.min_diameter`` to a share of the image's shorter side, are the image's blobs; the strong ones (well
above the response's noise at their scale) vote, weighted by their response, for the particle diameter
(`estimate_scale`). Grain and noise respond at small scales only weakly and are outvoted; an agglomerate still
shows its particles' seams. The same response at one diameter gives the blob centres the threshold is taken around
(`blob_centres`). `Point`, `Fixed` and `ScaleEstimate` are the records of the scale search (drgan.data.classical.search).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy import ndimage as ndi
from skimage.filters import threshold_otsu

from drgan.data.classical.calibration import CALIBRATION as CAL


@dataclass(frozen=True)
class ScaleEstimate:
    """The particle diameter one or more images show, and how it was found."""

    diameter_px: float | None  # None: no blob stood out
    blobs: int  # scale-space maxima that voted
    response: float  # median response of the voting blobs (grey levels: ~ the particles' contrast)
    diameters_tried_px: tuple[float, float]  # the range of the LoG scales, as disc diameters
    refined_px: float | None = None  # the diameter chosen by `search_scale`
    candidates: tuple = ()  # every fixed point `search_scale` found (`Fixed`)
    alike: bool = False  # min_separability lowered for a scale of alike segments (`search_scale`; `resolve_params`)
    plateau: bool = False  # the scale smooths more than the particles' size asks (`_plateau`)
    depth: float | None = None  # the neck depth chosen with the scale
    grid: tuple = ()  # (scale, neck depth, segments' median, separability) of every scale segmented

    def as_dict(self) -> dict:
        return {
            "diameter_px": None if self.diameter_px is None else round(self.diameter_px, 2),
            "blobs": self.blobs,
            "response": round(self.response, 4),
            "diameters_tried_px": [round(v, 1) for v in self.diameters_tried_px],
            "refined_px": None if self.refined_px is None else round(self.refined_px, 2),
            "candidates": [f.as_list() for f in self.candidates],
            "candidate_fields": list(Fixed._fields),
            "alike": self.alike,
            "plateau": self.plateau,
            "neck_depth": self.depth,
            "grid": [[round(s, 2), d, None if math.isnan(m) else round(m, 2), round(q, 3)] for s, d, m, q in self.grid],
        }


class Point(NamedTuple):
    """Every image segmented with the settings of one scale and neck depth (`search_scale`)."""

    scale: float  # px
    depth: float  # neck depth of the watershed's seeds
    median: float  # of the segments' equivalent diameters (not touching the border, of plausible area); NaN: none
    weighted: float  # their area-weighted median
    spread: float  # `size_spread`
    segments: int  # how many
    separability: float  # of the threshold, mean over the images
    lowest: float  # the least of the images'

    def size(self, weighted: bool) -> float:
        return self.weighted if weighted else self.median

    def agrees(self, weighted: bool) -> bool:
        """Its segments' (area-weighted) median lies within CAL.consistent of its scale."""
        size = self.size(weighted)
        return math.isfinite(size) and abs(math.log(size / self.scale)) < CAL.consistent


class Fixed(NamedTuple):
    """A fixed point of the scale map: of a run of grid scales whose segments agree with them, the one agreeing best
    (refined to its segments' own median when chosen)."""

    scale: float  # px
    depth: float
    median: float  # its segments' (area-weighted where the search followed that)
    separability: float
    lowest: float
    spread: float
    segments: int
    basin: int  # grid scales (same depth) whose segments' median lies within CAL.consistent of this one's
    alike: bool = False  # a candidate below min_separability for its alike segments (CAL.alike_*)
    plateau: bool = False  # not a fixed point: a size held below the scale over an octave and more (`_plateau`)

    @property
    def evidence(self) -> float:
        """How persistent and how alike: the basin (quarter-octave steps) less the size spread."""
        return self.basin - (CAL.spread_unknown if math.isnan(self.spread) else self.spread)

    def as_list(self) -> list:
        """The fields in order (JSON: NaN spread as None)."""
        f = self
        spread = None if math.isnan(f.spread) else round(f.spread, 3)
        return [round(f.scale, 2), f.depth, round(f.median, 2), round(f.separability, 3), round(f.lowest, 3), spread,
                f.segments, f.basin, f.alike, f.plateau]  # fmt: skip

    @classmethod
    def from_list(cls, values: Sequence) -> Fixed:
        """Back from `as_list` (a profile.json's candidates; an older one may lack the last field, `plateau`)."""
        f = cls(*values)
        return f._replace(spread=math.nan if f.spread is None else f.spread)


def _diameters(shape: tuple[int, int]) -> np.ndarray:
    top = CAL.max_diameter_share * min(shape)
    n = max(1, int(math.floor(math.log(top / CAL.min_diameter) / math.log(CAL.scale_step))) + 1)
    return CAL.min_diameter * CAL.scale_step ** np.arange(n)


def _log_stack(bright: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
    """-s^2 LoG_s of ``bright`` per scale s (len(sigmas), H, W); large scales on an averaged-down copy (effective
    sigma 2-4 px), interpolated back."""
    from skimage.transform import resize

    h, w = bright.shape
    out = np.empty((len(sigmas), h, w), np.float32)
    image = np.asarray(bright, np.float64)
    for k, s in enumerate(sigmas):
        f = 1
        while s / (2 * f) >= 2 and min(h, w) // (2 * f) >= 16:
            f *= 2
        small = image if f == 1 else resize(image, (h // f, w // f), order=1, anti_aliasing=True)
        r = -((s / f) ** 2) * ndi.gaussian_laplace(small, s / f, mode="reflect")
        out[k] = r if f == 1 else resize(r, (h, w), order=1)
    return out


def blob_responses(bright: np.ndarray, exclude: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Scale-space maxima of the bright blobs: (diameters px, responses) of those standing out of their scale's
    noise (CAL.significance robust stds). ``exclude``: pixels whose blobs do not count (annotations)."""
    bright = np.asarray(bright, np.float32)
    factor = max(1, int(math.ceil(math.sqrt(bright.size / CAL.working_pixels))))
    if factor > 1:
        from skimage.transform import resize

        shape = (bright.shape[0] // factor, bright.shape[1] // factor)
        bright = resize(bright, shape, order=1, anti_aliasing=True).astype(np.float32)
        exclude = None if exclude is None else resize(exclude.astype(float), shape, order=0) > 0.5
    diameters = _diameters(bright.shape)
    sigmas = diameters / (2 * math.sqrt(2))
    stack = _log_stack(bright, sigmas)
    found_d, found_r = [], []
    h, w = bright.shape
    for k, s in enumerate(sigmas):
        r = stack[k]
        centre = np.median(r)
        noise = 1.4826 * np.median(np.abs(r - centre)) + 1e-6
        window = 2 * int(math.ceil(s)) + 1
        peak = (r == ndi.maximum_filter(r, size=window, mode="nearest")) & (r > centre + CAL.significance * noise)
        if k > 0:
            peak &= r >= stack[k - 1]
        if k + 1 < len(sigmas):
            peak &= r >= stack[k + 1]
        margin = int(math.ceil(s))  # blobs centred within one sigma of the edge are mostly outside it
        peak[:margin], peak[h - margin :], peak[:, :margin], peak[:, w - margin :] = False, False, False, False
        if exclude is not None:
            peak &= ~exclude
        values = r[peak]
        found_d.append(np.full(values.size, diameters[k] * factor))
        found_r.append(values)
    return np.concatenate(found_d), np.concatenate(found_r)


def estimate_scale(bright_images: Sequence[np.ndarray], excludes: Sequence[np.ndarray | None] | None = None):
    """The particle diameter (px) of bright-particle images: the response-weighted median diameter of the blobs
    whose response is at least the strongest ones' (the 90th percentile) over CAL.vote_divisor, so faint texture
    and grain do not vote."""
    excludes = excludes or [None] * len(bright_images)
    ds, rs = [], []
    shape = min((np.shape(b) for b in bright_images), key=min)
    for bright, exclude in zip(bright_images, excludes):
        d, r = blob_responses(bright, exclude)
        ds.append(d)
        rs.append(r)
    d, r = np.concatenate(ds), np.concatenate(rs)
    tried = _diameters(shape)
    tried = (float(tried[0]), float(tried[-1]))
    if d.size == 0:
        return ScaleEstimate(None, 0, 0.0, tried)
    strong = r >= np.quantile(r, 0.9) / CAL.vote_divisor
    d, r = d[strong], r[strong]
    order = np.argsort(d)
    cumulative = np.cumsum((r * d**2)[order])
    median = float(d[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])
    return ScaleEstimate(median, int(d.size), float(np.median(r)), tried)


def blob_centres(bright: np.ndarray, diameter: float, significant: bool = False) -> np.ndarray:
    """bool (H, W): centres of the bright blobs of about ``diameter`` px: maxima of -s^2 LoG_s at s = d / (2 sqrt 2),
    at least d / 2 apart, of at least CAL.centre_share of the strong ones' response (their 90th percentile).
    ``significant``: they must also stand out of the film's noise (`out_of_film_noise`). Not by default: on a dense
    packing the film is the gaps and the particles' shaded sides, whose response is as strong as the particles',
    and real centres would be lost."""
    response, centres = blob_maxima(bright, diameter)
    return out_of_film_noise(bright, response, centres) if significant else centres


def blob_maxima(bright: np.ndarray, diameter: float) -> tuple[np.ndarray, np.ndarray]:
    """(-s^2 LoG_s of ``bright``, `blob_centres` without ``significant``): the response is kept for the retry."""
    s = diameter / (2 * math.sqrt(2))
    r = _log_stack(bright, np.array([s]))[0]
    window = max(3, int(diameter / 2) | 1)
    peak = (r == ndi.maximum_filter(r, size=window, mode="nearest")) & (r > 0)
    if peak.any():
        peak &= r >= CAL.centre_share * np.quantile(r[peak], 0.9)
    return r, peak


def out_of_film_noise(bright: np.ndarray, response: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """The ``centres`` whose ``response`` stands CAL.significance robust stds out of the response on the film (the
    pixels below the image's Otsu threshold): on a grainy film with a few particles most maxima are grain, and the
    90th percentile of the maxima is grain too."""
    if not centres.any() or np.ptp(bright) == 0:
        return centres
    film = response[bright <= threshold_otsu(bright)]
    centre = np.median(film)
    return centres & (response >= centre + CAL.significance * 1.4826 * np.median(np.abs(film - centre)))
