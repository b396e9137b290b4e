"""Finding particles in an unannotated image, whatever their size: drgan's one classical segmentation.

Profiling, patch mining, background selection and the FID brightness guards all ask the same question (which pixels
are particles, and which particle is which), so they all call this package. Nothing here is tuned to one data set:
every length follows from the particles' own scale, measured first, by fractions and rules whose values are in one
place, `calibration.Calibration` (with where they were measured).

- `params`: the settings (`SegmentParams`, a material's ``data.segment``): a length left None follows from the
  particle diameter (`SegmentParams.resolved`); a value set by the user is kept exactly.
- `scale`: the Laplacian-of-Gaussian estimate of the particle diameter, the blob centres, the search's records.
- `search`: the diameter and the neck depth searched together on a grid of scales (`resolve_params`).
- `foreground`: the image prepared (grey, particles bright, annotations filled), the threshold around the blobs,
  holes, outlines grown out to the particles' edges.
- `watershed`: touching particles split (the distance-transform watershed, shared with the U-Net's split).
- `particles`: one image segmented end to end (`segment_particles`, `particle_foreground`, `segment_with_report`).
"""

from drgan.data.classical.calibration import CALIBRATION, Calibration
from drgan.data.classical.foreground import (
    Cut,
    Prepared,
    cut_foreground,
    edge_level,
    fill_masked,
    flatten,
    grow_to_edges,
    prepare,
    retry_separability,
)
from drgan.data.classical.params import NoParticles, SegmentParams
from drgan.data.classical.particles import Segmentation, particle_foreground, segment_particles, segment_with_report
from drgan.data.classical.scale import Fixed, Point, ScaleEstimate, blob_centres, blob_responses, estimate_scale
from drgan.data.classical.search import (
    area_weighted_median,
    fixed_points,
    resolve_params,
    scale_grid,
    search_scale,
    segment_diameters,
    size_spread,
)
from drgan.data.classical.watershed import distance_seeds, distance_watershed, flood, split_by_depth, split_touching

__all__ = [
    "CALIBRATION",
    "Calibration",
    "Cut",
    "Fixed",
    "NoParticles",
    "Point",
    "Prepared",
    "ScaleEstimate",
    "SegmentParams",
    "Segmentation",
    "area_weighted_median",
    "blob_centres",
    "blob_responses",
    "cut_foreground",
    "distance_seeds",
    "distance_watershed",
    "edge_level",
    "estimate_scale",
    "fill_masked",
    "fixed_points",
    "flatten",
    "flood",
    "grow_to_edges",
    "particle_foreground",
    "prepare",
    "resolve_params",
    "retry_separability",
    "scale_grid",
    "search_scale",
    "segment_diameters",
    "segment_particles",
    "segment_with_report",
    "size_spread",
    "split_by_depth",
    "split_touching",
]
