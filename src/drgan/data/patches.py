"""Mining training patches from real images, without masks.

The discriminator sees real square patches (256 x 256 in the paper). The paper's authors picked them by
hand: patches showing at least three fully displayed particles. drgan picks them automatically:

1. segment each whole image classically (drgan.data.classical: the particle scale estimated once for the set,
   smoothing, Otsu threshold, watershed of the distance transform to split touching particles; scale bars
   and text left out); segments of plausible area are particles;
2. slide a window over the image (a grid with the given stride, centred so both margins are equal);
   a particle is fully displayed in a window when its bounding box touches no window edge;
3. keep windows with >= min_particles such particles, best first, dropping near-duplicates: windows
   overlapping an already kept window of the same image by more than max_overlap of their area, and
   patches whose normalised correlation with a kept patch is within min_corr_distance of 1;
4. background patches: windows free of particles (no foreground, scale bar or text pixel), same duplicate
   rules; fewer than asked (or none) when the images have fewer such windows.

Patch values stay as read: float32 grey in [0, 1].
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

from drgan.core.errors import ConfigError, DataError
from drgan.core.io import write_with
from drgan.core.progress import track
from drgan.data.classical import (
    SegmentParams,
    prepare,
    resolve_params,
    segment_particles,
)
from drgan.data.polarity import check_polarity

log = logging.getLogger(__name__)


# --- classical segmentation (drgan.data.classical) ---------------------------------------------------------


def particle_boxes(labels: np.ndarray, params: SegmentParams) -> np.ndarray:
    """Bounding boxes (K, 4) int: (row0, col0, row1, col1), ends exclusive, of segments of plausible area
    (``params`` resolved: drgan.data.classical.resolve_params)."""
    areas = np.bincount(labels.ravel())
    boxes = []
    for index, slices in enumerate(ndi.find_objects(labels), start=1):
        if slices is not None and params.min_area <= areas[index] <= params.max_area:
            boxes.append((slices[0].start, slices[1].start, slices[0].stop, slices[1].stop))
    return np.array(boxes, dtype=np.int64).reshape(-1, 4)


def full_particle_counts(boxes: np.ndarray, rows: np.ndarray, cols: np.ndarray, height: int, width: int) -> np.ndarray:
    """Particles fully displayed in each window: counts (len(rows), len(cols)).

    Window (r, c) spans rows [r, r + height) and columns [c, c + width); a particle counts when its box
    touches none of the window's edge pixels.
    """
    rows, cols = np.asarray(rows)[:, None], np.asarray(cols)[:, None]
    inside_rows = (boxes[:, 0] > rows) & (boxes[:, 2] < rows + height)  # (R, K)
    inside_cols = (boxes[:, 1] > cols) & (boxes[:, 3] < cols + width)  # (C, K)
    return inside_rows.astype(np.int64) @ inside_cols.T.astype(np.int64)


def count_particles(patch: np.ndarray, params: SegmentParams | None = None, polarity: str = "bright") -> int:
    """Fully displayed particles in one patch segmented on its own (mining segments whole images instead)."""
    try:
        params, _ = resolve_params([patch], params, polarity)
    except DataError:
        return 0
    labels, _ = segment_particles(patch, params, polarity)
    height, width = labels.shape
    return int(full_particle_counts(particle_boxes(labels, params), np.array([0]), np.array([0]), height, width)[0, 0])


# --- augmentation -----------------------------------------------------------------------------------------


def dihedral_augment(patch: np.ndarray, k: int) -> np.ndarray:
    """The k-th of the 8 symmetries of the square (k in 0..7), on the last two axes.

    k % 4 quarter turns counter-clockwise, then a left-right flip for k >= 4; together these are all
    rotations, flips and both transposes. k = 0 is the identity.
    """
    if not 0 <= k < 8:
        raise ConfigError(f"dihedral_augment k={k}: expected an integer in 0..7")
    out = np.rot90(patch, k % 4, axes=(-2, -1))
    if k >= 4:
        out = np.flip(out, axis=-1)
    return np.ascontiguousarray(out)


# --- the mined set ----------------------------------------------------------------------------------------

_ARRAYS_FILE = "patches.npz"
_SUMMARY_FILE = "summary.json"


@dataclass
class PatchSet:
    """Training patches (>= min_particles particles) and background patches (no particles), with provenance.

    Positions are the top-left (row, col) of a patch in its source image after cropping.
    """

    train: np.ndarray  # (N, S, S) float32 in [0, 1]
    train_ids: list[str]
    train_positions: np.ndarray  # (N, 2) int
    train_counts: np.ndarray  # (N,) int: fully displayed particles found in each
    background: np.ndarray  # (M, S, S) float32 in [0, 1]
    background_ids: list[str]
    background_positions: np.ndarray  # (M, 2) int: every one free of particles, scale bars and text
    params: dict = field(default_factory=dict)  # how the set was mined, and the background report

    def __post_init__(self) -> None:
        for name, n in (("train", len(self.train)), ("background", len(self.background))):
            lengths = {len(getattr(self, f"{name}{suffix}")) for suffix in ("_ids", "_positions")}
            if name == "train":
                lengths.add(len(self.train_counts))
            if lengths != {n}:
                raise DataError(
                    f"PatchSet {name}: {n} patches but ids/positions{'/counts' if name == 'train' else ''} of other lengths"
                )

    @property
    def patch_size(self) -> int:
        for array in (self.train, self.background):
            if array.ndim == 3 and len(array):
                return int(array.shape[-1])
        return int(self.params.get("size", 0))

    @staticmethod
    def saved_window(directory: str | Path) -> int | None:
        """Real image px a patch of the saved set covers: its mined window (resample_patches records it), else its
        size; read from its summary alone (no arrays). None when there is no set there."""
        try:
            params = json.loads((Path(directory) / _SUMMARY_FILE).read_text()).get("params") or {}
        except (OSError, ValueError):
            return None
        window = params.get("window") or params.get("size")
        return int(window) if window else None

    def summary(self) -> dict:
        """Counts a user checks first: patches kept, from how many images, particles per patch, background."""
        counts = np.asarray(self.train_counts)
        per_image: dict[str, int] = {}
        for i in self.train_ids:
            per_image[i] = per_image.get(i, 0) + 1
        return {
            "patch_size": self.patch_size,
            "n_train": len(self.train),
            "n_background": len(self.background),
            "n_images_with_train_patches": len(per_image),
            "train_per_image": per_image,
            "particles_per_patch": (
                {"min": int(counts.min()), "median": float(np.median(counts)), "max": int(counts.max())}
                if counts.size
                else {}
            ),
            # mining takes only windows free of particles: every background patch is empty
            "background_empty": len(self.background),
            "background_max_fraction": 0.0,
        }

    def save(self, directory: str | Path) -> Path:
        """Write patches.npz (arrays) and summary.json (ids, parameters, counts); each file atomically."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        arrays = {
            "train": self.train,
            "train_positions": self.train_positions,
            "train_counts": self.train_counts,
            "background": self.background,
            "background_positions": self.background_positions,
        }
        write_with(directory / _ARRAYS_FILE, lambda f: np.savez_compressed(f, **arrays))
        meta = {
            "summary": self.summary(),
            "params": self.params,
            "train_ids": list(self.train_ids),
            "background_ids": list(self.background_ids),
        }
        write_with(directory / _SUMMARY_FILE, lambda f: f.write(json.dumps(meta, indent=1).encode()))
        return directory

    @classmethod
    def load(cls, directory: str | Path) -> PatchSet:
        directory = Path(directory)
        for name in (_ARRAYS_FILE, _SUMMARY_FILE):
            if not (directory / name).is_file():
                raise DataError(f"patch set {directory}: no {name} (expected a folder written by PatchSet.save)")
        try:
            meta = json.loads((directory / _SUMMARY_FILE).read_text())
            with np.load(directory / _ARRAYS_FILE) as npz:
                arrays = {k: npz[k] for k in npz.files}
            return cls(
                train=arrays["train"],
                train_ids=list(meta["train_ids"]),
                train_positions=arrays["train_positions"],
                train_counts=arrays["train_counts"],
                background=arrays["background"],
                background_ids=list(meta["background_ids"]),
                background_positions=arrays["background_positions"],  # a cache's background_fractions (all 0): unread
                params=meta.get("params", {}),
            )
        except DataError:
            raise
        except Exception as exc:  # truncated npz, missing key, bad JSON
            raise DataError(f"patch set {directory}: unreadable ({type(exc).__name__}: {exc})") from exc


# --- mining -----------------------------------------------------------------------------------------------


SCALE_IMAGES = 8  # images the particle scale of a set is estimated on


def window_starts(length: int, size: int, stride: int) -> np.ndarray:
    """Window starts along one axis: windows of ``size`` every ``stride`` px, the grid centred so both margins are
    equal; none where ``length`` < ``size``."""
    if length < size:
        return np.zeros(0, np.int64)
    n = (length - size) // stride + 1
    margin = (length - size - (n - 1) * stride) // 2
    return margin + stride * np.arange(n, dtype=np.int64)


@dataclass
class _Candidate:
    score: float  # higher is better: particle count (train); 0 (background: every one is empty)
    image: int
    row: int
    col: int
    value: float  # particle count (train); 0 (background)


class _DuplicateFilter:
    """Keeps a patch unless it overlaps a kept window of its image too much or correlates with a kept patch."""

    def __init__(self, size: int, max_overlap: float, min_corr_distance: float):
        self.size, self.max_overlap, self.min_corr_distance = size, max_overlap, min_corr_distance
        self.windows: dict[int, list[tuple[int, int]]] = {}
        self.signatures: np.ndarray | None = None  # (capacity, features), grown by doubling
        self.kept = 0

    def _signature(self, patch: np.ndarray) -> np.ndarray:
        # Correlate block means (~64 x 64): cheap, and insensitive to pixel noise.
        f = max(1, self.size // 64)
        s = patch[: patch.shape[0] // f * f, : patch.shape[1] // f * f]
        s = s.reshape(s.shape[0] // f, f, s.shape[1] // f, f).mean(axis=(1, 3)).ravel().astype(np.float64)
        s = s - s.mean()
        norm = np.linalg.norm(s)
        return s / norm if norm > 0 else s

    def accept(self, image: int, row: int, col: int, patch: np.ndarray) -> bool:
        area = self.size * self.size
        for r, c in self.windows.get(image, []):
            overlap = max(0, self.size - abs(r - row)) * max(0, self.size - abs(c - col))
            if overlap > self.max_overlap * area:
                return False
        signature = self._signature(patch)
        if self.kept and np.max(self.signatures[: self.kept] @ signature) > 1 - self.min_corr_distance:
            return False
        if self.signatures is None or self.kept == len(self.signatures):
            grown = np.zeros((max(16, 2 * self.kept), signature.size))
            if self.signatures is not None:
                grown[: self.kept] = self.signatures
            self.signatures = grown
        self.signatures[self.kept] = signature
        self.kept += 1
        self.windows.setdefault(image, []).append((row, col))
        return True


def resample_patches(patches: PatchSet, size: int) -> PatchSet:
    """The same patches area-averaged to ``size`` x ``size`` px (a render resolution below the real px a patch
    covers); positions stay in the source image's px. Anti-aliased, so the real grain is averaged as the render's
    pixels average their samples."""
    from skimage.transform import resize

    def shrink(stack: np.ndarray) -> np.ndarray:
        if stack.ndim != 3 or len(stack) == 0:
            return np.zeros((0, size, size), np.float32)
        return np.stack([
            resize(p, (size, size), order=1, anti_aliasing=True, preserve_range=True) for p in stack
        ]).astype(np.float32)  # fmt: skip

    return replace(
        patches,
        train=shrink(patches.train),
        background=shrink(patches.background),
        params={**patches.params, "window": patches.patch_size, "size": int(size)},
    )


def check_image_sizes(images: Sequence[np.ndarray], ids: Sequence[str], size: int) -> None:
    """Every image grey (H, W) and at least one patch large; a DataError naming the first that is not."""
    for image, name in zip(images, ids):
        if image.ndim != 2:
            raise DataError(f"image {name!r}: shape {image.shape} (expected one grey channel, (H, W))")
        if image.shape[0] < size or image.shape[1] < size:
            raise DataError(
                f"image {name!r}: {image.shape[1]} x {image.shape[0]} px (W x H) is smaller than a {size} x {size} patch"
            )


def scale_sample(items: Sequence) -> list:
    """The images (or their ids) the particle scale of a set is searched on: up to SCALE_IMAGES spread over it."""
    return list(items[:: max(1, len(items) // SCALE_IMAGES)][:SCALE_IMAGES])


STRIDE = 128  # px between candidate windows: data.stride's default (conf/gan/data/real_patches.yaml)


def _stack(images: Sequence[np.ndarray], chosen: list[_Candidate], size: int) -> np.ndarray:
    """The ``chosen`` windows of ``images`` as one (n, size, size) float32 array."""
    patches = [images[k.image][k.row : k.row + size, k.col : k.col + size] for k in chosen]
    return np.stack(patches).astype(np.float32) if patches else np.zeros((0, size, size), np.float32)


def _positions(chosen: list[_Candidate]) -> np.ndarray:
    """The ``chosen`` windows' (row, col), (n, 2) int64."""
    return np.array([(k.row, k.col) for k in chosen], dtype=np.int64).reshape(-1, 2)


def mine_patches(
    images: Sequence[np.ndarray],
    ids: Sequence[str],
    size: int = 256,
    stride: int = STRIDE,
    min_particles: int = 3,
    n_background: int = 200,
    *,
    background_stride: int | None = None,
    segment: SegmentParams | None = None,
    max_overlap: float = 0.5,
    min_corr_distance: float = 0.05,
    polarity: str = "bright",
    progress: bool = True,
) -> PatchSet:
    """Select training patches with >= min_particles fully displayed particles, and n_background empty ones.

    images: grey float images (H, W) in [0, 1], info bars already cropped (see read_grey); ids: one name
    each. polarity: "bright" or "dark" particles (drgan.data.polarity); patches keep the images' own
    values. Windows lie on a grid with the given stride (background_stride for background, default
    size // 4: a fine grid finds the empty corners between agglomerates).
    Near-duplicates: overlap with a kept window of the same image above max_overlap (fraction of patch
    area), or correlation with any kept patch above 1 - min_corr_distance. Training patches are taken
    best first (most particles); background patches only from windows free of particles, scale bars and
    text: if fewer than n_background such windows exist, fewer are taken (zero allowed) and a warning says
    so (also in PatchSet.params["background_report"]). ``segment``: drgan.data.classical.SegmentParams;
    lengths not set follow from the particle scale, estimated once on up to SCALE_IMAGES of the images.
    """
    check_polarity(polarity, "mine_patches polarity")
    background_stride = background_stride or max(1, size // 4)
    _check_mining(images, ids, size, stride, background_stride, min_particles, n_background, max_overlap,
                  min_corr_distance)  # fmt: skip
    segment, estimate = _mining_scale(images, segment, polarity, progress)
    train_candidates, background_candidates = _candidates(
        images, segment, polarity, size, stride, background_stride, min_particles, progress
    )
    keep = {"size": size, "max_overlap": max_overlap, "min_corr_distance": min_corr_distance}
    train = _select(images, train_candidates, None, **keep)
    background = _select(images, background_candidates, n_background, **keep)
    report = {
        "requested": n_background,
        "found": len(background),
        "empty": len(background),
        "max_foreground_fraction": 0.0,
    }
    if len(background) < n_background:
        log.warning(
            "background patches: only %d of the %d requested %d px windows are free of particles (and of scale "
            "bars and text) once near-duplicates are dropped; taking those %d. A background patch must hold no "
            "particle: lower data.background_stride for more candidate windows, or add images with empty areas",
            len(background), n_background, size, len(background),
        )  # fmt: skip

    params = {
        "size": size,
        "stride": stride,
        "background_stride": background_stride,
        "min_particles": min_particles,
        "n_background": n_background,
        "max_overlap": max_overlap,
        "min_corr_distance": min_corr_distance,
        "segment": segment.as_dict(),
        "scale_estimate": estimate.as_dict() if estimate else None,
        "polarity": polarity,
        "background_report": report,
    }
    return PatchSet(
        train=_stack(images, train, size),
        train_ids=[str(ids[k.image]) for k in train],
        train_positions=_positions(train),
        train_counts=np.array([int(k.value) for k in train], dtype=np.int64),
        background=_stack(images, background, size),
        background_ids=[str(ids[k.image]) for k in background],
        background_positions=_positions(background),
        params=params,
    )


def _check_mining(images, ids, size, stride, background_stride, min_particles, n_background, max_overlap,
                  min_corr_distance) -> None:  # fmt: skip
    """`mine_patches`' arguments checked before any image is segmented: a ConfigError naming the bad one."""
    if len(images) != len(ids):
        raise ConfigError(f"mine_patches: {len(images)} images but {len(ids)} ids")
    if len(set(ids)) != len(ids):
        raise ConfigError("mine_patches: ids must be unique")
    if size < 8 or stride < 1 or background_stride < 1:
        raise ConfigError(
            f"mine_patches: size={size}, stride={stride}, background_stride={background_stride}: expected size >= 8, strides >= 1"
        )
    if min_particles < 1 or n_background < 0:
        raise ConfigError(
            f"mine_patches: min_particles={min_particles}, n_background={n_background}: expected >= 1 and >= 0"
        )
    if not 0 <= max_overlap < 1 or not 0 <= min_corr_distance < 1:
        raise ConfigError(
            f"mine_patches: max_overlap={max_overlap}, min_corr_distance={min_corr_distance}: expected in [0, 1)"
        )
    check_image_sizes(images, ids, size)


def _mining_scale(images, segment, polarity: str, progress: bool):
    """(SegmentParams, the scale search or None): one particle scale for the whole set (up to SCALE_IMAGES images
    spread over it), so that every image is segmented alike; the keys given are kept."""
    sample = scale_sample(images)
    given = SegmentParams.from_config(segment)
    if given.scale is None or given.neck_depth is None:
        log.info(
            "data: searching the particle scale on %d of the %d images (data.segment.scale/neck_depth not set; "
            "about a minute per image on 2 cores)", len(sample), len(images),
        )  # fmt: skip
    started = time.perf_counter()
    segment, estimate = resolve_params(sample, segment, polarity, progress=progress)
    if estimate is not None or given.neck_depth is None:
        pinned = f"data.segment.scale={segment.scale} data.segment.neck_depth={segment.neck_depth}"
        if segment.min_separability != given.min_separability:
            pinned += f" data.segment.min_separability={segment.min_separability}"
        log.info(
            "data: particle scale %.2f px, neck depth %s (searched in %.0f s); the same images mine alike without the "
            "search with %s", segment.scale, segment.neck_depth, time.perf_counter() - started, pinned,
        )  # fmt: skip
    return segment, estimate


def _candidates(images, segment, polarity, size, stride, background_stride, min_particles, progress):
    """(training candidates, background candidates) over every image: windows on the ``stride`` grid showing at
    least ``min_particles`` whole particles (scored by their count), windows on the ``background_stride`` grid free
    of particles and annotations (scale bars, text)."""
    train_candidates: list[_Candidate] = []
    background_candidates: list[_Candidate] = []
    for index, image in enumerate(track(images, "mining patches", unit="images") if progress else images):
        labels, foreground = segment_particles(image, segment, polarity)
        # Background windows hold neither particle nor annotation (scale bar, text) pixels.
        occupied = foreground | prepare(image, polarity, segment.annotations).annotations
        height, width = image.shape
        rows, cols = window_starts(height, size, stride), window_starts(width, size, stride)
        counts = full_particle_counts(particle_boxes(labels, segment), rows, cols, size, size)
        for i, r in enumerate(rows):
            for j, c in enumerate(cols):
                if counts[i, j] >= min_particles:
                    train_candidates.append(_Candidate(float(counts[i, j]), index, int(r), int(c), float(counts[i, j])))
        # Foreground fraction of every background window from one summed-area table.
        rows, cols = window_starts(height, size, background_stride), window_starts(width, size, background_stride)
        table = np.pad(occupied.astype(np.int64).cumsum(0).cumsum(1), ((1, 0), (1, 0)))
        sums = (
            table[rows[:, None] + size, cols + size]
            - table[rows[:, None], cols + size]
            - table[rows[:, None] + size, cols]
            + table[rows[:, None], cols]
        )
        for i, r in enumerate(rows):
            for j, c in enumerate(cols):
                if sums[i, j] == 0:  # only windows free of particles are backgrounds
                    background_candidates.append(_Candidate(0.0, index, int(r), int(c), 0.0))
    return train_candidates, background_candidates


def _select(images, candidates: list[_Candidate], limit: int | None, size: int, max_overlap: float,
            min_corr_distance: float) -> list[_Candidate]:  # fmt: skip
    """The candidates best first (ties by image and position), near-duplicates dropped, at most ``limit``; in image
    and position order."""
    candidates = sorted(candidates, key=lambda k: (-k.score, k.image, k.row, k.col))
    keep = _DuplicateFilter(size, max_overlap, min_corr_distance)
    chosen = []
    for k in candidates:
        if limit is not None and len(chosen) >= limit:
            break
        if keep.accept(k.image, k.row, k.col, images[k.image][k.row : k.row + size, k.col : k.col + size]):
            chosen.append(k)
    return sorted(chosen, key=lambda k: (k.image, k.row, k.col))


# --- checking by eye --------------------------------------------------------------------------------------


def contact_sheet(
    patches: PatchSet | np.ndarray,
    path: str | Path,
    *,
    title: str | None = None,
    captions: Sequence[str] | None = None,
    ncols: int = 16,
    thumb: int = 128,
    max_background: int = 64,
) -> Path:
    """Write a PNG grid of patches: a PatchSet's training patches (captioned id, position, particle
    count) and up to max_background of its background patches, sampled evenly over them (captioned id, position);
    or a plain (N, H, W) array with optional captions."""
    from PIL import Image, ImageDraw, ImageFont

    if isinstance(patches, PatchSet):
        n = len(patches.background)
        shown = np.unique(np.linspace(0, n - 1, min(max_background, n)).round().astype(int))
        sections = [
            (
                f"selected: {len(patches.train)} patches",
                patches.train,
                [
                    f"{i} {r},{c} n={n}"
                    for i, (r, c), n in zip(patches.train_ids, patches.train_positions, patches.train_counts)
                ],
            ),
            (
                f"background: {len(patches.background)} patches (showing {len(shown)})",
                patches.background[shown],
                [
                    f"{patches.background_ids[k]} {patches.background_positions[k][0]},{patches.background_positions[k][1]}"
                    for k in shown
                ],
            ),
        ]
        title = title or f"PatchSet: {len(patches.train)} selected, {len(patches.background)} background"
    else:
        array = np.asarray(patches)
        sections = [(f"{len(array)} patches", array, list(captions) if captions is not None else [""] * len(array))]
        title = title or ""

    font = ImageFont.load_default(size=max(9, thumb // 12))
    line = max(12, thumb // 8)
    gap = 4
    width = ncols * (thumb + gap) + gap
    heights = [line + max(1, -(-len(arr) // ncols)) * (thumb + gap) for _, arr, _ in sections]
    sheet = Image.new("L", (width, line * 2 + sum(heights) + gap), color=255)
    draw = ImageDraw.Draw(sheet)
    draw.text((gap, gap), title, fill=0, font=ImageFont.load_default(size=max(12, thumb // 8)))
    y = line * 2
    for heading, arr, caps in sections:
        draw.text((gap, y), heading, fill=0, font=font)
        y += line
        for n, patch in enumerate(arr):
            tile = Image.fromarray((np.clip(patch, 0, 1) * 255).astype(np.uint8)).resize((thumb, thumb), Image.BILINEAR)
            x0, y0 = gap + (n % ncols) * (thumb + gap), y + (n // ncols) * (thumb + gap)
            sheet.paste(tile, (x0, y0))
            if n < len(caps) and caps[n]:
                draw.rectangle((x0, y0, x0 + thumb - 1, y0 + line - 2), fill=0)
                draw.text((x0 + 2, y0), caps[n], fill=255, font=font)
        y += max(1, -(-len(arr) // ncols)) * (thumb + gap)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_with(path, lambda f: sheet.save(f, format="PNG"))
    return path
