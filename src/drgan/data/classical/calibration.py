"""The classical segmentation's tuned constants, in one place (`Calibration`, read through `CALIBRATION`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Calibration:
    """Every tuned constant of the classical particle segmentation; lengths in particle diameters d unless a unit is
    given, shares in [0, 1], spreads in log(q90 / q10) of the segments' diameters.

    Provenance: set, and each change measured, by the experiments in ``experiments/profile/`` (its README.md: "How
    the segmentation was tuned" for the lengths from the diameter, "One scale-adaptive segmentation for any images"
    and the sections after it for the rest, each under the heading that names it: seeds from the necks and the neck
    depth chosen by the sizes, outlines at the strongest edges, dense packings of alike particles, holes inside
    particles, every fixed point of the scale map, the plateau for small particles on noise, alike against what
    would win), against the TiO2 SEM / TSEM train masks and the EMPS instance maps. A change here is a change of
    the segmentation: measure it there first.
    """

    # --- the settings a particle scale d sets (`SegmentParams.resolved`) ---
    # Gaussian smoothing before the threshold: 1.5 px for TiO2's 26 px particles, the setting that met the median
    # and the count on both TiO2 sets
    sigma_per_diameter: float = 1.5 / 26
    # least distance between watershed seeds: fewer seeds merge touching particles, more cut them into pieces
    min_distance_per_diameter: float = 0.17
    min_area_diameter: float = 0.27  # a segment narrower than this (as a disc) is a speck or a watershed sliver
    max_area_diameter: float = 4.0  # one wider is an agglomerate the watershed could not split
    # the illumination is flattened at this size: larger than any particle, so none is flattened away
    background_per_diameter: float = 3.0

    # --- the threshold ---
    # Otsu's separability (between-class / total variance) below which a threshold separates no two classes:
    # smoothed noise scores 2 / pi = 0.64 at any scale, particles at their own scale more
    min_separability: float = 0.66

    # --- seeds at necks (`SegmentParams.neck_depth` left None: 0 or neck_depth, searched with the scale) ---
    # share of a seed's height above the saddle to a higher one: touching particles meet at deeper necks, a rod's
    # ridge and an irregular particle's bumps at shallower ones
    neck_depth: float = 0.2
    # seeds at necks are kept only where they narrow the segments' size spread to this share of every maximum
    # seeding's, near the same scale (within neck_near in log scale): merged rods come out alike, merged particles not
    neck_spread: float = 0.8
    neck_near: float = 0.35

    # --- the LoG scale estimate (`estimate_scale`, `blob_centres`) ---
    scale_step: float = 2**0.25  # between LoG scales, and between the scale search's grid scales
    min_diameter: float = 3.0  # px: smaller blobs are pixels, not particles
    max_diameter_share: float = 0.5  # of the image's shorter side: the largest scale tried
    working_pixels: int = 1024 * 1024  # larger images are averaged down for the estimate (lengths scaled back)
    significance: float = 4.0  # robust stds of the response (at a blob's scale, or on the film) a blob must exceed
    # a blob votes for the diameter when its response is at least the strong ones' (90th percentile) over this
    vote_divisor: float = 3.0
    # a blob centre is a maximum of at least this share of the strong maxima's response (90th percentile)
    centre_share: float = 0.25

    # --- the scale search (`search_scale`) ---
    min_scale: float = 6.0  # px: smaller fixed points are grain, texture or JPEG blocks
    consistent: float = 0.15  # |log(segments' median / scale)| below this: a segmentation agrees with its scale
    refine_rounds: int = 4  # steps a chosen scale (or the grid's top) follows its segments' median
    refine_until: float = 0.1  # a chosen scale within this (in log) of its segments' median is not moved
    # the size spread a fixed point of fewer than two segments is judged with: one segment shows nothing of how alike
    # the particles are (specks of every size spread 1.4-1.8, alike particles 0.03-0.7)
    spread_unknown: float = 3.0
    # A fixed point below min_separability is still a candidate (a dense packing of large textured particles: their
    # narrow gaps make a lopsided histogram that Otsu separates less than the texture cut into specks) where it
    # separates at least alike_separability on every image, with at least alike_segments segments that are alike:
    # a spread of at most alike_spread, or of at most alike_share of the spread of the candidate that would be
    # chosen without it (the geometric middle between specks' spread and alike particles')
    alike_separability: float = 0.55
    alike_spread: float = 0.5
    alike_share: float = 0.5
    alike_segments: int = 5
    # grid scales (an octave) over which the segments must keep their size to be particles where no fixed point is
    # a candidate (`_plateau`): noise's and grain's specks grow with the smoothing
    plateau_scales: int = 5

    # --- the foreground (`_foreground`, `_fill_holes`) ---
    centre_reach: float = 0.5  # a thresholded piece reaching no blob centre within this is a speck, not a particle
    # A hole at least this convex, and filling at least this share of the disc of its length, is a particle's own
    # darker centre, not a gap between several particles (concave, or a square between four: 0.64 of its disc)
    round_hole_solidity: float = 0.85
    round_hole_fill: float = 0.7

    # --- outlines at the particles' edges (`edge_level`) ---
    # levels tried, of the way from the film's grey to the particles': np.linspace(start, stop, count)
    outline_level_range: tuple[float, float, int] = (0.05, 0.95, 19)
    outline_band: float = 0.25  # the band around the outlines whose contours count
    min_contour: int = 20  # px: a level whose contour in the band is shorter says nothing

    @property
    def outline_levels(self) -> np.ndarray:
        start, stop, count = self.outline_level_range
        return np.linspace(start, stop, count)


CALIBRATION = Calibration()
