"""The real background items of a dataset, from a PatchSet (a training run's patches/), so that a segmenter also
learns what the real substrate looks like:

- **backgrounds** ``bg_0000`` ..: windows free of particles, scale bars and text (the PatchSet's background
  patches), with all-zero masks;
- **partial backgrounds** ``pbg_0000`` ..: when the PatchSet holds fewer such windows than ``n_background`` (dense
  images: on TEM agglomerates there may be none), real windows *with* particles fill up the rest: the PatchSet's
  training patches, their particles found again with the classical segmentation the patches were mined with
  (drgan.data.classical, the PatchSet's own resolved settings and polarity). Their masks are 0 (background) except
  on the particles, grown by a margin, and on scale bars and text, which are ``IGNORE`` (255): a segmenter's loss
  leaves those pixels out, so the window teaches background without claiming anything about its particles.

The margin (``partial_margin_px``; by default the larger of 3 px and twice the segmentation's smoothing sigma, in
the patch's px): the threshold puts a particle's outline at about half its edge contrast, so the outer half of its
blurred edge, the halo or bright rim of SEM edges and TEM's Fresnel fringes lie outside the foreground while
still not being substrate; the synthetic masks call such pixels contour or particle. Labelled background, they
would teach the segmenter to cut particles short. 3 px covers a blurred edge and the contour class (1-2 px); twice
the smoothing sigma covers how far the smoothing moves the outline (it grows with the particles: 0.058 d).

A window whose ignored fraction exceeds ``partial_max_ignored`` (0.6) is skipped (little background left to
teach; logged). The windows with the least ignored fraction come first. The choice depends only on the PatchSet
and the settings, so the k-th partial background is the same window in every run (resumable); how many windows
were skipped is recorded in partial_backgrounds.json, which also tells a later manifest that the PatchSet has no
more (``partial_exhausted``).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drgan.core import io
from drgan.core.errors import ConfigError, DataError
from drgan.synthetic.folder import BACKGROUND, IGNORE, PARTIAL_BACKGROUND, PARTIAL_RECORD, DatasetFolder, bg_id, pbg_id

log = logging.getLogger(__name__)

PARTIAL_MARGIN_MIN_PX = 3  # the least margin around a particle that a partial background ignores (patch px)
PARTIAL_MARGIN_SIGMAS = 2.0  # ... or this many of the segmentation's smoothing sigma, whichever is larger
PARTIAL_MAX_IGNORED = 0.6  # partial backgrounds ignoring more of their pixels are skipped (the config's default)


def _resized(patch: np.ndarray, resolution: int) -> np.ndarray:
    """A patch at the render's resolution (bicubic, on floats), clipped to [0, 1]."""
    patch = np.asarray(patch, dtype=np.float32)
    if patch.shape != (resolution, resolution):
        from PIL import Image

        resized = Image.fromarray(patch, mode="F").resize((resolution, resolution), Image.BICUBIC)
        patch = np.asarray(resized, dtype=np.float32)
    return np.clip(patch, 0.0, 1.0)


def _resized_ignore(ignore: np.ndarray, resolution: int) -> np.ndarray:
    """A bool ignore mask at the render's resolution: a pixel is ignored when any ignored pixel of the patch
    contributes to it (bilinear weights on the 0/1 mask above 0), so resizing never turns particle into background."""
    if ignore.shape == (resolution, resolution):
        return ignore
    from PIL import Image

    resized = Image.fromarray(ignore.astype(np.float32), mode="F").resize((resolution, resolution), Image.BILINEAR)
    return np.asarray(resized) > 1e-6


def load_backgrounds(path: Path | None, n: int, resolution: int) -> tuple[list[np.ndarray], list[dict]]:
    """Up to n background patches of a PatchSet, resized (bicubic, on floats) when their size is not the render's;
    with each its source record (patch set, image id, position) for the item's meta."""
    if n == 0:
        return [], []
    if path is None:
        raise ConfigError(
            f"n_background={n}: no background patches found; give backgrounds=PATCHSET_FOLDER "
            "(a run's patches/) or n_background=0"
        )
    from drgan.data.patches import PatchSet

    return _backgrounds(PatchSet.load(path), path, n, resolution, partial=False)


def _backgrounds(patches, path: Path, n: int, resolution: int, partial: bool) -> tuple[list[np.ndarray], list[dict]]:
    if len(patches.background) < n:
        log.warning(
            "backgrounds=%s holds %d background patches, fewer than n_background=%d: using all%s",
            path,
            len(patches.background),
            n,
            ", and filling up with partial backgrounds (windows with particles, which their masks ignore)"
            if partial
            else " (partial_background=true would fill up with windows with particles, which their masks ignore)",
        )
    images, sources = [], []
    for k in range(min(n, len(patches.background))):
        images.append(_resized(patches.background[k], resolution))
        sources.append({
            "patchset": str(path),
            "image_id": patches.background_ids[k],
            "position": [int(v) for v in patches.background_positions[k]],
            "foreground_fraction": 0.0,  # a mined background patch holds no particle pixel
            "patch_size": int(patches.background[k].shape[-1]),
        })  # fmt: skip
    return images, sources


# --- partial backgrounds -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PartialSettings:
    """How partial backgrounds are made: whether at all, the largest ignored fraction kept, the margin (patch px;
    None: `default_margin`)."""

    enabled: bool = True
    max_ignored: float = PARTIAL_MAX_IGNORED
    margin_px: int | None = None


def default_margin(sigma: float | None) -> int:
    """The margin (px) a partial background ignores around each particle: PARTIAL_MARGIN_MIN_PX, or
    PARTIAL_MARGIN_SIGMAS x the segmentation's smoothing ``sigma`` when larger (module docstring: why)."""
    return max(PARTIAL_MARGIN_MIN_PX, math.ceil(PARTIAL_MARGIN_SIGMAS * float(sigma or 0.0)))


def patchset_segmentation(patches, fallback_polarity: str):
    """(SegmentParams at the patches' px, polarity) the PatchSet was mined with (its params "segment", "polarity");
    a PatchSet resampled from windows of W px to S px gets its lengths scaled by S / W. Unresolved or missing
    settings: each patch's particle scale is estimated on the patch."""
    from drgan.data.classical import SegmentParams

    params = SegmentParams.from_config(patches.params.get("segment") or {})
    window, size = patches.params.get("window"), patches.patch_size
    if window and size and int(window) != int(size):
        params = params.scaled(size / float(window))
    return params, str(patches.params.get("polarity") or fallback_polarity)


def ignore_mask(patch: np.ndarray, params, polarity: str, margin_px: int) -> tuple[np.ndarray, bool]:
    """(bool ignore mask, whether any particle was found) of one real patch: its particle foreground (the classical
    segmentation, drgan.data.classical) grown by ``margin_px``, and its scale bars and text (also grown)."""
    from scipy import ndimage

    from drgan.data.classical import particle_foreground, prepare
    from drgan.scene.labels import disk

    foreground = particle_foreground(patch, params, polarity)
    occupied = foreground | prepare(patch, polarity, params.annotations).annotations
    if margin_px > 0 and occupied.any():
        occupied = ndimage.binary_dilation(occupied, structure=disk(margin_px))
    return occupied, bool(foreground.any())


@dataclass
class PartialCandidates:
    """The training patches of a PatchSet usable as partial backgrounds, in the order they fill the slots."""

    order: list[int]  # PatchSet train indices of the usable windows, least ignored first
    ignore: dict[int, np.ndarray]  # train index -> bool ignore mask at the render's resolution
    fractions: dict[int, float]  # train index -> ignored fraction at the render's resolution
    skipped: dict[str, list[int]]  # reason -> train indices: "ignored_fraction", "no_particle_found"
    margin_px: int
    polarity: str
    segment: dict

    def record(self, path, settings: PartialSettings, patches) -> dict:
        return {
            "patchset": str(path),
            "candidates": len(patches.train),
            "usable": len(self.order),
            "skipped": {reason: len(items) for reason, items in self.skipped.items()},
            "max_ignored": settings.max_ignored,
            "margin_px": self.margin_px,
            "polarity": self.polarity,
            "segment": self.segment,
        }


def partial_candidates(patches, resolution: int, settings: PartialSettings, fallback_polarity: str):
    """Every training patch of ``patches`` judged as a partial background: its ignore mask and fraction; those
    above ``settings.max_ignored``, or in which no particle is found again (their whole window would be called
    background), are skipped and logged."""
    params, polarity = patchset_segmentation(patches, fallback_polarity)
    margin = int(settings.margin_px) if settings.margin_px is not None else default_margin(params.sigma)
    ignore, fractions, skipped = {}, {}, {"ignored_fraction": [], "no_particle_found": []}
    for k, patch in enumerate(patches.train):
        mask, found = ignore_mask(np.asarray(patch, np.float32), params, polarity, margin)
        if not found:
            skipped["no_particle_found"].append(k)
            continue
        mask = _resized_ignore(mask, resolution)
        fractions[k] = float(mask.mean())
        if fractions[k] > settings.max_ignored:
            skipped["ignored_fraction"].append(k)
            continue
        ignore[k] = mask
    order = sorted(ignore, key=lambda k: (fractions[k], k))

    def examples(items: list[int]) -> str:
        shown = [f"{patches.train_ids[k]} at {tuple(int(v) for v in patches.train_positions[k])}" for k in items[:3]]
        return ", ".join(shown) + (" ..." if len(items) > 3 else "")

    too_full = skipped["ignored_fraction"]
    if too_full:
        log.info(
            "partial backgrounds: skipped %d of %d windows with particles whose ignored fraction exceeds "
            "partial_max_ignored=%s (particles and a %d px margin cover most of them; e.g. %s)",
            len(too_full), len(patches.train), settings.max_ignored, margin, examples(too_full),
        )  # fmt: skip
    if skipped["no_particle_found"]:
        log.info(
            "partial backgrounds: skipped %d windows in which the segmentation found no particle again (%s)",
            len(skipped["no_particle_found"]), examples(skipped["no_particle_found"]),
        )  # fmt: skip
    return PartialCandidates(order, ignore, fractions, skipped, margin, polarity, params.as_dict())


def write_backgrounds(
    folder: DatasetFolder,
    path: str | None,
    n: int,
    resolution: int,
    partial: PartialSettings | None = None,
    polarity: str = "bright",
) -> dict:
    """Write the background items bg_0000 .. of ``n`` that are not done yet, from the PatchSet at ``path``; when it
    holds fewer than n and ``partial`` is enabled, the partial backgrounds pbg_0000 .. that fill up to n. Returns
    {"background": background items the PatchSet offers (up to n), "partial": partial backgrounds there are}
    ({} when all n backgrounds were done already). ``polarity``: the particles' side when the PatchSet does not
    record it."""
    partial = partial or PartialSettings(enabled=False)
    todo = [k for k in range(n) if not folder.done(bg_id(k))]
    if not todo:  # all n backgrounds done: the PatchSet has enough, no partial background is wanted
        return {}
    if path is None:
        load_backgrounds(None, n, resolution)  # raises, naming the settings
    from drgan.data.patches import PatchSet

    patches = PatchSet.load(path)
    available = min(n, len(patches.background))
    if todo:
        images, sources = _backgrounds(patches, Path(path), n, resolution, partial.enabled)
        for k in todo:
            if k >= len(images):
                break
            zeros = np.zeros(images[k].shape, np.uint8)
            folder.write(bg_id(k), images[k], zeros, zeros, {"kind": BACKGROUND, "index": k, "source": sources[k]})
    counts = {"background": available}
    if not partial.enabled:
        return counts
    wanted = n - available
    partial_todo = [j for j in range(wanted) if not folder.done(pbg_id(j))]
    if not partial_todo:
        counts["partial"] = wanted
        return counts
    candidates = partial_candidates(patches, resolution, partial, polarity)
    for j in partial_todo:
        if j >= len(candidates.order):
            break
        k = candidates.order[j]
        mask = np.where(candidates.ignore[k], IGNORE, 0).astype(np.uint8)
        meta = {
            "kind": PARTIAL_BACKGROUND,
            "index": j,
            "ignored_fraction": candidates.fractions[k],
            "margin_px": candidates.margin_px,
            "source": {
                "patchset": str(path),
                "train_index": k,
                "image_id": patches.train_ids[k],
                "position": [int(v) for v in patches.train_positions[k]],
                "particles": int(patches.train_counts[k]),
                "patch_size": int(patches.train[k].shape[-1]),
                "polarity": candidates.polarity,
            },
        }
        labels = np.zeros(mask.shape, np.uint8)  # its particles are not annotated: the mask ignores them
        folder.write(pbg_id(j), _resized(patches.train[k], resolution), mask, labels, meta)
    usable = len(candidates.order)
    if usable < wanted:
        log.warning(
            "partial backgrounds: only %d of %d windows with particles are usable (ignored fraction <= "
            "partial_max_ignored=%s): the dataset gets %d background + %d partial background items, not "
            "n_background=%d",
            usable, len(patches.train), partial.max_ignored, available, usable, n,
        )  # fmt: skip
    io.write_json(folder.root / PARTIAL_RECORD, candidates.record(path, partial, patches))
    counts["partial"] = min(usable, wanted)
    return counts


def backgrounds_exhausted(path: str | None, done: int) -> bool:
    """True when the PatchSet at ``path`` holds fewer background patches than asked for and all of them are done."""
    if not path:
        return False
    from drgan.data.patches import PatchSet

    try:
        return done >= len(PatchSet.load(path).background)
    except DataError:
        return False


def partial_exhausted(folder: DatasetFolder, done: int) -> bool:
    """True when partial_backgrounds.json says the PatchSet has no more usable windows than the ``done`` ones."""
    try:
        record = json.loads((folder.root / PARTIAL_RECORD).read_text())
    except (OSError, ValueError):
        return False
    return isinstance(record, dict) and isinstance(record.get("usable"), int) and done >= record["usable"]
