"""The real background items of a dataset: patches without particles from a PatchSet (a training run's patches/),
added with all-zero masks so that a segmenter also sees empty fields."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from drgan.dataset.layout import BACKGROUND, DatasetFolder, bg_id
from drgan.errors import ConfigError, DataError

log = logging.getLogger(__name__)


def load_backgrounds(path: Path | None, n: int, resolution: int) -> tuple[list[np.ndarray], list[dict]]:
    """Up to n background patches of a PatchSet, resized (bicubic, on floats) when their size is not the render's;
    with each its source record (patch set, image id, position) for the item's meta."""
    if n == 0:
        return [], []
    from drgan.data.patches import PatchSet

    if path is None:
        raise ConfigError(
            f"n_background={n}: no background patches found; give backgrounds=PATCHSET_FOLDER "
            "(a run's patches/) or n_background=0"
        )
    patches = PatchSet.load(path)
    if len(patches.background) < n:
        log.warning(
            "backgrounds=%s holds %d background patches, fewer than n_background=%d: using all",
            path,
            len(patches.background),
            n,
        )
    images, sources = [], []
    for k in range(min(n, len(patches.background))):
        patch = np.asarray(patches.background[k], dtype=np.float32)
        if patch.shape != (resolution, resolution):
            from PIL import Image

            resized = Image.fromarray(patch, mode="F").resize((resolution, resolution), Image.BICUBIC)
            patch = np.asarray(resized, dtype=np.float32)
        images.append(np.clip(patch, 0.0, 1.0))
        sources.append({
            "patchset": str(path),
            "image_id": patches.background_ids[k],
            "position": [int(v) for v in patches.background_positions[k]],
            "foreground_fraction": float(patches.background_fractions[k]),
            "patch_size": int(patches.background[k].shape[-1]),
        })  # fmt: skip
    return images, sources


def write_backgrounds(folder: DatasetFolder, path: str | None, n: int, resolution: int) -> int:
    """Write the background items bg_0000 .. of ``n`` that are not done yet, from the PatchSet at ``path``;
    returns how many patches the PatchSet offers (0 when nothing was left to do)."""
    todo = [k for k in range(n) if not folder.done(bg_id(k))]
    if not todo:
        return 0
    images, sources = load_backgrounds(Path(path) if path else None, n, resolution)
    for k in todo:
        if k >= len(images):
            break
        zeros = np.zeros(images[k].shape, np.uint8)
        folder.write(bg_id(k), images[k], zeros, zeros, {"kind": BACKGROUND, "index": k, "source": sources[k]})
    return len(images)


def backgrounds_exhausted(path: str | None, done: int) -> bool:
    """True when the PatchSet at ``path`` holds fewer background patches than asked for and all of them are done."""
    if not path:
        return False
    from drgan.data.patches import PatchSet

    try:
        return done >= len(PatchSet.load(path).background)
    except DataError:
        return False
