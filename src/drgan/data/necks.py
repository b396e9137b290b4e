"""Where particles touch, and whether the image shows it: contacts of an instance label image and their neck grey.

A segmenter can only cut two touching particles apart where the image shows a cue: a contact whose grey falls towards
the background (a visible neck or gap) is cut, one as dark (or bright) as the particles is not (experiments/statistics/
README.md, "Merges where the image shows no neck": contacts with a neck grey near 1 are merged several times as
often as those below 0.8, on real and generated images alike). For every pair of touching instances, the ridge is
the pixels with both particles within 1 px (3 x 3 window: exact labels that touch, or an annotation's 1 px separating
line); its grey on the particles' own scale is

    neck = (median ridge grey - background grey) / (median core grey of the two - background grey)

1: the contact looks like the particles (no cue); 0: it falls to the background (a gap); > 1: a line brighter than the
particles (an SEM edge). Core: instance pixels with no other label within 2 px; background: pixels with no particle
within 3 px (the image's median). The neck's width is the ridge's extent along its principal axis (sqrt(12 var)) over
the smaller particle's equivalent diameter: near 0 a point contact, near 1 two particles that look like one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

HIDDEN_NECK = 0.97  # a contact whose neck grey is at least this shows no cut to a segmenter
MIN_CONTRAST = 0.05  # pairs whose particles differ less from the background (grey units) are not measured


def contact_pairs(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ridge, low, high): the pixels with two different instances of ``labels`` within 1 px (3 x 3 window), and at
    every pixel the smallest and the largest instance id within 1 px (int64; ``labels.max() + 1`` for none), which
    name the touching pair at a ridge pixel."""
    labels = np.asarray(labels, dtype=np.int64)
    none = int(labels.max()) + 1
    high = ndimage.maximum_filter(labels, size=3)
    low = ndimage.minimum_filter(np.where(labels > 0, labels, none), size=3)
    return (low < none) & (high > low), low, high


@dataclass(frozen=True)
class Neck:
    """One contact between instances ``a`` < ``b``: its neck grey and relative width (module docstring)."""

    a: int
    b: int
    grey: float
    width: float


def necks(image: np.ndarray, labels: np.ndarray, min_ridge: int = 3) -> list[Neck]:
    """Every contact of one image whose ridge has >= ``min_ridge`` pixels and whose particles differ from the
    background by at least MIN_CONTRAST; none without 100 background pixels."""
    image, labels = np.asarray(image, np.float64), np.asarray(labels, np.int64)
    big = int(labels.max()) + 1
    ridge, low, high = contact_pairs(labels)
    core = (labels > 0) & (ndimage.maximum_filter(labels, size=5) == labels)
    core &= ndimage.minimum_filter(np.where(labels > 0, labels, big), size=5) == labels
    background = ndimage.maximum_filter(labels, size=7) == 0
    if background.sum() < 100 or not ridge.any():
        return []
    bg = float(np.median(image[background]))
    ids = np.arange(1, big)
    core_grey = dict(zip(ids.tolist(), ndimage.median(image, np.where(core, labels, 0), ids)))
    pair = low[ridge] * big + high[ridge]
    diameter = 2.0 * np.sqrt(np.bincount(labels.ravel(), minlength=big) / np.pi)
    coords = np.argwhere(ridge)
    out = []
    for key in np.unique(pair):
        grey = image[ridge][pair == key]
        a, b = int(key // big), int(key % big)
        cores = [core_grey.get(a), core_grey.get(b)]
        if grey.size < min_ridge or any(c is None or not np.isfinite(c) for c in cores):
            continue
        contrast = float(np.mean(cores)) - bg
        if abs(contrast) < MIN_CONTRAST:
            continue
        xy = coords[pair == key].astype(float)
        width = float(np.sqrt(12.0 * np.linalg.eigvalsh(np.cov(xy.T))[-1])) if len(xy) > 1 else 0.0
        out.append(Neck(a, b, (float(np.median(grey)) - bg) / contrast, width / min(diameter[a], diameter[b])))
    return out


def contact_counts(labels: np.ndarray) -> tuple[int, int, int]:
    """(particles, their contacts, those touching another) over the particles of one label image that do not touch
    its border (a particle cut by the border may have lost its neighbours with it)."""
    labels = np.asarray(labels, np.int64)
    big = int(labels.max()) + 1
    ridge, low, high = contact_pairs(labels)
    pairs = np.unique(low[ridge] * big + high[ridge])
    degree = np.bincount(np.concatenate([pairs // big, pairs % big]), minlength=big)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    inner = np.setdiff1d(np.unique(labels[labels > 0]), border)
    return int(inner.size), int(degree[inner].sum()), int((degree[inner] > 0).sum())


def contact_statistics(images: Sequence[np.ndarray], labels: Sequence[np.ndarray]) -> dict | None:
    """The contacts of a set of images with their instance labels: how many, their neck grey's quartiles, the share
    ``hidden`` (neck grey >= HIDDEN_NECK: no cue to cut) and ``gap`` (< 0.5), the neck width's median, contacts per
    particle and the share of particles touching another (those not cut by the border); None without a contact."""
    found = [n for image, label in zip(images, labels) for n in necks(image, label)]
    if not found:
        return None
    grey = np.array([n.grey for n in found])
    width = np.array([n.width for n in found])
    particles, contacts, touching = np.sum([contact_counts(label) for label in labels], axis=0)
    quartiles = np.percentile(grey, [25, 50, 75])
    return {
        "contacts": len(found),
        "neck_grey_quartiles": [round(float(q), 3) for q in quartiles],
        "hidden": round(float(np.mean(grey >= HIDDEN_NECK)), 3),
        "gap": round(float(np.mean(grey < 0.5)), 3),
        "neck_width_median": round(float(np.median(width)), 3),
        "contacts_per_particle": round(float(contacts / particles), 3) if particles else None,
        "touching": round(float(touching / particles), 3) if particles else None,
    }
