"""Particle outlines in the formats Fiji (ImageJ) and napari open: a 16-bit label TIFF per image (one id per particle,
the pixel size in its resolution tags so that Fiji measures in nm) and an ImageJ ROI set (a .zip of one traced
polygon ROI per particle, named by its id, for the ROI Manager).

The ROI of a particle is the outline of its pixels, traced along their edges (ImageJ's own wand and Analyze
Particles make such "traced" ROIs): its vertices are pixel corners, (x, y) with pixel (row r, column c) covering
[c, c + 1) x [r, r + 1). Filled, it gives back exactly the particle's pixels, so Fiji's Measure on the ROI set gives
the areas of particles.csv, except where a particle has holes: a traced ROI has one outline, so it covers them
(on real images a few percent at most, every case a predicted particle with interior holes; the label TIFF keeps
the exact pixels). A particle whose pixels touch only at corners would be outlined by its largest
4-connected piece (drgan's particles are 4-connected components, so that does not happen to them). The ROI format is written with ``roifile`` (by tifffile's author), the TIFF
with ``tifffile``, both already what scikit-image and the ImageJ community use.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from drgan.core.io import atomic_path

# the four sides of a pixel as directed edges between its corners (x, y), clockwise on screen (y down): a side is
# on the outline when the neighbour across it is outside
_SIDES = (
    ((-1, 0), lambda r, c: ((c, r), (c + 1, r))),  # top
    ((0, 1), lambda r, c: ((c + 1, r), (c + 1, r + 1))),  # right
    ((1, 0), lambda r, c: ((c + 1, r + 1), (c, r + 1))),  # bottom
    ((0, -1), lambda r, c: ((c, r + 1), (c, r))),  # left
)


def traced_outline(mask: np.ndarray) -> np.ndarray:
    """The outer outline of the pixels of ``mask`` (bool, one particle), as (N, 2) int (x, y) pixel corners in order,
    collinear corners dropped; (0, 2) for an empty mask. Its polygon's area is the pixel count for a 4-connected mask
    without holes."""
    from scipy import ndimage as ndi

    mask = np.asarray(mask, dtype=bool)
    if not mask.any():
        return np.zeros((0, 2), dtype=np.int64)
    pieces, n = ndi.label(mask)
    if n > 1:
        sizes = np.bincount(pieces.ravel())[1:]
        mask = pieces == 1 + int(np.argmax(sizes))
    mask = ndi.binary_fill_holes(mask)
    padded = np.pad(mask, 1)
    nxt: dict[tuple[int, int], list[tuple[int, int]]] = {}
    rows, cols = np.nonzero(mask)
    for (dr, dc), edge in _SIDES:
        outside = ~padded[rows + 1 + dr, cols + 1 + dc]
        for r, c in zip(rows[outside].tolist(), cols[outside].tolist()):
            a, b = edge(r, c)
            nxt.setdefault(a, []).append(b)
    start = min(nxt)  # the top-left corner (smallest x, then y) lies on the outer outline
    loop, here, previous = [start], start, None
    while True:
        choices = nxt[here]
        if len(choices) == 1:
            step = choices[0]
        else:  # two outline edges leave a corner where the particle's pixels touch diagonally: keep turning right
            incoming = (here[0] - previous[0], here[1] - previous[1])
            right = (-incoming[1], incoming[0])
            step = next(
                (b for b in choices if (b[0] - here[0], b[1] - here[1]) == right),
                choices[0],
            )
        choices.remove(step)
        previous, here = here, step
        if here == start:
            break
        loop.append(here)
    points = np.asarray(loop, dtype=np.int64)
    before, after = np.roll(points, 1, axis=0), np.roll(points, -1, axis=0)
    cross = (points - before)[:, 0] * (after - points)[:, 1] - (points - before)[:, 1] * (after - points)[:, 0]
    return points[cross != 0]


def polygon_area(points: np.ndarray) -> float:
    x, y = np.asarray(points, dtype=np.float64).T
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def fill_polygon(points: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The pixels whose centres lie inside the polygon of (x, y) ``points`` (ImageJ's reading of a ROI)."""
    from matplotlib.path import Path as Polygon

    points = np.asarray(points, dtype=np.float64)
    mask = np.zeros(shape, dtype=bool)
    if len(points) < 3:
        return mask
    x0, y0 = np.floor(points.min(axis=0)).astype(int)
    x1, y1 = np.ceil(points.max(axis=0)).astype(int)
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, shape[1]), min(y1, shape[0])
    yy, xx = np.mgrid[y0:y1, x0:x1]
    inside = Polygon(points).contains_points(np.column_stack([xx.ravel() + 0.5, yy.ravel() + 0.5]))
    mask[y0:y1, x0:x1] = inside.reshape(yy.shape)
    return mask


def kept_labels(labels: np.ndarray, ids: Iterable[int]) -> np.ndarray:
    """``labels`` with every id not in ``ids`` set to 0 (the particles particles.csv lists, e.g. specks removed)."""
    labels = np.asarray(labels)
    keep = np.isin(labels, np.fromiter(ids, dtype=labels.dtype))
    return np.where(keep, labels, 0)


def write_label_tiff(path: Path, labels: np.ndarray, nm_per_px: float | None = None) -> None:
    """A label image Fiji and napari open: 16-bit (32-bit beyond 65,535 ids), ImageJ's TIFF flavour, with the pixel
    size as resolution in nm (ImageJ's unit) when known."""
    import tifffile

    labels = np.asarray(labels)
    dtype = np.uint16 if labels.max(initial=0) <= np.iinfo(np.uint16).max else np.uint32
    extra = {}
    if nm_per_px:
        extra = {"resolution": (1.0 / nm_per_px, 1.0 / nm_per_px), "metadata": {"unit": "nm", "axes": "YX"}}
    else:
        extra = {"metadata": {"axes": "YX"}}
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, labels.astype(dtype), imagej=dtype == np.uint16, **extra)


def read_label_tiff(path: Path) -> tuple[np.ndarray, float | None]:
    """(labels, nm per px or None) of a label TIFF written by ``write_label_tiff`` (or by Fiji)."""
    import tifffile

    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        labels = page.asarray()
        tag = page.tags.get("XResolution")
        unit = (tif.imagej_metadata or {}).get("unit")
        nm = None
        if tag is not None and unit in ("nm", "nanometer"):
            num, den = tag.value
            nm = den / num if num else None
    return labels, nm


def write_roi_set(path: Path, labels: np.ndarray, ids: Iterable[int] | None = None) -> int:
    """An ImageJ ROI set (.zip): one traced polygon ROI per particle of ``labels`` (every id, or ``ids``), named by
    its id; the number of ROIs written."""
    import roifile
    from scipy import ndimage as ndi

    labels = np.asarray(labels)
    wanted = sorted(int(i) for i in (np.unique(labels[labels > 0]) if ids is None else ids))
    rois = []
    boxes = ndi.find_objects(labels.astype(np.int64)) if wanted else []
    for i in wanted:
        box = boxes[i - 1] if i - 1 < len(boxes) else None
        if box is None:
            continue
        r0, c0 = box[0].start, box[1].start
        points = traced_outline(labels[box] == i) + np.array([c0, r0])
        roi = roifile.ImagejRoi.frompoints(points.astype(np.float64), name=str(i))
        roi.roitype = roifile.ROI_TYPE.TRACED
        rois.append(roi)
    with atomic_path(path) as tmp:  # (mode "w": the empty temporary file is replaced, not appended to)
        if rois:
            roifile.roiwrite(tmp, rois, mode="w")
        else:
            import zipfile

            zipfile.ZipFile(tmp, "w").close()
    return len(rois)


def read_roi_set(path: Path, shape: tuple[int, int]) -> Mapping[str, np.ndarray]:
    """name -> filled mask of every polygon ROI of an ImageJ ROI set (.zip or .roi), as ImageJ fills it."""
    import roifile

    rois = roifile.roiread(path)
    rois = rois if isinstance(rois, list) else [rois]
    return {roi.name: fill_polygon(roi.coordinates(), shape) for roi in rois}


def write_outlines(
    out: Path, image_id: str, labels: np.ndarray, ids: Iterable[int] | None = None, nm_per_px: float | None = None
) -> None:
    """OUT/labels/ID.tif and OUT/rois/ID.zip of the particles ``ids`` of ``labels`` (every particle when None)."""
    if ids is not None:
        ids = list(ids)
        labels = kept_labels(labels, ids)
    write_label_tiff(out / "labels" / f"{image_id}.tif", labels, nm_per_px)
    write_roi_set(out / "rois" / f"{image_id}.zip", labels, ids)
