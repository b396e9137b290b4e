"""A weak segmenter caught before it reaches the user's numbers: its agreement with the classical segmentation of the
user's own images, and another seed when it leaves too much of it uncovered.

A U-Net seed can miss the agglomerates' inner particles on the real images while its closed-loop check on generated
pairs looks as good as the other seeds': the check's pairs are its training distribution. The profile's classical
segmentation (threshold + watershed at the measured scale) finds the particles' area on such images without
training, so the share of its foreground that the segmenter's foreground covers ranks seeds as the truth does
(experiments/statistics/trust.md, "A weak seed caught without annotations"). No annotation is read.

drgan.segment (the pipeline wires ``agreement.images`` and ``agreement.reference``: its data folder and the profile's
``labels/``) predicts up to ``max_images`` of those images after training, and when the segmenter covers less than
``min_covered`` of the classical foreground (or their Dice is under ``min_dice``: a foreground spilling over
everything covers it all) it trains again with the next seed (the same pairs, the same validation
and check split), at most ``retries`` times; of the seeds tried it keeps the one whose foreground agrees best with the
classical one (Dice: covering everything does not win). Every attempt's numbers go to metrics.json ("agreement") and
the others' checkpoints stay in ``attempts/<k>/``.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from drgan.core.errors import ConfigError, DataError
from drgan.core.io import write_json
from drgan.core.typed_settings import read_settings, setting, typed

ATTEMPTS_FILE = "attempts.json"
ATTEMPTS_DIR = "attempts"
MOVED = ("checkpoints", "metrics.json")  # what one attempt leaves in the run folder


@typed
@dataclass(frozen=True)
class AgreementSettings:
    """The ``agreement`` block of segment.yaml, typed (`agreement_settings`)."""

    images: Path = setting()  # the user's images (named like the reference labels)
    reference: Path = setting()  # their classical instance labels, ID.tif (the profile's labels/)
    max_images: int = setting(8, ge=1)
    min_covered: float = setting(0.85, ge=0, expected="a share in [0, 1]", le=1)
    min_dice: float = setting(0.6, ge=0, expected="a share in [0, 1]", le=1)
    retries: int = setting(1, ge=0)
    crop_rows: Any = "auto"


def agreement_settings(node) -> AgreementSettings | None:
    """The ``agreement`` block checked (None when its ``reference`` is null: off), or a ConfigError naming the key."""
    if node is None or node.get("reference") is None:
        return None
    if node.get("images") is None:
        raise ConfigError("agreement.reference is set but agreement.images is null: expected the folder of the images")
    typed = read_settings(AgreementSettings, node, "segment", prefix="agreement.")
    return replace(typed, images=typed.images.expanduser(), reference=typed.reference.expanduser())


def spread(ids: Sequence[str], n: int) -> list[str]:
    """At most ``n`` of ``ids`` (sorted), evenly spread over them."""
    ids = sorted(ids)
    if len(ids) <= n:
        return ids
    return [ids[int(round(k))] for k in np.linspace(0, len(ids) - 1, n)]


def read_reference(s: AgreementSettings) -> list[tuple[object, np.ndarray]]:
    """(image item, classical instance labels) of up to ``max_images`` reference images, every file read and checked
    (the same image rows the predictor sees: ``crop_rows``), or a DataError naming the file. The labels' foreground
    (> 0) is what `foreground_agreement` compares; their particles are what the split's count guard counts
    (drgan.segmenters.calibrate.real_count_guard)."""
    from drgan.data.imagej import read_label_tiff
    from drgan.data.images import list_images
    from drgan.segmenters.pairs import read_image_item

    for what, folder in (("images", s.images), ("reference", s.reference)):
        if not folder.is_dir():
            raise DataError(f"agreement.{what}={folder}: no such folder")
    labels = {p.stem: p for p in s.reference.glob("*.tif")}
    if not labels:
        raise DataError(f"agreement.reference={s.reference}: no ID.tif label image in it (drgan.profile writes them)")
    ids = spread(list(labels), s.max_images)
    try:
        paths = list_images(s.images, ids)
    except DataError as error:
        raise DataError(f"agreement.images={s.images}: {error} (the reference {s.reference} names those ids)") from None
    items = []
    for path, image_id in zip(paths, ids):
        item = read_image_item(path, image_id, s.crop_rows)
        classical = read_label_tiff(labels[image_id])[0]
        if classical.shape != item.image.shape:
            raise DataError(
                f"agreement.reference: {labels[image_id]} is {classical.shape[1]} x {classical.shape[0]} px, the "
                f"image {path} {item.image.shape[1]} x {item.image.shape[0]} px (after its info bar): expected the same"
            )
        items.append((item, classical))
    return items


def foreground_agreement(reference: Sequence[np.ndarray], found: Sequence[np.ndarray]) -> dict:
    """``covered``: the share of the reference foreground pixels that ``found`` holds too; ``dice``: the two
    foregrounds' Dice; both pooled over the images."""
    ref = np.concatenate([np.asarray(r, bool).ravel() for r in reference])
    got = np.concatenate([np.asarray(f, bool).ravel() for f in found])
    if ref.shape != got.shape:
        raise ValueError(f"foreground_agreement: {ref.size} reference pixels against {got.size} found")
    both, n_ref, n_got = float((ref & got).sum()), float(ref.sum()), float(got.sum())
    return {
        "covered": both / n_ref if n_ref else float("nan"),
        "dice": 2.0 * both / (n_ref + n_got) if n_ref + n_got else float("nan"),
    }


def check_agreement(checkpoint: Path, items: Sequence[tuple[object, np.ndarray]], progress: bool = False) -> dict:
    """The segmenter of ``checkpoint`` (as analyze predicts: its calibrated split, noise matching, working scale)
    against the reference foregrounds: `foreground_agreement` and the images' ids."""
    from drgan.core.progress import track
    from drgan.segmenters.predictors import load_predictor

    predictor = load_predictor(str(checkpoint), {}, "agreement")
    images = [item for item, _ in items]
    predictor.check(images)
    iterator = track(images, "checking against the classical foreground", unit="images") if progress else images
    found = [np.asarray(predictor(item)) > 0 for item in iterator]
    result = foreground_agreement([ref > 0 for _, ref in items], found)
    return {**result, "ids": [item.id for item in images]}


# --- the attempts, one seed each ---------------------------------------------------------------------------------


class Attempts:
    """The seeds a guarded segment run has tried (``attempts.json`` in its folder): each attempt's seed, agreement
    and folder; a killed run resumes the attempt in progress."""

    def __init__(self, out: Path, settings: AgreementSettings):
        self.out, self.s = Path(out), settings
        path = self.out / ATTEMPTS_FILE
        self.records: list[dict] = json.loads(path.read_text())["attempts"] if path.is_file() else []

    def finished(self) -> bool:
        if not self.records:
            return False
        return not weak(self.records[-1], self.s) or len(self.records) > self.s.retries

    def stash(self, seed: int, check: dict) -> None:
        """The attempt just trained moved to attempts/<k>/ and recorded."""
        k = len(self.records)
        folder = self.out / ATTEMPTS_DIR / str(k)
        if folder.exists():
            shutil.rmtree(folder)  # a killed run's half-stashed attempt of the same number
        folder.mkdir(parents=True)
        for name in MOVED:
            if (self.out / name).exists():
                os.replace(self.out / name, folder / name)
        self.records.append({"attempt": k, "seed": seed, "covered": check["covered"], "dice": check["dice"],
                             "ids": check["ids"], "folder": str(folder.relative_to(self.out))})  # fmt: skip
        write_json(self.out / ATTEMPTS_FILE, {"attempts": self.records})

    def keep_best(self) -> dict:
        """The attempt whose foreground agrees best (Dice) moved back into the run folder, its metrics.json told
        why (written last: the run's done file); returns that metrics.json's content."""
        best = max(self.records, key=lambda r: (r["dice"], -r["attempt"]))
        folder = self.out / best["folder"]
        metrics = json.loads((folder / "metrics.json").read_text())
        os.replace(folder / "checkpoints", self.out / "checkpoints")
        metrics["agreement"] = {
            "kept_attempt": best["attempt"],
            "kept_seed": best["seed"],
            "min_covered": self.s.min_covered,
            "min_dice": self.s.min_dice,
            "attempts": self.records,
            "why": why(self.records, best, self.s),
        }
        write_json(self.out / "metrics.json", metrics)
        (folder / "metrics.json").unlink()
        if not any(folder.iterdir()):
            folder.rmdir()
        if not any((self.out / ATTEMPTS_DIR).iterdir()):
            (self.out / ATTEMPTS_DIR).rmdir()
        return metrics


def weak(record: dict, s: AgreementSettings) -> bool:
    """Too little of the classical foreground covered (the weak seed's failure), or too little agreement at all (a
    foreground spilling far beyond the particles covers everything)."""
    return not (record["covered"] >= s.min_covered and record["dice"] >= s.min_dice)


def _agreed(record: dict) -> str:
    return f"covered {record['covered']:.0%} of the classical foreground (Dice {record['dice']:.2f})"


def why(records: Sequence[dict], best: dict, s: AgreementSettings) -> str:
    """One sentence for the report: what the check found and which seed was kept."""
    first = records[0]
    expected = f"at least {s.min_covered:.0%}, Dice {s.min_dice:.2f}"
    if len(records) == 1:
        return (
            f"seed {first['seed']} {_agreed(first)}; {'too little' if weak(first, s) else 'as expected'} ({expected})"
        )
    tried = ", ".join(f"seed {r['seed']} {r['covered']:.0%} (Dice {r['dice']:.2f})" for r in records)
    return f"seed {first['seed']} {_agreed(first)}, too little ({expected}): tried {tried}; kept seed {best['seed']}"
