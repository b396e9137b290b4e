"""manifest.json: what a dataset folder holds, written once it is complete and read by every consumer.

    {"config": the generation settings (shard: null), "material": {"name": ..., "clark_evans": ...},
     "counts": {...}, "throughput": {...},
     "entries": [{"id": "syn_000000", "kind": "synthetic", "index": 0, "files": {"image": ..., "mask": ...,
                  "label": ..., "meta": ...}}, ..., {"id": "bg_0000", "kind": "background", "files": {...}}, ...,
                 {"id": "pbg_0000", "kind": "partial_background", "files": {...}}]}

Synthetic entries come first, by index, then the backgrounds, then the partial backgrounds (real windows with
particles whose masks ignore them: drgan.synthetic.backgrounds); counts has each number, and "partial_backgrounds"
how they were chosen (their mean ignored fraction, windows skipped); "material" what the checkpoint's material knows
of the real particles beyond the settings (`material_facts`: drgan.segment's contact_weight=auto reads it). A shard
writes its own part to manifest_shard_I.json; whichever process finds the dataset complete writes manifest.json
(atomically).
``read_manifest`` checks a folder before anything is done with it and names the folder when it is not a
dataset written by drgan.generate.
"""

from __future__ import annotations

import json
import logging
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING

from drgan.core import io
from drgan.core.errors import ConfigError, DataError
from drgan.synthetic.backgrounds import backgrounds_exhausted, partial_exhausted
from drgan.synthetic.folder import (
    CONFIG,
    FILE_KINDS,
    KINDS,
    MANIFEST,
    PARTIAL_RECORD,
    DatasetFolder,
    Entry,
    bg_id,
    pbg_id,
    syn_id,
)
from drgan.synthetic.shards import Shard, dataset_cutoff, kept_below, shard_manifest_name

if TYPE_CHECKING:
    from drgan.synthetic.generation_settings import GenerateSettings

log = logging.getLogger(__name__)

GENERATED_DATASET = "a dataset folder written by drgan.generate (manifest.json, images/, masks/, labels/, meta/)"


# --- writing ------------------------------------------------------------------------------------------------


def material_facts(material) -> dict:
    """What a dataset's consumers may need to know of the checkpoint's material (a ``material`` config node, typed
    here) beyond the generation settings: its name and the real particles' arrangement (Clark-Evans ratio the
    profile measured; None for a material written by hand)."""
    from drgan.scene.config import typed_material

    typed = typed_material(material)
    return {"name": typed.name, "clark_evans": typed.clark_evans}


def write_shard_manifest(
    folder: DatasetFolder, settings: GenerateSettings, shard: Shard, stats: dict, pixel_scale: float = 1.0
) -> None:
    """manifest_shard_I.json: the kept indices of one shard found on disk, and its throughput."""
    outcomes = folder.outcomes()
    mine = sorted(i for i, kept in outcomes.items() if kept and shard.owns_index(i))
    io.write_json(folder.root / shard_manifest_name(shard), {
        "shard": str(shard),
        "config": settings.record(),
        "pixel_scale": pixel_scale,
        "entries": [Entry.synthetic(i).to_json() for i in mine],
        "throughput": stats,
    })  # fmt: skip


def write_manifest(
    folder: DatasetFolder,
    settings: GenerateSettings,
    stats: dict | None,
    required: bool,
    pixel_scale: float | None = None,
    material: dict | None = None,
) -> dict | None:
    """manifest.json of the first n kept indices and the backgrounds, when all are done.

    ``pixel_scale``: image px per px of the real images the GAN learned from (render resolution / the material's
    view_width; below 1 when the GAN saw large particles in wide windows, area-averaged); None (merge=true): the
    shard manifests' (1.0 without any). A segmenter trained on the set keeps it (drgan.segment) and resamples the
    real images it predicts by it (drgan.segmenters.inference). ``material``: `material_facts` of the checkpoint's
    material (None: not recorded).

    Incomplete: a ConfigError naming what is missing when ``required`` (single process, merge=true),
    else None (a shard whose siblings are still running)."""
    outcomes = folder.outcomes()
    n, n_background = settings.n, settings.n_background
    cutoff, missing = dataset_cutoff(outcomes, n)
    backgrounds = [bg_id(k) for k in range(n_background) if folder.done(bg_id(k))]
    # Partial backgrounds fill up what the PatchSet's backgrounds leave of n_background (once those are all done).
    wanted = n_background - len(backgrounds) if settings.partial_background else 0
    partials = [pbg_id(j) for j in range(wanted) if folder.done(pbg_id(j))]
    problem = _incomplete(folder, settings, outcomes, cutoff, missing, backgrounds, partials, wanted)
    if problem:
        if required:
            raise ConfigError(
                f"{folder.root}: dataset incomplete: {problem}; run the shards (same command, without merge=true)"
            )
        log.info("manifest.json not written yet: %s", problem)
        return None
    kept = [i for i in range(cutoff + 1) if outcomes[i]]
    dropped = [i for i in range(cutoff + 1) if not outcomes[i]]
    reasons = Counter(folder.dropped_reason(i) for i in dropped)
    entries = (
        [Entry.synthetic(i).to_json() for i in kept]
        + [Entry.background(b).to_json() for b in backgrounds]
        + [Entry.partial_background(p).to_json() for p in partials]
    )
    shards, scales = _shard_records(folder, settings.ckpt)
    if pixel_scale is None:
        pixel_scale = scales[0] if scales else 1.0
    surplus = sum(1 for i, k in outcomes.items() if k and i > cutoff)
    manifest = {
        "config": {**settings.record(), "shard": None},
        "pixel_scale": float(pixel_scale),
        "material": material,
        "counts": {
            "synthetic": len(kept),
            "background": len(backgrounds),
            "partial_background": len(partials),
            "kept": len(kept),
            "dropped": len(dropped),
            "drop_reasons": dict(reasons),
            "attempted": cutoff + 1,
            "surplus_kept_not_listed": surplus,
        },
        "throughput": {"this_run": stats, "shards": shards},
        "entries": entries,
    }
    if partials:
        manifest["partial_backgrounds"] = partial_summary(folder, partials)
    io.write_json(folder.root / MANIFEST, manifest)
    log.info(
        "manifest.json: %d synthetic (%d dropped) + %d background + %d partial background",
        len(kept), len(dropped), len(backgrounds), len(partials),
    )  # fmt: skip
    return manifest


def _incomplete(folder, settings, outcomes, cutoff, missing, backgrounds, partials, wanted) -> str | None:
    """What the dataset still lacks (the first synthetic index not done, backgrounds or partial backgrounds shard 0
    has not written), or None when it is complete."""
    n, n_background = settings.n, settings.n_background
    if cutoff is None:
        return (
            f"synthetic index {missing} ({syn_id(missing)}) is not done yet "
            f"({kept_below(outcomes, missing)} of n={n} kept below it)"
        )
    if len(backgrounds) < n_background and not backgrounds_exhausted(settings.backgrounds, len(backgrounds)):
        return f"{len(backgrounds)} of n_background={n_background} background patches are done (shard 0 writes them)"
    if len(partials) < wanted and not partial_exhausted(folder, len(partials)):
        return (
            f"{len(partials)} of the {wanted} partial backgrounds that fill up n_background={n_background} are "
            "done (shard 0 writes them)"
        )
    return None


def _shard_records(folder: DatasetFolder, ckpt) -> tuple[list[dict], list[float]]:
    """(throughput, pixel scale) of each shard manifest written from the same checkpoint."""
    shards, scales = [], []
    for path in sorted(folder.root.glob("manifest_shard_*.json")):
        record = json.loads(path.read_text())
        if record.get("config", {}).get("ckpt") == ckpt:
            shards.append({"shard": record.get("shard"), **record.get("throughput", {})})
            scales.append(float(record.get("pixel_scale", 1.0)))
    return shards, scales


def partial_summary(folder: DatasetFolder, partials: list[str]) -> dict:
    """How the partial backgrounds ``partials`` ignore their pixels (from their meta), and how they were chosen
    (partial_backgrounds.json, when there)."""
    fractions = []
    for item in partials:
        try:
            fractions.append(float(json.loads((folder.root / "meta" / f"{item}.json").read_text())["ignored_fraction"]))
        except (OSError, ValueError, KeyError, TypeError):
            continue
    summary: dict = {"count": len(partials)}
    if fractions:
        summary["ignored_fraction"] = {
            "mean": round(sum(fractions) / len(fractions), 4),
            "min": round(min(fractions), 4),
            "max": round(max(fractions), 4),
        }
    try:
        record = json.loads((folder.root / PARTIAL_RECORD).read_text())
    except (OSError, ValueError):
        record = None
    if isinstance(record, dict):
        summary.update(
            {k: record[k] for k in ("candidates", "usable", "skipped", "max_ignored", "margin_px") if k in record}
        )
    return summary


# --- reading ------------------------------------------------------------------------------------------------


def is_generated(root: str | Path) -> bool:
    """Whether ``root`` was made by drgan.generate (complete or not): it holds manifest.json or config.json."""
    root = Path(root)
    return (root / MANIFEST).is_file() or (root / CONFIG).is_file()


def manifest_pixel_scale(manifest: dict, setting: str = "data") -> float:
    """A generated set's image px per real image px (``write_manifest``); 1.0 for a manifest without one (sets made
    before it was recorded rendered one px per real px), a DataError naming ``setting`` for a value that is none."""
    value = manifest.get("pixel_scale", 1.0)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < float("inf"):
        raise DataError(f"{setting}: manifest.json's pixel_scale {value!r}: expected a positive number")
    return float(value)


def read_manifest(root: str | Path, setting: str = "data") -> dict:
    """The checked manifest.json of a complete dataset folder, or a DataError naming ``setting=root`` and what
    is wrong: no such folder, a folder of another kind, a dataset whose shards are not merged yet, or a
    manifest that is not one (unreadable, no entries, entries without an image or mask)."""
    root = Path(root)
    if not root.is_dir():
        kind = "a file, not a folder" if root.exists() else "no such folder"
        raise DataError(f"{setting}={root}: {kind} (expected {GENERATED_DATASET})")
    path = root / MANIFEST
    if not path.is_file():
        if (root / CONFIG).is_file():
            raise DataError(
                f"{setting}={root}: a drgan.generate folder without manifest.json, so the dataset is not complete: "
                "run the same generate command again (it resumes), or with merge=true once all its shards are done"
            )
        raise DataError(
            f"{setting}={root}: not a drgan dataset: no manifest.json (holds {_listing(root)}; "
            f"expected {GENERATED_DATASET})"
        )
    try:
        manifest = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as err:
        raise DataError(f"{setting}={root}: manifest.json cannot be read ({type(err).__name__}: {err})") from err
    entries = manifest.get("entries") if isinstance(manifest, dict) else None
    if not isinstance(entries, list):
        raise DataError(f"{setting}={root}: manifest.json has no 'entries' list (expected {GENERATED_DATASET})")
    if not entries:
        raise DataError(f"{setting}={root}: manifest.json lists no entries")
    for k, entry in enumerate(entries):
        files = entry.get("files") if isinstance(entry, dict) else None
        if not isinstance(files, dict) or not isinstance(entry.get("id"), str) or not {"image", "mask"} <= set(files):
            raise DataError(
                f"{setting}={root}: manifest.json entry {k} ({str(entry)[:80]}) is not an item with "
                "'id' and 'files' holding 'image' and 'mask'"
            )
        outside = [f for f in files.values() if not isinstance(f, str) or not _inside(f)]
        if outside:
            raise DataError(
                f"{setting}={root}: manifest.json entry {entry['id']} names {outside[0]!r} "
                "(expected a path inside the dataset folder, e.g. images/ID.png)"
            )
        if entry.get("kind") not in KINDS:
            raise DataError(
                f"{setting}={root}: manifest.json entry {entry['id']} has kind {entry.get('kind')!r} "
                f"(expected one of {', '.join(map(repr, KINDS))})"
            )
    return manifest


def _inside(relative: str) -> bool:
    """Whether a manifest's file path stays inside the dataset folder (relative, no "..")."""
    return not Path(relative).is_absolute() and ".." not in Path(relative).parts


def _listing(root: Path, shown: int = 6) -> str:
    """A few names of what a folder holds, for a message."""
    names = sorted(p.name + ("/" if p.is_dir() else "") for p in root.iterdir())
    if not names:
        return "nothing"
    return ", ".join(names[:shown]) + (f" and {len(names) - shown} more" if len(names) > shown else "")


def manifest_entries(manifest: dict) -> list[Entry]:
    """The entries of a manifest read by ``read_manifest``, in its order."""
    return [Entry(e["id"], e["kind"], dict(e["files"]), e.get("index")) for e in manifest["entries"]]


def check_files(root: str | Path, entries: list[Entry], roles=("image", "mask"), setting: str = "data") -> None:
    """A DataError naming the first missing file of an entry (by ``roles``), before any of them is used."""
    root = Path(root)
    for entry in entries:
        for role in roles:
            if not (root / entry.files[role]).is_file():
                raise DataError(f"{setting}={root}: {entry.files[role]} of {entry.id} is missing")


def unlisted_items(root: str | Path, entries: list[Entry]) -> list[str]:
    """Ids of images on disk that the manifest does not list (e.g. kept by a shard beyond the n-th)."""
    listed = {e.id for e in entries}
    images = Path(root) / FILE_KINDS[0]
    on_disk = {p.stem for p in images.glob("*.png") if not p.name.startswith(".")} if images.is_dir() else set()
    return sorted(on_disk - listed)


# --- image/mask pairs for a segmenter -----------------------------------------------------------------------


def image_mask_pairs(root: str | Path, setting: str = "data") -> list[tuple[str, Path, Path]]:
    """(id, image file, mask file) of every item of a dataset folder, sorted by id.

    A folder written by drgan.generate: the items its manifest.json lists (each file checked to exist; images on
    disk that it does not list, e.g. kept by a shard beyond the n-th, are left out); without its manifest it is
    not complete and refused. A folder of hand-made pairs (images/ID.<ext> and masks/ID.<ext>, no manifest or
    config.json): paired by file name. Anything else: a DataError naming ``setting=root``."""
    root = Path(root)
    if root.is_dir() and not is_generated(root):
        if (root / "images").is_dir() and (root / "masks").is_dir():
            return _pairs_by_name(root, setting)
        raise DataError(
            f"{setting}={root}: not a drgan dataset: no manifest.json, and no images/ and masks/ folders "
            f"(holds {_listing(root)}; expected {GENERATED_DATASET}, or image/mask pairs images/ID.png "
            "and masks/ID.png)"
        )
    entries = manifest_entries(read_manifest(root, setting))
    check_files(root, entries, ("image", "mask"), setting)
    unlisted = unlisted_items(root, entries)
    if unlisted:
        log.info(
            "%s=%s: %d image(s) on disk not listed in manifest.json (e.g. %s) are left out",
            setting,
            root,
            len(unlisted),
            unlisted[0],
        )
    return [(e.id, root / e.files["image"], root / e.files["mask"]) for e in sorted(entries, key=lambda e: e.id)]


def _pairs_by_name(root: Path, setting: str) -> list[tuple[str, Path, Path]]:
    from drgan.data.images import IMAGE_SUFFIXES, list_images

    images_dir, masks_dir = root / "images", root / "masks"
    image_paths = list_images(images_dir)
    mask_stems = {p.stem for p in masks_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES}
    missing = [p.stem for p in image_paths if p.stem not in mask_stems]
    if missing:
        raise DataError(f"{setting}={root}: no mask for {len(missing)} image(s) in masks/, e.g. {missing[0]!r}")
    mask_paths = list_images(masks_dir, [p.stem for p in image_paths])
    return [(image.stem, image, mask) for image, mask in zip(image_paths, mask_paths)]
