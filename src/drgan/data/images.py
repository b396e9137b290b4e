"""Reading real microscope images as one grey channel in [0, 1], finding them by id, and reading splits.

Every reader returns float32 arrays of shape (H, W) with values in [0, 1], whatever the file holds:
8-bit values are divided by 255, 16-bit values by 65535 (the full range of the type, not the image's
own maximum, so that brightness stays comparable between images of one instrument). Values are left
in the file's encoding (detector counts or gamma-encoded grey); nothing is linearised.

- palette images are mapped through their palette, then to luminance;
- RGB(A) images go to luminance with the ITU-R BT.601 weights (0.299, 0.587, 0.114), the same weights
  PIL's "L" conversion uses; alpha is ignored (microscope images have no meaningful transparency);
- floating-point images must already lie in [0, 1]: a float image outside that range has an unknown
  scale (counts? a normalised export?), and rescaling it by its own min and max would silently change
  contrast from image to image, so it is refused with a DataError instead.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import tifffile
from PIL import Image, UnidentifiedImageError

from drgan.core.errors import DataError

IMAGE_SUFFIXES = (".tif", ".tiff", ".png", ".jpg", ".jpeg")
_TIFF_SUFFIXES = (".tif", ".tiff")
_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float64)


def read_grey(path: str | Path, crop_rows: tuple[int, int] | str | None = None) -> np.ndarray:
    """Read a TIFF, PNG or JPEG image as float32 (H, W) grey values in [0, 1].

    crop_rows: a row range [start, stop) to drop, e.g. a microscope's info bar; the TiO2 SEM images
    carry theirs in rows 712-767, so crop_rows=(712, 768) keeps rows 0-711. "auto": drop the info bar
    that `info_bar_rows` finds in this image, if any.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"image {path}: no such file (expected a TIFF, PNG or JPEG image)")
    suffix = path.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise DataError(f"image {path}: unsupported file kind {suffix!r} (expected one of {', '.join(IMAGE_SUFFIXES)})")
    try:
        raw = _read_tiff(path) if suffix in _TIFF_SUFFIXES else _read_pil(path)
    except DataError:
        raise
    except Exception as exc:  # corrupt or truncated files raise many kinds of errors in tifffile and PIL
        raise DataError(
            f"image {path}: cannot be read as a {suffix[1:].upper()} image ({type(exc).__name__}: {exc})"
        ) from exc
    grey = _to_unit_grey(raw, path)
    crop_rows = resolve_crop_rows(crop_rows, grey, path)
    if crop_rows is not None:
        grey = _drop_rows(grey, crop_rows, path)
    return grey


# An info bar (scale bar, magnification, detector) is a band of rows along the top or bottom edge, most of whose
# pixels are exactly black or exactly white, with text; image rows have no such plateau (TiO2 SEM and TSEM: at
# most 33 % of a row's pixels share one value, none at 0 or 1; their bar rows: 85-100 % black).
_BAR_ROW_FRACTION = 0.5  # least share of a row at exactly 0 or 1 for a bar row
_BAR_MAX_SHARE = 0.3  # a bar covers at most this share of the image's rows
_BAR_MIN_ROWS = 8
_BAR_EDGE_ROWS = 4  # image rows between a bar and the image edge that still go with the bar (TiO2: rows 766-767)


def info_bar_rows(grey: np.ndarray) -> tuple[int, int] | None:
    """Rows [start, stop) of an info bar along the bottom (or top) edge of ``grey``, or None when there is none.

    Bar rows have at least half their pixels exactly black (0) or exactly white (1); a bar is a run of such
    rows (gaps of up to 3 rows allowed: text lines) of at least 8 rows, covering at most 30 % of the image,
    ending within 4 rows of the edge (those rows are dropped with it).
    """
    grey = np.asarray(grey)
    height = grey.shape[0]
    extreme = np.maximum((grey == 0).mean(axis=1), (grey == 1).mean(axis=1)) >= _BAR_ROW_FRACTION
    for rows, flip in ((extreme[::-1], True), (extreme, False)):  # bottom edge first, then top
        hits = np.flatnonzero(rows[: int(_BAR_MAX_SHARE * height) + _BAR_EDGE_ROWS])
        if hits.size == 0 or hits[0] > _BAR_EDGE_ROWS:
            continue
        end = hits[0]
        for k in hits[1:]:
            if k - end > 4:
                break
            end = k
        if end + 1 - hits[0] < _BAR_MIN_ROWS or end + 1 > _BAR_MAX_SHARE * height:
            continue
        return (int(height - end - 1), int(height)) if flip else (0, int(end) + 1)
    return None


def resolve_crop_rows(crop_rows, grey: np.ndarray, path: str | Path = "image") -> tuple[int, int] | None:
    """The [start, stop) rows to drop: ``crop_rows`` as given (a pair or None), or the detected bar for "auto"."""
    if crop_rows is None:
        return None
    if isinstance(crop_rows, str):
        if crop_rows != "auto":
            raise DataError(f"image {path}: crop_rows={crop_rows!r}: expected [start, stop), auto or null")
        return info_bar_rows(grey)
    rows = tuple(crop_rows)
    if len(rows) != 2:
        raise DataError(f"image {path}: crop_rows={list(rows)}: expected two row numbers [start, stop), auto or null")
    return int(rows[0]), int(rows[1])


def _read_tiff(path: Path) -> np.ndarray:
    """First page of a TIFF as a numeric array; palette pages come back mapped to RGB in [0, 1]."""
    with tifffile.TiffFile(path) as tif:
        if not tif.pages:
            raise DataError(f"image {path}: TIFF holds no image page")
        page = tif.pages[0]
        data = page.asarray()
        if page.photometric == tifffile.PHOTOMETRIC.PALETTE and page.colormap is not None:
            # The colormap is (3, 2**bits) uint16 in TIFF files.
            colormap = np.asarray(page.colormap, dtype=np.float64) / 65535.0
            return colormap[:, data].transpose(*range(1, data.ndim + 1), 0)
        if page.photometric == tifffile.PHOTOMETRIC.MINISWHITE:
            data = _invert(data, path)
        return data


def _read_pil(path: Path) -> np.ndarray:
    """A PNG or JPEG through PIL; palette images come back mapped to RGB(A) uint8."""
    try:
        with Image.open(path) as img:
            img.load()
            if img.mode == "P":
                img = img.convert("RGBA" if "transparency" in img.info else "RGB")
            elif img.mode == "1":
                img = img.convert("L")
            elif img.mode not in ("L", "LA", "RGB", "RGBA", "I;16", "I;16B", "I;16L", "I"):
                raise DataError(f"image {path}: unsupported PIL mode {img.mode!r} (expected grey, palette or RGB(A))")
            data = np.asarray(img)
            if img.mode == "I":
                # PIL opens 16-bit grey PNGs as 32-bit "I"; their values must fit 16 bits.
                if data.size and (data.min() < 0 or data.max() > 65535):
                    raise DataError(
                        f"image {path}: 32-bit integer values outside 0-65535 (expected an 8- or 16-bit image)"
                    )
                data = data.astype(np.uint16)
            return data
    except UnidentifiedImageError as exc:
        raise DataError(f"image {path}: not a recognisable image file ({exc})") from exc


def _invert(data: np.ndarray, path: Path) -> np.ndarray:
    if np.issubdtype(data.dtype, np.unsignedinteger):
        return np.iinfo(data.dtype).max - data
    if data.dtype == np.bool_:
        return ~data
    return 1.0 - data


def _to_unit_grey(data: np.ndarray, path: Path) -> np.ndarray:
    """Scale by the type's range and reduce colour channels to luminance."""
    data = np.asarray(data)
    if data.dtype == np.bool_:
        values = data.astype(np.float64)
    elif data.dtype == np.uint8:
        values = data / 255.0
    elif data.dtype in (np.uint16, np.dtype(">u2"), np.dtype("<u2")):
        values = data / 65535.0
    elif np.issubdtype(data.dtype, np.floating):
        values = data.astype(np.float64)
        if not np.all(np.isfinite(values)):
            raise DataError(f"image {path}: holds NaN or infinite values (expected finite values in [0, 1])")
        if values.size and (values.min() < 0.0 or values.max() > 1.0):
            raise DataError(
                f"image {path}: floating-point values span [{values.min():.4g}, {values.max():.4g}] "
                "(expected [0, 1]; rescale the image yourself, its scale is not known here)"
            )
    else:
        raise DataError(
            f"image {path}: unsupported pixel type {data.dtype} (expected 8- or 16-bit integers or floats in [0, 1])"
        )

    if values.ndim == 3 and values.shape[-1] in (3, 4):
        values = values[..., :3] @ _LUMA
    elif values.ndim == 3 and values.shape[-1] == 2:  # grey + alpha
        values = values[..., 0]
    if values.ndim != 2:
        raise DataError(f"image {path}: array of shape {data.shape} (expected one 2-D grey, palette or RGB(A) image)")
    return np.clip(values, 0.0, 1.0).astype(np.float32)


def _drop_rows(grey: np.ndarray, crop_rows: tuple[int, int], path: Path) -> np.ndarray:
    start, stop = (int(v) for v in crop_rows)
    height = grey.shape[0]
    if not 0 <= start < stop <= height:
        raise DataError(
            f"image {path}: crop_rows {crop_rows} is not a row range [start, stop) inside its {height} rows"
        )
    if stop - start == height:
        raise DataError(f"image {path}: crop_rows {crop_rows} would drop all {height} rows")
    return np.ascontiguousarray(np.concatenate([grey[:start], grey[stop:]], axis=0))


def list_images(folder: str | Path, ids: Sequence[str] | None = None) -> list[Path]:
    """Image files in folder, matched by file stem.

    ids=None: every image in the folder, sorted by stem. Otherwise one path per id, in the order given.
    An id must match exactly one image (two files 'a.tif' and 'a.png' make 'a' ambiguous).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"image folder {folder}: no such folder")
    by_stem: dict[str, list[Path]] = {}
    for p in sorted(folder.iterdir()):
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES:
            by_stem.setdefault(p.stem, []).append(p)
    if not by_stem:
        raise DataError(
            f"image folder {folder}: holds no image files (expected files ending in {', '.join(IMAGE_SUFFIXES)})"
        )
    stems = sorted(by_stem) if ids is None else [str(i) for i in ids]
    missing = [s for s in stems if s not in by_stem]
    if missing:
        shown = ", ".join(missing[:10]) + (" ..." if len(missing) > 10 else "")
        raise DataError(f"image folder {folder}: no image for {len(missing)} requested id(s): {shown}")
    ambiguous = [s for s in stems if len(by_stem[s]) > 1]
    if ambiguous:
        raise DataError(
            f"image folder {folder}: id {ambiguous[0]!r} matches several files {[p.name for p in by_stem[ambiguous[0]]]}"
        )
    return [by_stem[s][0] for s in stems]


SPLIT_FILE = "split.json"


def default_split(folder: str | Path) -> Path | None:
    """The split file of an image folder found by ``split: auto``: ``folder/split.json``, else one beside the folder
    (``folder/../split.json``, as in DATASET/images + DATASET/split.json), else None (every image trains)."""
    folder = Path(folder)
    return next((p for p in (folder / SPLIT_FILE, folder.parent / SPLIT_FILE) if p.is_file()), None)


def read_split(path: str | Path) -> dict[str, list[str]]:
    """A split file: a JSON object mapping split names to lists of image ids (strings).

    It must name 'train' and 'test'; other splits (e.g. 'val') are allowed. No id may appear twice,
    within one split or across splits: a test image that leaks into training spoils every benchmark.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"split file {path}: no such file")
    try:
        split = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(f"split file {path}: not valid JSON ({exc})") from exc
    if not isinstance(split, dict):
        raise DataError(f'split file {path}: expected a JSON object like {{"train": [ids], "test": [ids]}}')
    for key in ("train", "test"):
        if key not in split:
            raise DataError(f"split file {path}: no {key!r} list (expected keys 'train' and 'test')")
    seen: dict[str, str] = {}
    for name, ids in split.items():
        if not isinstance(ids, list) or not all(isinstance(i, str) for i in ids):
            raise DataError(f"split file {path}: {name!r} must be a list of id strings")
        for i in ids:
            if i in seen:
                where = f"in both {seen[i]!r} and {name!r}" if seen[i] != name else f"twice in {name!r}"
                raise DataError(f"split file {path}: id {i!r} appears {where} (splits must not overlap)")
            seen[i] = name
    return {name: list(ids) for name, ids in split.items()}


def resample(image: np.ndarray, scale: float) -> np.ndarray:
    """``image`` (H, W) resized by ``scale`` (at least 1 px a side): area-averaged (anti-aliased) when shrinking,
    as the GAN's real patches were (drgan.data.patches.resample_patches); unchanged for 1. Inference resamples real
    images by a segmenter's pixel scale with it (drgan.segmenters.inference), drgan.segment its pairs to a working
    scale (drgan.segmenters.pairs.rescale_pair)."""
    if scale == 1.0:
        return image
    from skimage.transform import resize

    image = np.asarray(image, dtype=np.float32)
    shape = tuple(max(1, int(round(n * scale))) for n in image.shape)
    return resize(image, shape, order=1, anti_aliasing=scale < 1, preserve_range=True).astype(np.float32)
