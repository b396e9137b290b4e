"""A user's corrected outlines as training pairs: the correction loop (`drgan segment finetune=RUN corrected=DIR`).

A user who sees wrong outlines fixes a few images where microscopists work and saves them into one folder DIR, one
file per corrected image, named by the image's id:

- ``ID.tif`` / ``ID.tiff``: a label image, 0 background and one id per particle (napari: the labels layer of
  ``drgan view RUN`` edited and saved; or analyze's ``labels/ID.tif`` edited in Fiji);
- ``ID.zip`` / ``ID.roi``: an ImageJ ROI set, one polygon per particle (Fiji's ROI Manager: analyze's ``rois/ID.zip``
  opened on the image, fixed, "More > Save..."); overlapping ROIs: a later one wins the pixels they share;
- ``ID.png``: a mask, binary (its 4-connected components are the particles) or an instance map.

Files may lie in DIR itself or in its ``labels/``, ``rois/`` or ``masks/`` folder; every particle of the image must
be drawn (a pixel left 0 is background: the network learns it as such). The images themselves are read from
``DIR/images/`` when it exists, else from the folder the outlines were drawn on (``correction.images``; the pipeline
passes its data folder). An outline of the image file's full size loses the info bar's rows as the image does; one of
the image's size without the bar is taken as it is. Everything is read and checked before any training.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from drgan.core.errors import ConfigError, DataError
from drgan.data.images import list_images, resample
from drgan.scene.labels import class_mask
from drgan.segmenters.noise_match import match_noise
from drgan.segmenters.pairs import (
    ImageItem,
    Pair,
    _nearest,
    drop_mask_rows,
    mask_instances,
    read_image_item,
    read_raw_mask,
)

LABEL_SUFFIXES = (".tif", ".tiff")
ROI_SUFFIXES = (".zip", ".roi")
MASK_SUFFIXES = (".png",)
SUBFOLDERS = ("", "labels", "rois", "masks")  # where in DIR the outlines may lie


def find_corrections(folder: str | Path, setting: str = "corrected") -> dict[str, Path]:
    """id -> outline file of every corrected image in ``folder`` (module docstring); a DataError names the folder when
    it holds none, or an id with two files (which one is the correction?)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"{setting}={folder}: no such folder (expected the corrected outlines, one file per image)")
    found: dict[str, list[Path]] = {}
    for sub in SUBFOLDERS:
        where = folder / sub if sub else folder
        if not where.is_dir():
            continue
        for path in sorted(where.iterdir()):
            if path.is_file() and path.suffix.lower() in (*LABEL_SUFFIXES, *ROI_SUFFIXES, *MASK_SUFFIXES):
                found.setdefault(path.stem, []).append(path)
    if not found:
        raise DataError(
            f"{setting}={folder}: holds no corrected outlines (expected ID.tif label images, ID.zip ImageJ ROI sets "
            f"or ID.png masks, named by the images' ids, in it or in its labels/, rois/ or masks/ folder)"
        )
    twice = {k: v for k, v in found.items() if len(v) > 1}
    if twice:
        image_id, paths = next(iter(twice.items()))
        raise DataError(
            f"{setting}={folder}: image {image_id!r} has {len(paths)} outline files ({', '.join(str(p) for p in paths)}):"
            " keep the one that holds the corrections"
        )
    return {k: v[0] for k, v in sorted(found.items())}


def rois_to_labels(masks: Iterable[np.ndarray], shape: tuple[int, int]) -> np.ndarray:
    """Filled ROI masks (drgan.data.imagej.read_roi_set) -> int32 labels 1..N in their order (a later ROI takes the
    pixels it shares with an earlier one; an empty ROI gets no id)."""
    labels = np.zeros(shape, np.int32)
    n = 0
    for mask in masks:
        if mask.any():
            n += 1
            labels[mask] = n
    return labels


def read_outline(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """The particles of one outline file as int32 instance labels; ``shape``: the image file's (H, W), which ROIs are
    filled in (label images and masks carry their own)."""
    from drgan.data.imagej import read_label_tiff, read_roi_set

    suffix = path.suffix.lower()
    try:
        if suffix in ROI_SUFFIXES:
            return rois_to_labels(read_roi_set(path, shape).values(), shape)
        if suffix in LABEL_SUFFIXES:
            raw = read_label_tiff(path)[0]
        else:
            raw = read_raw_mask(path)
    except (OSError, ValueError, KeyError) as error:  # a damaged TIFF, a zip that holds no ROIs
        raise DataError(f"corrected outline {path}: cannot be read ({type(error).__name__}: {error})") from None
    raw = np.asarray(raw)
    if raw.ndim != 2:
        raise DataError(f"corrected outline {path}: expected one 2-D label image, got shape {raw.shape}")
    return mask_instances(raw.astype(np.int64), path)


def load_corrections(
    folder: str | Path, images: str | Path | None = None, crop_rows="auto", setting: str = "corrected"
) -> list[tuple[ImageItem, np.ndarray]]:
    """(image, instance labels) of every corrected image of ``folder`` (module docstring), the images from
    ``folder/images`` or ``images``; all read and checked (sizes, ids) before returning."""
    outlines = find_corrections(folder, setting)
    own = Path(folder) / "images"
    images_dir = own if own.is_dir() else images
    if images_dir is None:
        raise ConfigError(
            f"{setting}={folder}: no images/ folder in it; give correction.images=FOLDER (the images the outlines "
            "were drawn on, e.g. the folder the pipeline or analyze read)"
        )
    try:
        paths = list_images(images_dir, list(outlines))
    except DataError as error:
        raise DataError(f"{setting}={folder}: {error} (the outlines are named by the images' ids)") from None
    out = []
    for (image_id, outline), image_path in zip(outlines.items(), paths):
        item = read_image_item(image_path, image_id, crop_rows)
        labels = read_outline(outline, item.file_shape)
        if labels.shape == item.file_shape:
            labels = drop_mask_rows(labels, item.rows, outline) if item.rows else labels
        elif labels.shape != item.image.shape:
            raise DataError(
                f"corrected outline {outline}: size {labels.shape[1]} x {labels.shape[0]} px, its image {image_path} "
                f"{item.file_shape[1]} x {item.file_shape[0]} px (expected the outline drawn on that image)"
            )
        if not labels.any():
            raise DataError(f"corrected outline {outline}: holds no particle (expected every particle of the image)")
        out.append((item, labels))
    return out


def correction_pairs(
    items: Iterable[tuple[ImageItem, np.ndarray]], pixel_scale: float, contour_px: int, noise: float | None = None
) -> list[Pair]:
    """Training pairs of corrected images as the segmenter sees them at inference: each image resampled by its
    ``pixel_scale`` (drgan.data.images.resample, area-averaged when shrinking) with white noise up to the generated
    images' level ``noise`` where cleaner (drgan.segmenters.noise_match), its labels resampled by nearest neighbour
    and their classes drawn ``contour_px`` wide (drgan.scene.labels.class_mask)."""
    pairs = []
    for item, labels in items:
        image = item.image if pixel_scale == 1.0 else resample(item.image, pixel_scale)
        image = np.asarray(match_noise(image, noise), dtype=np.float32)
        labels = labels if image.shape == labels.shape else _nearest(labels, image.shape).astype(np.int32)
        pairs.append(Pair(f"corrected/{item.id}", image, class_mask(labels, contour_px).astype(np.uint8), labels))
    return pairs


def crops_for_share(corrected: list[Pair], n_generated: int, share: float) -> list[int]:
    """Crops per corrected pair and epoch such that they make ``share`` of an epoch beside ``n_generated`` generated
    crops, spread over the corrected images by their area; at least one each."""
    if not 0.0 < share < 1.0:
        raise ConfigError(f"correction.share={share}: expected the corrected images' share of each epoch in (0, 1)")
    total = max(len(corrected), round(n_generated * share / (1.0 - share)))
    areas = np.array([p.image.size for p in corrected], np.float64)
    return [max(1, round(total * a / areas.sum())) for a in areas]
