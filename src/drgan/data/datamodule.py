"""Real training patches for the discriminator, as a LightningDataModule.

The patches are mined once (drgan.data.patches.mine_patches) from the training images of a folder and
cached in the run folder (``patches/``: patches.npz, summary.json, contact_sheet.png, source.json); a
resumed run reads the cache instead of mining again, as long as the data settings are unchanged.
Test ids of the split never reach training: only the split's train ids are read.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from lightning.pytorch import LightningDataModule
from torch.utils.data import DataLoader, Dataset, RandomSampler

from drgan.core.errors import ConfigError, DataError
from drgan.core.io import write_with
from drgan.data.classical import ScaleEstimate, SegmentParams, resolve_params
from drgan.data.images import default_split, list_images, read_grey, read_split
from drgan.data.patches import (
    STRIDE,
    PatchSet,
    check_image_sizes,
    contact_sheet,
    dihedral_augment,
    mine_patches,
    resample_patches,
    scale_sample,
)
from drgan.data.polarity import check_polarity, detect_polarity
from drgan.scene.config import Material

log = logging.getLogger(__name__)

_SOURCE_FILE = "source.json"


class AugmentedPatches(Dataset):
    """(N, H, W) float32 patches -> (1, H, W) tensors, each in a random one of the 8 dihedral symmetries."""

    def __init__(self, patches: np.ndarray, augment: bool = True):
        self.patches = patches
        self.augment = augment

    def __len__(self) -> int:
        return len(self.patches)

    def __getitem__(self, index: int) -> torch.Tensor:
        patch = self.patches[index]
        if self.augment:
            patch = dihedral_augment(patch, int(torch.randint(8, ()).item()))
        return torch.from_numpy(np.ascontiguousarray(patch, dtype=np.float32)).unsqueeze(0)


class RealPatchDataModule(LightningDataModule):
    """Training patches mined from the train images of ``dir``.

    dir: folder of real images (TIFF/PNG/JPEG). split: a split.json ({"train": [...], "test": [...]});
    "auto" uses ``dir/split.json`` or ``dir/../split.json`` when present; null trains on every image of
    the folder. crop_rows: [start, stop) rows to drop (an info bar), "auto" (the bar found in each image) or null. patch_size must equal the
    renderer's resolution (``resolution``): the discriminator compares real and rendered patches pixel
    by pixel. polarity: "bright" or "dark" particles, or "auto" to detect it from the training images
    (drgan.data.polarity); the detected value is in ``polarity`` after setup and in the patches' summary.
    check_material: whether `check_fits` refuses a material made for other images (polarity, particle size).
    cache_dir: where the mined patches are written (the run folder's ``patches/``).
    """

    def __init__(
        self,
        dir: str,
        split: str | None = "auto",
        crop_rows: Sequence[int] | None = None,
        patch_size: int = 256,
        stride: int = STRIDE,
        min_particles: int = 3,
        n_background: int = 200,
        background_stride: int | None = None,
        segment: Mapping | None = None,
        batch_size: int = 1,
        num_workers: int = 0,
        augment: bool = True,
        steps_per_epoch: int | None = None,
        cache_dir: str | None = None,
        resolution: int | None = None,
        polarity: str = "auto",
        check_material: bool = True,
        view_width: int | None = None,
    ):
        super().__init__()
        if dir is None or str(dir) in ("", "None", "null"):
            raise ConfigError(
                "data.dir is not set: point it at the folder of your real images (python -m drgan.train data.dir=/path/to/images); "
                "python -m drgan.profile data.dir=/path/to/images name=NAME proposes a material for them"
            )
        self.polarity_setting = check_polarity(polarity, allow_auto=True)
        self.polarity: str | None = None if polarity == "auto" else polarity
        self.polarity_estimate: dict | None = None
        self.check_material = bool(check_material)
        self.dir = Path(dir)
        self.split = split
        if isinstance(crop_rows, str) and crop_rows != "auto":
            raise ConfigError(f"data.crop_rows={crop_rows!r}: expected [start, stop), auto or null")
        self.crop_rows = (
            crop_rows if crop_rows is None or isinstance(crop_rows, str) else tuple(int(v) for v in crop_rows)
        )
        self.patch_size = int(patch_size)
        # Real px a patch covers (the camera's view, material.view_width); windows of this size are mined and then
        # resampled to patch_size (the render's pixels) when the two differ, so real and rendered patches show the
        # same scale at any render resolution. None: patch_size.
        self.window = self.patch_size if view_width is None else int(view_width)
        if self.window < self.patch_size:
            raise ConfigError(
                f"material.view_width={self.window} px is less than data.patch_size={self.patch_size} (the render's "
                "pixels): the real patches would be upsampled; render at most view_width pixels per side"
            )
        self.stride = int(stride)
        self.min_particles = int(min_particles)
        self.n_background = int(n_background)
        self.background_stride = None if background_stride is None else int(background_stride)
        # The settings as given (lengths left null follow from the particle scale); after setup, `segment` holds
        # the resolved ones mining used, which the FID brightness guards apply to real and synthetic patches alike.
        self.segment_setting = SegmentParams.from_config(segment)
        self.segment = self.segment_setting
        self.batch_size = int(batch_size)
        self.num_workers = int(num_workers)
        self.augment = bool(augment)
        self.cache_dir = Path(cache_dir) if cache_dir else None
        if self.batch_size < 1:
            raise ConfigError(f"data.batch_size={batch_size}: expected >= 1")
        if steps_per_epoch is not None and (not isinstance(steps_per_epoch, int) or isinstance(steps_per_epoch, bool)
                                            or steps_per_epoch < 1):  # fmt: skip
            raise ConfigError(f"data.steps_per_epoch={steps_per_epoch!r}: expected an integer >= 1 or null")
        self.steps_per_epoch = None if steps_per_epoch is None else int(steps_per_epoch)
        if resolution is not None and int(resolution) != self.patch_size:
            raise ConfigError(
                f"data.patch_size={self.patch_size} but renderer.resolution={resolution}: the discriminator compares "
                "real and rendered patches pixel by pixel, so they must be equal. Set data.patch_size to the render "
                "resolution (and material.view_width to the real px the patch covers, usually the same number)."
            )
        self.patches: PatchSet | None = None
        self.train_ids: list[str] = []
        self.test_ids: list[str] = []

    # --- which images -------------------------------------------------------------------------------------

    def _split_path(self) -> Path | None:
        if self.split is None or self.split in ("", "none", "null"):
            return None
        if self.split == "auto":
            return default_split(self.dir)
        return Path(self.split)

    def resolve_ids(self) -> tuple[list[Path], list[str], list[str]]:
        """(train image paths, train ids, test ids); raises DataError on a missing image or a leaked test id."""
        if not self.dir.is_dir():
            raise DataError(
                f"data.dir={self.dir}: no such folder (expected a folder of real images: data.dir=/path/to/your/images)"
            )
        split_path = self._split_path()
        if split_path is None:
            paths = list_images(self.dir)
            log.warning(
                "data: no split file; training on all %d images of %s (no test ids held out)", len(paths), self.dir
            )
            return paths, [p.stem for p in paths], []
        split = read_split(split_path)
        train, test = split["train"], split["test"]
        leaked = sorted(set(train) & set(test))
        if leaked:  # read_split refuses overlaps already; this guards the invariant itself
            raise DataError(
                f"split {split_path}: test id(s) {leaked[:5]} are in the train list; test images must never be trained on"
            )
        if not train:
            raise DataError(f"split {split_path}: empty 'train' list")
        list_images(self.dir, test)  # a test id without an image means the split does not belong to this folder
        return list_images(self.dir, train), list(train), list(test)

    # --- mining and caching -------------------------------------------------------------------------------

    def _source(self, ids: list[str]) -> dict:
        return {
            "dir": str(self.dir.resolve()),
            "train_ids": ids,
            "crop_rows": list(self.crop_rows) if isinstance(self.crop_rows, tuple) else self.crop_rows,
            "patch_size": self.patch_size,
            **({"window": self.window} if self.window != self.patch_size else {}),
            "stride": self.stride,
            "min_particles": self.min_particles,
            "n_background": self.n_background,
            "background_stride": self.background_stride,
            "segment": self.segment_setting.as_dict(),
            "polarity": self.polarity_setting,
        }

    def _load_cache(self, source: dict) -> PatchSet | None:
        if self.cache_dir is None or not (self.cache_dir / _SOURCE_FILE).is_file():
            return None
        try:
            cached = json.loads((self.cache_dir / _SOURCE_FILE).read_text())
        except json.JSONDecodeError:
            return None
        if cached != source:
            log.info("data: cached patches in %s were mined with other settings; mining again", self.cache_dir)
            return None
        log.info("data: reusing mined patches from %s", self.cache_dir)
        return PatchSet.load(self.cache_dir)

    def prepare_data(self) -> None:
        self.setup("fit")

    def setup(self, stage: str | None = None) -> None:
        if self.patches is not None:
            return
        paths, ids, self.test_ids = self.resolve_ids()
        self.train_ids = ids
        source = self._source(ids)
        patches = self._load_cache(source)
        if patches is None:
            images = [read_grey(p, self.crop_rows) for p in paths]
            check_image_sizes(images, ids, self.window)
            self.resolve_polarity(images)
            patches = mine_patches(
                images,
                ids,
                size=self.window,
                stride=self.stride,
                min_particles=self.min_particles,
                n_background=self.n_background,
                background_stride=self.background_stride,
                segment=self.segment,
                polarity=self.polarity,
                progress=False,
            )
            patches.params["polarity_estimate"] = self.polarity_estimate
            if self.window != self.patch_size:
                patches = resample_patches(patches, self.patch_size)
            if self.cache_dir is not None:
                patches.save(self.cache_dir)
                contact_sheet(patches, self.cache_dir / "contact_sheet.png")
                write_with(self.cache_dir / _SOURCE_FILE, lambda f: f.write(json.dumps(source, indent=1).encode()))
        leaked = sorted(set(patches.train_ids) & set(self.test_ids))
        if leaked:
            raise DataError(f"data: patches of test image(s) {leaked[:5]} reached the training set")
        self._check_enough(patches, len(ids))
        self.polarity = patches.params["polarity"]
        self.polarity_estimate = patches.params["polarity_estimate"]
        self.segment = SegmentParams.from_config(patches.params["segment"])
        self.patches = patches
        log.info("data: %s", json.dumps(patches.summary()))

    def search_segment(self) -> tuple[SegmentParams, ScaleEstimate | None, list[str]]:
        """What mining's scale search finds on the train images (their crop, their polarity) with data.segment's
        scale and neck depth unset: (the settings resolved, the search's `ScaleEstimate`, the ids searched). An
        experiment pins these to skip the search (`experiments/profile/pin_scale.py`)."""
        from dataclasses import replace

        paths, ids, _ = self.resolve_ids()
        images = [read_grey(p, self.crop_rows) for p in paths]
        polarity = self.resolve_polarity(images)
        unset = replace(SegmentParams.from_config(self.segment), scale=None, neck_depth=None)
        params, estimate = resolve_params(scale_sample(images), unset, polarity)
        return params, estimate, scale_sample(ids)

    def resolve_polarity(self, images: Sequence[np.ndarray]) -> str:
        """The particles' polarity: the setting, or detected from ``images`` when it is "auto" (logged)."""
        if self.polarity is None:
            estimate = detect_polarity(images)
            self.polarity, self.polarity_estimate = estimate.polarity, estimate.as_dict()
            log.info(
                "data: particles are %s (data.polarity=auto: %s)", self.polarity, json.dumps(self.polarity_estimate)
            )
        return self.polarity

    def check_fits(self, material: Material) -> dict | None:
        """Refuse a material whose polarity or particle size contradicts these images (`drgan.data.consistency`),
        looking at a few training images (seconds, before mining); None when data.check_material is false."""
        from drgan.data.consistency import N_IMAGES, check_material_fits_data, data_particle_size

        paths, ids, _ = self.resolve_ids()
        images = [read_grey(p, self.crop_rows) for p in paths[:N_IMAGES]]
        check_image_sizes(images, ids, self.window)
        polarity = self.resolve_polarity(images)
        if not self.check_material:
            return None
        return check_material_fits_data(
            material, polarity, data_particle_size(images, polarity, self.segment_setting), self.dir
        )

    def min_train_patches(self) -> int:
        """Fewest training patches a run can use: 2 for the real FID statistics (a covariance needs two
        images), and one full batch (data.batch_size) for a training step."""
        return max(2, self.batch_size)

    def _check_enough(self, patches: PatchSet, n_images: int) -> None:
        """Refuse a patch set too small to train on, right after mining: otherwise the run would find out only at
        its first FID, after a whole epoch of rendering."""
        found, needed = len(patches.train), self.min_train_patches()
        if found >= needed:
            return
        what = f"no {self.patch_size} px patch" if found == 0 else f"only {found} {self.patch_size} px patch(es)"
        sheet = (
            f"; the mined patches are shown in {self.cache_dir / 'contact_sheet.png'}"
            if self.cache_dir and found
            else ""
        )
        raise DataError(
            f"data.dir {self.dir}: {what} with >= {self.min_particles} fully displayed particles in the {n_images} "
            f"training image(s); training needs at least {needed} (2 for the FID statistics, data.batch_size="
            f"{self.batch_size} for one batch){sheet}. Lower data.stride (now {self.stride}: more, overlapping windows) or "
            f"data.min_particles (now {self.min_particles}), use a smaller data.patch_size (with renderer.resolution "
            "and material.view_width), add more images, or check data.segment against your particle sizes"
        )

    # --- what the GAN sees --------------------------------------------------------------------------------

    @property
    def real_patches(self) -> np.ndarray:
        self.setup()
        return self.patches.train

    @property
    def background_patches(self) -> np.ndarray:
        self.setup()
        return self.patches.background

    @property
    def n_train(self) -> int:
        return len(self.real_patches)

    def train_dataloader(self) -> DataLoader:
        """Shuffled patches. With ``steps_per_epoch``, an epoch (one evaluation) is that many steps whatever the
        number of patches: fewer steps than patches take the first ones of a permutation (as Lightning's
        ``limit_train_batches`` would), more steps run through several permutations, each patch once per pass."""
        patches = AugmentedPatches(self.real_patches, self.augment)
        sampler = None
        if self.steps_per_epoch is not None:
            sampler = RandomSampler(patches, num_samples=self.steps_per_epoch * self.batch_size)
        return DataLoader(
            patches,
            batch_size=self.batch_size,
            shuffle=sampler is None,
            sampler=sampler,
            num_workers=self.num_workers,
            persistent_workers=self.num_workers > 0,
            drop_last=len(self.real_patches) >= self.batch_size,
        )
