"""The folder of one synthetic dataset: item ids, their files, and the records that mark an item done.

    images/ID.png   8-bit grey           masks/ID.png   uint8 {0 background, 1 particle, 2 contour, 255 ignore}
    labels/ID.png   instance ids (16-bit when > 255)    meta/ID.json   what made the item (written last)
    dropped/ID.json why a synthetic index was dropped    config.json    the settings that fix every index
    manifest.json   the dataset (drgan.synthetic.manifest)    manifest_shard_I.json   one shard's part
    partial_backgrounds.json   how the partial backgrounds were chosen (drgan.synthetic.backgrounds)

Items: ``syn_000123`` synthetic (a render; masks 0/1/2), ``bg_0004`` background (a real window free of particles;
mask all 0), ``pbg_0002`` partial background (a real window with particles: mask 0 on its background and
``IGNORE`` = 255 on its particles and a margin around them, which a segmenter's loss leaves out; its labels/ are
all 0, as its particles are not annotated).

Every file is written atomically (drgan.core.io). An item is done when its meta/ID.json (kept) or dropped/ID.json
record exists: the record is written after the item's PNGs, so a PNG without a record is what an interrupted
run left behind (``DatasetFolder.remove_partial``).
"""

from __future__ import annotations

import json
import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drgan.core import io
from drgan.core.errors import ConfigError
from drgan.scene.labels import IGNORE  # noqa: F401  (the mask value of no class: imported from here too)

log = logging.getLogger(__name__)

SYN, BG, PBG = "syn", "bg", "pbg"
SYNTHETIC, BACKGROUND, PARTIAL_BACKGROUND = "synthetic", "background", "partial_background"  # the kinds of an item
KINDS = (SYNTHETIC, BACKGROUND, PARTIAL_BACKGROUND)
FILE_KINDS = ("images", "masks", "labels")  # PNG folders; meta/ID.json comes last
MANIFEST = "manifest.json"
CONFIG = "config.json"
PARTIAL_RECORD = "partial_backgrounds.json"
# drgan.core.io.atomic_path's temporary name for a file NAME: ".NAME.<random>.tmp<suffix of NAME>".
_TEMP_NAME = re.compile(r"^\.(?P<target>.+)\.[A-Za-z0-9_]+\.tmp(\.[A-Za-z0-9]+)?$")


def syn_id(index: int) -> str:
    """``syn_000123``: synthetic index 123 (dropped indices leave gaps)."""
    return f"{SYN}_{index:06d}"


def bg_id(index: int) -> str:
    """``bg_0004``: the fifth real background patch."""
    return f"{BG}_{index:04d}"


def pbg_id(index: int) -> str:
    """``pbg_0002``: the third partial background (a real window with particles, which its mask ignores)."""
    return f"{PBG}_{index:04d}"


def syn_index(item: str) -> int | None:
    """The index of a synthetic item id, None for any other name."""
    digits = item[len(SYN) + 1 :]
    return int(digits) if item.startswith(SYN + "_") and digits.isdigit() else None


def item_files(item: str) -> dict[str, str]:
    """Paths of an item's files relative to the dataset folder, by role: image, mask, label, meta."""
    names = {kind.rstrip("s"): f"{kind}/{item}.png" for kind in FILE_KINDS}
    names["meta"] = f"meta/{item}.json"
    return names


@dataclass(frozen=True)
class Entry:
    """One item of a dataset as its manifest lists it."""

    id: str
    kind: str  # SYNTHETIC, BACKGROUND or PARTIAL_BACKGROUND
    files: dict  # role -> path relative to the dataset folder (item_files)
    index: int | None = None  # the synthetic index; None for a background

    @classmethod
    def synthetic(cls, index: int) -> Entry:
        return cls(syn_id(index), SYNTHETIC, item_files(syn_id(index)), index)

    @classmethod
    def background(cls, item: str) -> Entry:
        return cls(item, BACKGROUND, item_files(item))

    @classmethod
    def partial_background(cls, item: str) -> Entry:
        return cls(item, PARTIAL_BACKGROUND, item_files(item))

    def to_json(self) -> dict:
        record = {"id": self.id, "kind": self.kind}
        if self.index is not None:
            record["index"] = self.index
        record["files"] = dict(self.files)
        return record


class DatasetFolder:
    """Files of one generated dataset; an item is done when its meta (kept) or dropped record exists."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)

    def files(self, item: str) -> dict[str, str]:
        return item_files(item)

    def done(self, item: str) -> bool:
        return all((self.root / f).is_file() for f in self.files(item).values())

    def outcomes(self) -> dict[int, bool]:
        """index -> kept (True) / dropped (False), for every finished synthetic index (file names only)."""
        found: dict[int, bool] = {}
        for folder, kept in (("dropped", False), ("meta", True)):
            directory = self.root / folder
            if not directory.is_dir():
                continue
            for entry in os.scandir(directory):
                index = syn_index(entry.name[: -len(".json")]) if entry.name.endswith(".json") else None
                if index is not None:
                    found[index] = kept or found.get(index, False)
        return found

    def write(self, item: str, image: np.ndarray, mask: np.ndarray, labels: np.ndarray, meta: dict) -> None:
        """An item's PNGs, then its meta record (which marks it done)."""
        for kind, array in (("images", image), ("masks", mask), ("labels", labels)):
            io.write_png(self.root / kind / f"{item}.png", array)
        io.write_json(self.root / "meta" / f"{item}.json", {"id": item, **meta, "files": self.files(item)})

    def write_dropped(self, item: str, record: dict) -> None:
        io.write_json(self.root / "dropped" / f"{item}.json", {"id": item, **record})

    def dropped_reason(self, index: int) -> str | None:
        """The reason recorded for a dropped index; "unknown" when its record cannot be read."""
        try:
            return json.loads((self.root / "dropped" / f"{syn_id(index)}.json").read_text()).get("reason")
        except (OSError, ValueError):
            return "unknown"

    def remove_partial(self, owns) -> dict[str, int]:
        """Remove what a killed run left of the items this process owns (``owns(item) -> bool``): temporary files
        of drgan.core.io's atomic writes (a SIGKILL skips their clean-up), and the PNGs of items without their
        meta/ID.json or dropped/ID.json record (killed between an item's files: meta comes last). Such an item
        is not done, so this run renders it again; removing its files first means that no image is ever left
        without its mask, whatever n the next run asks for. Returns the counts removed, by kind."""
        removed = {"temporary": 0, "unpaired": 0}
        for folder in (*FILE_KINDS, "meta", "dropped"):
            directory = self.root / folder
            if not directory.is_dir():
                continue
            for entry in os.scandir(directory):
                temp = _TEMP_NAME.match(entry.name)
                if temp:
                    if owns(Path(temp["target"]).stem):
                        os.unlink(entry.path)
                        removed["temporary"] += 1
                elif folder in FILE_KINDS and entry.name.endswith(".png"):
                    item = entry.name[: -len(".png")]
                    recorded = any((self.root / kind / f"{item}.json").is_file() for kind in ("meta", "dropped"))
                    if owns(item) and not recorded:
                        os.unlink(entry.path)
                        removed["unpaired"] += 1
        for entry in os.scandir(self.root) if self.root.is_dir() else ():
            temp = _TEMP_NAME.match(entry.name)
            if temp and owns(Path(temp["target"]).stem):  # config.json, manifest*.json
                os.unlink(entry.path)
                removed["temporary"] += 1
        if any(removed.values()):
            log.warning(
                "%s: removed %d temporary file(s) and %d file(s) of unfinished items left by an interrupted run",
                self.root, removed["temporary"], removed["unpaired"],
            )  # fmt: skip
        return removed

    def check_settings(self, fixed: dict) -> None:
        """Record the settings that fix every item at first use (config.json); refuse to complete a folder
        made with other ones."""
        path = self.root / CONFIG
        if path.is_file():
            old = json.loads(path.read_text()).get("fixed", {})
            diff = {k: (old.get(k), fixed.get(k)) for k in {**old, **fixed} if old.get(k) != fixed.get(k)}
            if diff:
                text = "; ".join(f"{k}: {a!r} there, {b!r} now" for k, (a, b) in diff.items())
                raise ConfigError(
                    f"out={self.root} holds a dataset generated with other settings ({text}): "
                    "use another out= or the same settings"
                )
        else:
            io.write_json(path, {"fixed": fixed})
