"""Image/mask pairs for the segmenter, and the random-crop training dataset.

Two sources, both giving float32 grey images in [0, 1] and uint8 class masks {0 background, 1 particle,
2 contour}, and in generated masks also ``IGNORE`` = 255 (no class: the loss and val/dsc leave those pixels out,
drgan.segmenters.module):
- generated data (`python -m drgan.generate`): the items DIR/manifest.json lists, images/ID.png + masks/ID.png
  (classes; 255 on the particles of partial backgrounds), read through drgan.synthetic; a folder of such pairs
  without a manifest (made by hand) is paired by file name, and a folder that is neither is refused, naming it;
- real annotated data: DATASET/images/ID.<ext> and binary masks (0/255, or 0/1) or instance maps (0 background,
  one id per particle, e.g. 16-bit) DATASET/masks/ID<suffix>.<ext> (suffix "_m" as in the TiO2 SEM set, or none as
  in TSEM; `mask_suffix`); a mask has its image's size, or the size left after the image's info bar is cropped
  (TSEM publishes its masks so). Instances are a binary mask's 4-connected components or an instance map's ids,
  turned into classes with `class_mask(labels, contour_px)`.
Every pair is checked (sizes, mask values) before any training or evaluation starts.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage
from torch.utils.data import Dataset

from drgan.core.errors import ConfigError, DataError
from drgan.data.images import IMAGE_SUFFIXES, list_images, read_grey, read_split, resample, resolve_crop_rows
from drgan.scene.labels import BACKGROUND, CONTOUR, IGNORE, PARTICLE, centre_distance, class_mask
from drgan.synthetic.manifest import image_mask_pairs

_FOUR_CONNECTED = ndimage.generate_binary_structure(2, 1)

# Per-image input normalisation of the segmenter. "zscore" (nnU-Net's default for non-CT images):
# (x - mean) / std of the whole image, so that a model does not depend on the detector's brightness and
# contrast settings (which differ between microscopes and sessions, and between synthetic and real data).
NORMALIZATIONS = ("none", "zscore")


def check_normalize(mode: str, name: str = "normalize") -> str:
    if mode not in NORMALIZATIONS:
        raise ConfigError(f"{name}: expected one of {', '.join(NORMALIZATIONS)}, got {mode!r}")
    return mode


def normalization(image: np.ndarray, mode: str) -> tuple[float, float]:
    """(shift, scale) such that (image - shift) / scale is the network input for a whole image."""
    if check_normalize(mode) == "none":
        return 0.0, 1.0
    image = np.asarray(image, dtype=np.float64)
    return float(image.mean()), max(float(image.std()), 1e-3)


@dataclass
class Pair:
    id: str
    image: np.ndarray  # float32 (H, W) in [0, 1]
    mask: np.ndarray  # uint8 (H, W) classes {0, 1, 2}, and IGNORE (255) where no class is known
    labels: np.ndarray | None = (
        None  # int (H, W) instance ids (0 background) where known: generated labels/, real masks
    )

    def instances(self) -> np.ndarray:
        """Instance ids: ``labels``, else the particle class's 4-connected components (a hand-made pair)."""
        if self.labels is not None:
            return self.labels
        return instance_labels(self.mask == PARTICLE)


def read_raw_mask(path: Path, crop_rows=None) -> np.ndarray:
    """A mask file as its integer values (no scaling), info-bar rows dropped like read_grey does."""
    from PIL import Image

    if not path.is_file():
        raise DataError(f"mask {path}: no such file")
    try:
        if path.suffix.lower() in (".tif", ".tiff"):
            import tifffile

            arr = np.asarray(tifffile.imread(path))
        else:
            with Image.open(path) as img:
                arr = np.asarray(img)
    except Exception as exc:
        raise DataError(f"mask {path}: cannot be read ({type(exc).__name__}: {exc})") from exc
    if arr.ndim == 3 and arr.shape[-1] in (3, 4) and np.all(arr[..., :3] == arr[..., :1]):
        arr = arr[..., 0]
    if arr.ndim != 2 or not (arr.dtype == bool or np.issubdtype(arr.dtype, np.integer)):
        raise DataError(f"mask {path}: expected a 2-D integer mask, got shape {arr.shape}, dtype {arr.dtype}")
    return drop_mask_rows(arr, crop_rows, path)


def drop_mask_rows(arr: np.ndarray, crop_rows, path: Path) -> np.ndarray:
    """``arr`` without the rows [start, stop) of ``crop_rows`` (None: as it is); ``path`` names the file in errors."""
    if crop_rows is None:
        return arr
    start, stop = (int(v) for v in crop_rows)
    if not 0 <= start < stop <= arr.shape[0]:
        raise DataError(f"mask {path}: crop_rows {tuple(crop_rows)} is not a row range inside its {arr.shape[0]} rows")
    return np.concatenate([arr[:start], arr[stop:]], axis=0)


def _check_same_size(image_shape, mask_shape, image_path: Path, mask_path: Path, cropped=None) -> None:
    """Image and mask files must be the same size; compared before any crop, which drops the same rows of both.
    ``cropped``: the image's size after its info bar is dropped, which a mask may also have."""
    if tuple(image_shape) != tuple(mask_shape):
        (mh, mw), (ih, iw) = mask_shape, image_shape
        also = f" or, without its info bar, {cropped[1]} x {cropped[0]} px" if cropped is not None else ""
        raise DataError(
            f"mask {mask_path}: size {mw} x {mh} px (W x H) differs from its image {image_path}: {iw} x {ih} px{also} "
            "(a mask must have its image's size)"
        )


def binary_mask(raw: np.ndarray, path: Path) -> np.ndarray:
    """A real annotation (0/255 or 0/1) as bool particle pixels; any other value is refused."""
    values = np.unique(raw)
    allowed = {0, 255} if values.max(initial=0) > 1 else {0, 1}
    bad = sorted(set(values.tolist()) - allowed)
    if bad:
        raise DataError(
            f"mask {path}: unexpected values {bad[:5]} (expected a binary mask of 0 and 255, or 0 and 1; an instance "
            "map with one id per particle is read from a 16-bit image)"
        )
    return raw > 0


def instance_labels(particle: np.ndarray) -> np.ndarray:
    """4-connected components of a binary mask (int32, 0 = background)."""
    labels, _ = ndimage.label(particle, structure=_FOUR_CONNECTED)
    return labels.astype(np.int32)


def is_instance_map(raw: np.ndarray) -> bool:
    """Whether an annotation holds one id per particle (0 background, 1..N; a 16- or 32-bit label image, as Cellpose,
    CVAT or the EMPS data set write them) rather than a binary mask. An 8-bit file is always read as a binary mask: grey
    values there are more often a resampled or compressed binary mask's edges than particle ids."""
    raw = np.asarray(raw)
    if raw.dtype == bool or raw.dtype.itemsize < 2:
        return False
    values = set(np.unique(raw).tolist())
    return not (values <= {0, 255} or values <= {0, 1})


def mask_instances(raw: np.ndarray, path: Path) -> np.ndarray:
    """Instance labels (int32, 0 background, 1..N) of an annotation: a binary mask (0/255 or 0/1) as its
    4-connected components (touching particles drawn apart), an instance map as its own ids, renumbered 1..N
    (touching particles stay apart however they touch)."""
    if not is_instance_map(raw):
        return instance_labels(binary_mask(raw, path))
    if raw.min() < 0:
        raise DataError(f"mask {path}: negative values (expected 0 background and one positive id per particle)")
    ids, labels = np.unique(raw, return_inverse=True)
    labels = labels.reshape(raw.shape).astype(np.int32)
    return labels if ids[0] == 0 else labels + 1  # id 0 (background) first when present


MASK_SUFFIXES = ("_m", "")  # mask_suffix=auto tries these, in order


def real_mask_path(masks_dir: Path, image_id: str, mask_suffix: str | None = "auto") -> Path:
    """masks_dir/ID<mask_suffix>.<ext>; ``mask_suffix`` "auto" (or None) tries ID_m.* then ID.*."""
    stems = MASK_SUFFIXES if mask_suffix in (None, "auto") else (str(mask_suffix),)
    for stem in stems:
        for ext in IMAGE_SUFFIXES:
            if (masks_dir / f"{image_id}{stem}{ext}").is_file():
                return masks_dir / f"{image_id}{stem}{ext}"
    tried = " or ".join(f"{image_id}{stem}.tif" for stem in stems)
    raise DataError(
        f"mask folder {masks_dir}: no mask for image id {image_id!r} (expected {tried} or another image "
        "type; set mask_suffix if your masks are named otherwise)"
    )


def real_ids(data_dir: Path, split: str | Path | None, subset: str, setting: str = "real") -> list[str]:
    """Ids of one subset ('train' or 'test') of a real dataset folder (images/, masks/, split.json), or of every
    image in images/ (subset 'all': no split file needed). setting: the command-line key that named the folder,
    for the message when it is missing."""
    data_dir = check_dataset_folder(data_dir, setting, REAL_DATASET)
    if subset == "all":
        return [p.stem for p in list_images(data_dir / "images")]
    split_path = Path(split) if split else data_dir / "split.json"
    ids = read_split(split_path)
    if subset not in ids:
        raise ConfigError(f"split file {split_path}: no subset {subset!r} (has {sorted(ids)})")
    return ids[subset]


def check_dataset_folder(data_dir, setting: str, what: str) -> Path:
    """``data_dir`` as a Path, or a DataError naming the setting (``real=``, ``data=``) when it is no folder: a
    missing folder would otherwise be reported as the first missing file inside it (split.json, images/)."""
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        kind = "a file, not a folder" if data_dir.exists() else "no such folder"
        raise DataError(f"{setting}={data_dir}: {kind} (expected {what})")
    return data_dir


REAL_DATASET = "a real dataset folder with images/, masks/ and split.json"


@dataclass(frozen=True)
class ImageItem:
    """An image to segment: its id, its grey values without the info bar, and the rows [start, stop) dropped from
    the file's image (None: none), so that a class map of the file's full size can lose the same rows."""

    id: str
    image: np.ndarray  # float32 (H, W) in [0, 1]
    rows: tuple[int, int] | None = None

    @property
    def file_shape(self) -> tuple[int, int]:
        """The image file's (H, W), info bar included."""
        h, w = self.image.shape
        return (h + self.rows[1] - self.rows[0], w) if self.rows else (h, w)


def read_image_item(path: Path, image_id: str, crop_rows="auto") -> ImageItem:
    """One image file as an ImageItem; crop_rows as in ``read_grey`` ("auto": the info bar found in this image)."""
    full = read_grey(path)
    rows = resolve_crop_rows(crop_rows, full, path)
    return ImageItem(image_id, read_grey(path, rows) if rows else full, rows)


def load_real_items(
    data_dir, ids, crop_rows="auto", mask_suffix: str | None = "auto", masks: str = "masks"
) -> list[tuple[ImageItem, np.ndarray]]:
    """(image, instance labels) of real images; every file is read and checked before returning.

    crop_rows: info-bar rows [start, stop) to drop, "auto" (detected per image, `info_bar_rows`) or None.
    A mask of the image's full size loses the same rows; a mask already the size of the cropped image is
    taken as it is; any other size is refused, naming both."""
    data_dir = Path(data_dir)
    images_dir, masks_dir = data_dir / "images", data_dir / masks
    if not masks_dir.is_dir():
        raise DataError(f"real dataset {data_dir}: no {masks}/ folder (expected binary masks named like the images)")
    out = []
    for image_path, image_id in zip(list_images(images_dir, ids), ids):
        item = read_image_item(image_path, image_id, crop_rows)
        mask_path = real_mask_path(masks_dir, image_id, mask_suffix)
        raw = read_raw_mask(mask_path)
        # The files' own sizes are compared (the image's rows before the crop), so a mask of another size is
        # reported as such and not as a crop_rows range that does not fit it.
        if item.rows and raw.shape == item.image.shape:
            pass  # published without the info bar already
        else:
            _check_same_size(
                item.file_shape, raw.shape, image_path, mask_path, cropped=item.image.shape if item.rows else None
            )
            raw = drop_mask_rows(raw, item.rows, mask_path)
        out.append((item, mask_instances(raw, mask_path)))
    return out


def load_real(
    data_dir, ids, crop_rows="auto", mask_suffix: str | None = "auto", masks: str = "masks"
) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(id, image, instance labels) of real images: ``load_real_items`` as plain tuples."""
    return [
        (item.id, item.image, labels) for item, labels in load_real_items(data_dir, ids, crop_rows, mask_suffix, masks)
    ]


def load_real_pairs(
    data_dir, ids, contour_px: int, crop_rows="auto", mask_suffix: str | None = "auto", masks: str = "masks"
) -> list[Pair]:
    return [
        Pair(i, img, class_mask(lab, contour_px), lab)
        for i, img, lab in load_real(data_dir, ids, crop_rows, mask_suffix, masks)
    ]


GENERATED_MASK_VALUES = (BACKGROUND, PARTICLE, CONTOUR, IGNORE)  # what a generated dataset's masks may hold


def load_generated_pairs(data_dir, setting: str = "data") -> list[Pair]:
    """The items of a generated dataset (drgan.synthetic: those its manifest.json lists; a folder of hand-made
    images/ID.png + masks/ID.png pairs without manifest: paired by file name), sorted by id; masks are uint8
    classes 0/1/2 and IGNORE (255). Every pair is read and checked before returning."""
    pairs = []
    for item, image_path, mask_path in image_mask_pairs(data_dir, setting):
        image = read_grey(image_path)
        mask = read_raw_mask(mask_path)
        _check_same_size(image.shape, mask.shape, image_path, mask_path)
        bad = sorted(set(np.unique(mask).tolist()) - set(GENERATED_MASK_VALUES))
        if bad:
            raise DataError(
                f"mask {mask_path}: unexpected values {bad[:5]} (expected classes 0 background, 1 particle, "
                f"2 contour, or {IGNORE} ignore)"
            )
        labels_path = mask_path.parent.parent / "labels" / mask_path.name  # a generated set's exact instances
        labels = read_raw_mask(labels_path).astype(np.int32) if labels_path.is_file() else None
        if labels is not None and labels.shape != mask.shape:
            raise DataError(f"labels {labels_path}: size {labels.shape} differs from its mask's {mask.shape}")
        pairs.append(Pair(item, image, mask.astype(np.uint8), labels))
    return pairs


def split_pairs(pairs: list[Pair], val_fraction: float, seed: int) -> tuple[list[Pair], list[Pair]]:
    """A random (seeded) validation subset: at least one pair when val_fraction > 0 and there are >= 2 pairs."""
    if not 0.0 <= val_fraction < 1.0:
        raise ConfigError(f"val_fraction={val_fraction}: expected a value in [0, 1)")
    n_val = int(round(len(pairs) * val_fraction))
    if val_fraction > 0 and len(pairs) >= 2:
        n_val = max(n_val, 1)
    order = np.random.default_rng(seed).permutation(len(pairs))
    val = {int(i) for i in order[:n_val]}
    return [p for k, p in enumerate(pairs) if k not in val], [p for k, p in enumerate(pairs) if k in val]


CENTRE_WORKING_PX = 40.0  # working_px=auto for a segmenter with a centre map (`working_scale`)
WORKING_SAMPLE = 200  # pairs whose instances give the median diameter `working_scale` compares


def sample_diameters(pairs: list[Pair]) -> np.ndarray:
    """The instances' diameters (drgan.metrics.statistics.diameters_of) of the first ``WORKING_SAMPLE`` pairs that
    hold a particle (a generated set lists its particle-free background pairs first)."""
    from drgan.metrics.statistics import diameters_of

    holding = (labels for labels in (p.instances() for p in pairs) if labels.max() > 0)
    return diameters_of(list(itertools.islice(holding, WORKING_SAMPLE)))


MAX_ENLARGE = 4.0  # the most `working_scale` enlarges pairs by (inference's cost grows with its square)


def working_scale(
    pairs: list[Pair],
    working_px: float | None,
    crop: int,
    diameters: np.ndarray | None = None,
    min_px: float | None = None,
) -> tuple[float, float]:
    """(scale, median diameter px): the factor (<= 1) the pairs are shrunk by so that their median particle (over
    the instances of the first ``WORKING_SAMPLE`` pairs that hold particles, sized as drgan.metrics.statistics sizes
    them) spans ``working_px`` px, but never so far that the smallest pair gets narrower than one ``crop``; or the
    factor (> 1, at most ``MAX_ENLARGE``) they are enlarged by so that it spans ``min_px`` px where it is smaller; 1
    when neither applies or no pair holds a particle. ``diameters``: the pairs' `sample_diameters` where the caller
    has them already.

    Why: a segmenter learns from ``crop``-px crops, and the instance-aware one's centre map (1 on each particle's
    core, drgan.segmenters.instances) can only be learnt where a crop shows the whole particle: with particles wider
    than the crops its centre map stays flat over every particle. Cellpose rescales to a
    working diameter (30 px) for the same reason."""
    if (working_px is None and min_px is None) or not pairs:
        return 1.0, math.nan
    diameters = sample_diameters(pairs) if diameters is None else diameters
    median = float(np.median(diameters)) if diameters.size else math.nan
    if min_px is not None and median < min_px:
        return float(min(min_px / median, MAX_ENLARGE)), median
    if working_px is None or not median > working_px:
        return 1.0, median
    floor = crop / min(min(p.image.shape) for p in pairs)
    return float(min(1.0, max(working_px / median, floor))), median


def _nearest(array: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``array`` resized to ``shape`` by taking each new pixel's centre's old pixel (labels and classes stay exact)."""
    rows = np.minimum(((np.arange(shape[0]) + 0.5) * array.shape[0] / shape[0]).astype(int), array.shape[0] - 1)
    cols = np.minimum(((np.arange(shape[1]) + 0.5) * array.shape[1] / shape[1]).astype(int), array.shape[1] - 1)
    return array[np.ix_(rows, cols)]


def rescale_pair(pair: Pair, scale: float, contour_px: int = 1) -> Pair:
    """``pair`` at ``scale``: the image resampled as inference resamples real images (drgan.data.images.resample:
    area-averaged when shrinking, bilinear when enlarging), the instances by nearest neighbour, the classes drawn anew
    from them (``contour_px`` wide, as drgan.scene.labels.class_mask draws them) with the pair's IGNORE pixels kept."""
    image = resample(pair.image, scale)
    labels = _nearest(pair.instances(), image.shape).astype(np.int32)
    mask = class_mask(labels, contour_px).astype(np.uint8)
    mask[_nearest(pair.mask, image.shape) == IGNORE] = IGNORE
    return Pair(pair.id, image.astype(np.float32), mask, labels)


def centre_map(pair: Pair) -> np.ndarray:
    """The centre-map target of a pair (drgan.segmenters.instances.centre_distance of its instances), float16."""
    return centre_distance(pair.instances()).astype(np.float16)


def crops_by_area(pairs: list[Pair], crop: float) -> list[int]:
    """Crops per pair and epoch in proportion to each image's area: round(area / crop^2), at least 1, so that an epoch
    covers the images' area about once whatever their number (20 large tiles are not 20 samples). Pairs shrunk to a
    working scale s pass crop x s: they keep the crops (the training steps) of their original size."""
    return [max(1, round(p.image.size / float(crop * crop))) for p in pairs]


TEXTURE_PX = (0.7, 3.0)  # correlation lengths (Gaussian stddev, px) of the texture augmentation: grain to cracks


def surface_texture(shape: tuple[int, int], amplitude: float, rng: np.random.Generator) -> np.ndarray:
    """A random texture of ``shape``: white noise low-passed by a Gaussian of stddev drawn from TEXTURE_PX, scaled to
    a std drawn from [0, amplitude] (grey units)."""
    from scipy.ndimage import gaussian_filter

    field = gaussian_filter(rng.standard_normal(shape), rng.uniform(*TEXTURE_PX), mode="wrap")
    return (rng.uniform(0.0, amplitude) / max(float(field.std()), 1e-12)) * field


def with_texture(image: np.ndarray, amplitude: float, rng: np.random.Generator) -> np.ndarray:
    """``image`` (grey, [0, 1]) with a `surface_texture` of ``amplitude`` added, clipped to [0, 1]: the training crops'
    texture augmentation."""
    return np.clip(image + surface_texture(image.shape, amplitude, rng), 0.0, 1.0)


CONTACT_SHADE_PX = 0.7  # Gaussian stddev (px) of the contact shading's profile across a contact line


def contact_ridge(labels: np.ndarray) -> np.ndarray:
    """bool (H, W): the pixels with two different instances of ``labels`` within 1 px (3 x 3 window): where two
    particles touch (their boundary pixels on both sides; a real annotation's 1 px separating line)."""
    from drgan.data.necks import contact_pairs

    return contact_pairs(labels)[0]


def shade_contacts(image: np.ndarray, labels: np.ndarray, mask: np.ndarray, depth: float) -> np.ndarray:
    """``image`` with the grey where particles touch (`contact_ridge`) pulled towards the crop's background grey
    (the median of its background-class pixels) by ``depth`` in [0, 1] at the ridge, falling off as a Gaussian of
    CONTACT_SHADE_PX across it: the dip a real contact shows (experiments/statistics/merges.md, "What a contact looks
    like"). Unchanged without a ridge, a depth of 0 or fewer than 16 background pixels."""
    from scipy.ndimage import gaussian_filter

    ridge = contact_ridge(labels)
    background = mask == 0
    if depth <= 0 or not ridge.any() or background.sum() < 16:
        return image
    # a Gaussian-blurred 1 px line peaks at 1 / (sqrt(2 pi) sigma): scaled so that a contact line reaches 1
    weight = np.minimum(
        1.0, gaussian_filter(ridge.astype(np.float32), CONTACT_SHADE_PX) * np.sqrt(2 * np.pi) * CONTACT_SHADE_PX
    )
    return image + (depth * weight) * (float(np.median(image[background])) - image)


class CropDataset(Dataset):
    """Random crops of the pairs, `samples_per_pair` per pair and epoch (one number for all, or one per pair, e.g.
    `crops_by_area`).

    augment: a random dihedral transform (8 flips/rotations) and a small brightness/contrast jitter,
    x -> clip((x - mean) * c + mean + b) with c in [1 - contrast, 1 + contrast], b in [-brightness, brightness];
    with ``texture`` > 0 also a surface texture the renderer cannot show (cracks, beads, grain of a real particle):
    Gaussian noise low-passed at a correlation length drawn from TEXTURE_PX, of a std drawn from [0, texture],
    added to the whole crop, so that the network does not take every textured region for background; with
    ``contact_shade`` > 0 the contacts between touching particles (the pairs' instances) darken (brighten) towards
    the background by a depth drawn from [0, contact_shade] (`shade_contacts`), before the jitter.
    Without augment (validation) every sample is the pair's centre crop, unchanged, so val scores are repeatable.
    Images smaller than the crop are reflect-padded, their masks likewise. Masks are only cut, padded by copying,
    rotated and flipped, never interpolated: an IGNORE (255) pixel stays 255 and no other class is made from it.
    normalize: per-image input normalisation (NORMALIZATIONS), with the statistics of the *whole* image (as at
    inference, `predict_probs`), applied to each crop after the jitter.
    """

    def __init__(
        self,
        pairs: list[Pair],
        crop: int,
        augment: bool,
        samples_per_pair: int | list[int] = 1,
        brightness: float = 0.05,
        contrast: float = 0.1,
        seed: int = 0,
        normalize: str = "none",
        centres: bool = False,
        texture: float = 0.0,
        contact_shade: float = 0.0,
        rays: int = 0,
        ray_px: int = 64,
    ):
        if not pairs:
            raise DataError("segmentation dataset: no image/mask pairs")
        self.pairs, self.crop, self.augment = pairs, int(crop), augment
        counts = [int(samples_per_pair)] * len(pairs) if isinstance(samples_per_pair, int) else list(samples_per_pair)
        if len(counts) != len(pairs) or min(counts) < 1:
            raise DataError(
                f"samples_per_pair: expected one count >= 1 per pair ({len(pairs)}), got {samples_per_pair}"
            )
        self.owner = np.repeat(np.arange(len(pairs)), counts)  # sample index -> pair index
        self.brightness, self.contrast, self.seed, self.texture = brightness, contrast, seed, float(texture)
        mode = check_normalize(normalize, "loader normalize")
        self.stats = [normalization(p.image, mode) for p in pairs]  # (shift, scale) of each whole image
        # centre-map targets of whole images (their particles' extents), cut like the masks (an instance-aware segmenter)
        self.centres = [centre_map(p) for p in pairs] if centres else None
        self.contact_shade = float(contact_shade)
        # ray distances of each crop's instances (the star-convex segmenter, drgan.segmenters.star), with the centres
        self.rays, self.ray_px = (int(rays), int(ray_px)) if centres else (0, int(ray_px))

    def __len__(self) -> int:
        return len(self.owner)

    def __getitem__(self, index: int):
        owner = int(self.owner[index])
        pair, (shift, scale) = self.pairs[owner], self.stats[owner]
        # Training crops and jitter draw from torch's generator (seeded by the run's seed, per worker by the
        # DataLoader): the same command gives the same segmenter; validation crops are fixed by the index.
        rng = (
            np.random.default_rng(int(torch.randint(0, 2**62, ())))
            if self.augment
            else np.random.default_rng((self.seed, index))
        )
        image, mask = pair.image, pair.mask
        maps = [image, mask] + ([self.centres[owner]] if self.centres is not None else [])
        with_instances = (self.augment and self.contact_shade > 0) or self.rays > 0
        if with_instances:
            maps.append(pair.instances())  # cut like the masks; the shading and the rays read it
        c = self.crop
        h, w = image.shape
        if h < c or w < c:
            pad = ((0, max(c - h, 0)), (0, max(c - w, 0)))
            maps = [np.pad(m, pad, mode="reflect") for m in maps]
            h, w = maps[0].shape
        if self.augment:
            y, x = int(rng.integers(0, h - c + 1)), int(rng.integers(0, w - c + 1))
        else:
            y, x = (h - c) // 2, (w - c) // 2
        maps = [m[y : y + c, x : x + c] for m in maps]
        if self.augment:
            k = int(rng.integers(0, 8))
            maps = [np.rot90(m, k % 4) for m in maps]
            if k >= 4:
                maps = [m[:, ::-1] for m in maps]
        image, mask = maps[0], maps[1]
        if self.augment:
            if self.contact_shade > 0:
                image = shade_contacts(image, maps[-1], mask, rng.uniform(0.0, self.contact_shade))
            mean = float(image.mean())
            c = rng.uniform(1 - self.contrast, 1 + self.contrast)
            image = np.clip((image - mean) * c + mean + rng.uniform(-self.brightness, self.brightness), 0.0, 1.0)
            if self.texture > 0:
                image = with_texture(image, self.texture, rng)
        image = (image - shift) / scale
        sample = (
            torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32))[None],
            torch.from_numpy(np.ascontiguousarray(mask).astype(np.int64)),
        )
        if self.centres is None:
            return sample
        sample = (*sample, torch.from_numpy(np.ascontiguousarray(maps[2], dtype=np.float32)))
        if not self.rays:
            return sample
        from drgan.segmenters.polygons import ray_distances

        return (*sample, torch.from_numpy(ray_distances(np.ascontiguousarray(maps[-1]), self.rays, self.ray_px)))
