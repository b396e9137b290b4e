"""sha256 of the classical segmentation's and the U-Net watershed split's outputs on real images, to run before and
after a refactor of either (experiments/refactor/checksums.md).

    PYTHONPATH=/tmp/before/src python experiments/refactor/classical_checksums.py IMAGE... > before.txt
    python experiments/refactor/classical_checksums.py IMAGE... > after.txt

Per image (read with drgan.data.images.read_grey, crop_rows=auto; polarity detected): the resolved settings and
the scale search's record (`resolve_params`, as JSON), the labels and foreground of `segment_with_report` with them,
`particle_foreground`, `segment_particles` at the resolved scale with seed_depth 1 and without grown outlines, and
`drgan.segmenters.inference.split_touching` of class probabilities made from the classical labels (particle,
a 1-px contour between segments, background; Gaussian-blurred, seeded noise) with its default and two other
settings. Each line: image, what, sha256 of the array's bytes (with its dtype and shape) or of the JSON.
"""

from __future__ import annotations

import argparse
import hashlib
import json
from dataclasses import replace

import numpy as np
from scipy import ndimage as ndi

try:  # the classical segmentation's package (after issue 53); before it, one module
    from drgan.data.classical import (
        SegmentParams,
        particle_foreground,
        resolve_params,
        segment_particles,
        segment_with_report,
    )
except ImportError:
    from drgan.data.particles import (
        SegmentParams,
        particle_foreground,
        resolve_params,
        segment_particles,
        segment_with_report,
    )
from drgan.data.images import read_grey
from drgan.data.polarity import detect_polarity
from drgan.segmenters.inference import split_touching


def digest(value) -> str:
    if isinstance(value, np.ndarray):
        data = f"{value.dtype}{value.shape}".encode() + np.ascontiguousarray(value).tobytes()
    else:
        data = json.dumps(value, sort_keys=True, default=str).encode()
    return hashlib.sha256(data).hexdigest()


def probabilities(labels: np.ndarray, seed: int) -> np.ndarray:
    """(3, H, W) class probabilities from a label image: particle inside segments, contour on a 1-px line between
    touching ones, background elsewhere; blurred and noisy as a network's output."""
    grown = ndi.grey_dilation(labels, size=3)
    contour = (labels > 0) & (grown != labels)
    classes = np.where(contour, 2, (labels > 0).astype(np.int64))
    rng = np.random.default_rng(seed)
    logits = np.stack([ndi.gaussian_filter((classes == c).astype(np.float64), 1.5) for c in range(3)])
    logits = 4 * logits + 0.5 * rng.standard_normal(logits.shape)
    e = np.exp(logits - logits.max(axis=0))
    return (e / e.sum(axis=0)).astype(np.float32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("images", nargs="+")
    args = parser.parse_args()
    for k, path in enumerate(args.images):
        name = path.rsplit("/", 1)[-1]
        image = read_grey(path, "auto")
        polarity = detect_polarity([image]).polarity
        params, estimate = resolve_params([image], SegmentParams(), polarity)
        rows = [("params", params.as_dict()), ("estimate", None if estimate is None else estimate.as_dict())]
        found = segment_with_report(image, params, polarity)
        rows += [("labels", found.labels), ("foreground", found.foreground)]
        rows += [("report", [found.separability, found.grown])]
        at_scale = SegmentParams(scale=params.scale)
        rows.append(("particle_foreground", particle_foreground(image, at_scale, polarity)))
        strands = replace(at_scale, seed_depth=1.0, grow_outlines=False)
        rows.append(("labels_seed_depth_1_otsu_outlines", segment_particles(image, strands, polarity)[0]))
        probs = probabilities(found.labels, k)
        rows.append(("unet_split_default", split_touching(probs)))
        rows.append(("unet_split_core_0.6", split_touching(probs, split_core=0.6)))
        rows.append(("unet_split_depth_1_unsmoothed", split_touching(probs, split_depth=1.0, split_smooth=0.0)))
        for what, value in rows:
            print(f"{name}\t{polarity}\t{what}\t{digest(value)}", flush=True)


if __name__ == "__main__":
    main()
