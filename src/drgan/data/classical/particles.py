"""Segmenting one image: the scale resolved, the foreground, the watershed split, the outlines grown, the report."""

from __future__ import annotations

from dataclasses import replace
from typing import NamedTuple

import numpy as np

from drgan.data.classical.foreground import cut_foreground, grow_to_edges, grown_foreground, prepare
from drgan.data.classical.params import NoParticles, SegmentParams
from drgan.data.classical.search import resolve_params
from drgan.data.classical.watershed import split_touching


def particle_foreground(image: np.ndarray, params: SegmentParams | None = None, polarity: str = "bright") -> np.ndarray:
    """The bool foreground of `segment_particles` without splitting it into particles (cheaper): pixels past
    the Otsu threshold of the smoothed, flattened image in the particles' direction, less annotations and
    connected specks below ``min_area``, grown out to the particles' edges (`grow_to_edges`; unsplit, every piece
    grows, watershed slivers too: a superset of `segment_particles`' foreground). All False when no particle
    stands out."""
    params = SegmentParams.from_config(params)
    try:  # the neck depth splits the foreground, it does not change it: none chosen
        params, _ = resolve_params([image], replace(params, neck_depth=params.neck_depth or 0.0), polarity)
    except NoParticles:
        return np.zeros(np.shape(image)[:2], bool)
    prepared = prepare(image, polarity, params.annotations)
    cut = cut_foreground(prepared, params)
    return grown_foreground(cut, params.scale, prepared.annotations) if params.grow_outlines else cut.foreground


def segment_particles(
    image: np.ndarray, params: SegmentParams | None = None, polarity: str = "bright"
) -> tuple[np.ndarray, np.ndarray]:
    """Segment particles: brighter than the background (polarity "bright") or darker ("dark").

    Returns (labels, foreground): int32 labels (0 = none) of the watershed segments, and the bool
    foreground mask: everything above the threshold except annotations and connected specks smaller than
    min_area (it keeps agglomerates too large to count as particles), grown out to the particles' edges where
    those lie below the threshold (`grow_to_edges`; the labels with it). ``params`` not resolved (the default):
    the lengths follow from this image's particle scale. Empty when no particle stands out.
    """
    try:
        params, _ = resolve_params([image], params, polarity)
    except NoParticles:
        shape = np.shape(image)[:2]
        return np.zeros(shape, np.int32), np.zeros(shape, bool)
    found = segment_with_report(image, params, polarity)
    return found.labels, found.foreground


class Segmentation(NamedTuple):
    """`segment_with_report`: the segmentation and what the profile reports of it."""

    labels: np.ndarray  # int32, 0 = none
    foreground: np.ndarray  # bool
    separability: float  # Otsu's
    grown: float  # the share of foreground the outlines' growth added (`grow_to_edges`; 0: none)


def segment_with_report(image: np.ndarray, params: SegmentParams, polarity: str) -> Segmentation:
    """`segment_particles` with resolved ``params``, and what the profile reports of it (`Segmentation`)."""
    prepared = prepare(image, polarity, params.annotations)
    cut = cut_foreground(prepared, params)
    labels = split_touching(cut.foreground, params)
    if not params.grow_outlines:
        return Segmentation(labels, cut.foreground, cut.separability, 0.0)
    labels, foreground = grow_to_edges(cut, labels, params.scale, params.min_area, prepared.annotations)
    grown = float(foreground.sum() / cut.foreground.sum() - 1) if cut.foreground.any() else 0.0
    return Segmentation(labels, foreground, cut.separability, grown)
