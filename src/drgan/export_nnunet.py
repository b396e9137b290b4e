"""`python -m drgan.export_nnunet data=DIR out=NNUNET_RAW dataset_id=501 name=TiO2SEM`: nnU-Net v2 raw layout.

Reads the dataset that drgan.generate lists in DIR/manifest.json (synthetic pairs, backgrounds and partial
backgrounds; read and checked by drgan.synthetic.manifest) and writes

    NNUNET_RAW/Dataset501_TiO2SEM/imagesTr/{case}_0000.png   the grey image (one channel, "SEM")
    NNUNET_RAW/Dataset501_TiO2SEM/labelsTr/{case}.png        the mask: 0 background, 1 particle, 2 contour (3 ignore)
    NNUNET_RAW/Dataset501_TiO2SEM/dataset.json

Cases keep the dataset's ids (syn_000012, bg_0003, pbg_0000). Files are copied byte for byte, each atomically,
except the masks holding drgan's ``IGNORE`` (255: the particles of partial backgrounds). nnU-Net v2 takes an
ignore label only as the *highest* label value, named "ignore" in dataset.json (its documentation/ignore_label.md;
it then trains with partial losses and leaves those pixels out of its validation metrics). So when any mask holds
255, dataset.json gets ``"ignore": K`` (K = one above the highest class of ``labels``: 3 for drgan's three
classes; or the value given as ``labels.ignore``, which must be the highest) and those masks are written with 255
replaced by K. A mask value that is neither a label nor 255 is refused, naming the file, before anything is written.
An existing dataset folder is completed when it holds the same dataset (same dataset.json, no other
cases); a different one, or another folder with the same dataset id, is refused.
"""

from __future__ import annotations

import json
import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from drgan.core import io
from drgan.core.errors import ConfigError, DataError
from drgan.core.typed_settings import read_settings, setting, typed
from drgan.launch.runtime import stage_main, start
from drgan.synthetic.folder import IGNORE
from drgan.synthetic.manifest import check_files, manifest_entries, read_manifest

log = logging.getLogger(__name__)

CHANNEL = "_0000"  # nnU-Net's channel suffix: one channel
IGNORE_NAME = "ignore"  # the name nnU-Net v2 gives its ignore label (the highest label value)


def dataset_folder_name(dataset_id: int, name: str) -> str:
    if isinstance(dataset_id, bool) or not isinstance(dataset_id, int) or not 1 <= dataset_id <= 999:
        raise ConfigError(f"dataset_id={dataset_id!r}: expected an integer in 1..999 (nnU-Net's DatasetNNN)")
    if not re.fullmatch(r"[A-Za-z0-9_-]+", str(name or "")):
        raise ConfigError(
            f"name={name!r}: expected letters, digits, '_' or '-' (it becomes Dataset{dataset_id:03d}_<name>)"
        )
    return f"Dataset{dataset_id:03d}_{name}"


def check_labels(labels: dict) -> None:
    """nnU-Net v2's rules for dataset.json's labels: 'background': 0, consecutive values 0..K-1, and an 'ignore'
    label, if any, the highest."""
    values = sorted(int(v) for v in labels.values())
    if values != list(range(len(values))) or labels.get("background") != 0:
        raise ConfigError(f"labels={labels}: nnU-Net expects 'background': 0 and consecutive integer values 0..K-1")
    if IGNORE_NAME in labels and int(labels[IGNORE_NAME]) != values[-1]:
        raise ConfigError(
            f"labels={labels}: nnU-Net's ignore label must be the highest value ({values[-1]} here), named 'ignore'"
        )


def dataset_json(
    manifest: dict, n_cases: int, channel_names: dict, labels: dict, name: str, description: str | None
) -> dict:
    check_labels(labels)
    config = manifest.get("config", {})
    counts = manifest.get("counts", {})
    partial = counts.get("partial_background", 0)
    return {
        "name": name,
        "description": description
        or (
            f"drgan synthetic {config.get('material', '')} dataset: {counts.get('synthetic', '?')} DiffRenderGAN renders "
            f"+ {counts.get('background', '?')} real background patches"
            + (f" + {partial} real partial backgrounds (their particles: label 'ignore')" if partial else "")
            + f" (checkpoint {config.get('ckpt', '?')})"
        ),
        "channel_names": {str(k): str(v) for k, v in channel_names.items()},
        "labels": {str(k): int(v) for k, v in labels.items()},
        "numTraining": n_cases,
        "file_ending": ".png",
    }


@typed
@dataclass(frozen=True)
class ExportSettings:
    """Every key of conf/segmentation/export_nnunet.yaml, typed (`read_settings`)."""

    data: Path = setting()
    out: Path = setting()
    dataset_id: int = setting(501, ge=1, le=999, expected="an integer in 1..999 (nnU-Net's DatasetNNN)")
    name: str = "TiO2SEM"
    channel_names: dict = field(default_factory=lambda: {"0": "SEM"})
    labels: dict = field(default_factory=lambda: {"background": 0, "particle": 1, "contour": 2})
    description: str | None = None

    @classmethod
    def from_config(cls, cfg: DictConfig) -> ExportSettings:
        return read_settings(cls, cfg, "export_nnunet")


def export(s: ExportSettings) -> Path:
    """Write the nnU-Net raw dataset; return its folder."""
    data = s.data.expanduser().resolve()
    out = s.out.expanduser().resolve()
    folder_name = dataset_folder_name(s.dataset_id, s.name)
    channel_names, labels = s.channel_names, s.labels
    if not channel_names:
        raise ConfigError("channel_names: expected at least one channel, e.g. {'0': 'SEM'}")
    check_labels(labels)
    manifest = read_manifest(data, setting="data")
    entries = manifest_entries(manifest)
    check_files(data, entries, ("image", "mask"), setting="data")
    ignored = _ignored_cases(data, entries, labels)
    if ignored and IGNORE_NAME not in labels:
        labels = {**labels, IGNORE_NAME: max(int(v) for v in labels.values()) + 1}
    description = dataset_json(manifest, len(entries), channel_names, labels, s.name, s.description)

    target = out / folder_name
    _check_target(out, target, s.dataset_id, description, {e.id for e in entries})
    for entry in entries:
        _copy(data / entry.files["image"], target / "imagesTr" / f"{entry.id}{CHANNEL}.png")
        if entry.id in ignored:
            _write_mask(data / entry.files["mask"], target / "labelsTr" / f"{entry.id}.png", int(labels[IGNORE_NAME]))
        else:
            _copy(data / entry.files["mask"], target / "labelsTr" / f"{entry.id}.png")
    if ignored:
        log.info(
            "%d case(s) hold drgan's ignore value %d: written as nnU-Net's ignore label %d",
            len(ignored),
            IGNORE,
            labels[IGNORE_NAME],
        )
    io.write_json(target / "dataset.json", description)  # last: a complete export has a dataset.json
    log.info("wrote %s: %d cases", target, len(entries))
    print(f"{target}: {len(entries)} training cases")
    return target


def _read_mask(path: Path) -> np.ndarray:
    from PIL import Image

    try:
        with Image.open(path) as image:
            return np.asarray(image)
    except Exception as exc:
        raise DataError(f"mask {path}: cannot be read ({type(exc).__name__}: {exc})") from exc


def _ignored_cases(data: Path, entries, labels: dict) -> set[str]:
    """Ids of the cases whose mask holds drgan's IGNORE; a DataError naming the first mask holding a value that is
    neither one of ``labels`` (its "ignore" aside) nor IGNORE."""
    allowed = {int(v) for k, v in labels.items() if k != IGNORE_NAME} | {IGNORE}
    ignored = set()
    for entry in entries:
        path = data / entry.files["mask"]
        values = set(np.unique(_read_mask(path)).tolist())
        bad = sorted(values - allowed)
        if bad:
            raise DataError(
                f"mask {path}: values {bad[:5]} are none of labels={labels} nor drgan's ignore value {IGNORE}"
            )
        if IGNORE in values:
            ignored.add(entry.id)
    return ignored


def _write_mask(source: Path, destination: Path, ignore_label: int) -> None:
    """``source``'s mask with IGNORE replaced by nnU-Net's ``ignore_label``, as an 8-bit PNG (skipped when the same)."""
    mask = _read_mask(source)
    mask = np.where(mask == IGNORE, ignore_label, mask).astype(np.uint8)
    if destination.is_file() and np.array_equal(_read_mask(destination), mask):
        return
    io.write_png(destination, mask)


def _check_target(out: Path, target: Path, dataset_id: int, description: dict, cases: set[str]) -> None:
    if out.is_dir():
        others = [p.name for p in out.glob(f"Dataset{dataset_id:03d}_*") if p.name != target.name]
        if others:
            raise ConfigError(
                f"out={out} already holds {others[0]} with dataset_id={dataset_id}: pick another dataset_id (nnU-Net ids are unique)"
            )
    if not target.exists():
        return
    existing = target / "dataset.json"
    if existing.is_file():
        old = json.loads(existing.read_text())
        if old != description:
            raise ConfigError(
                f"{target} holds a different dataset (its dataset.json differs): remove it or choose another dataset_id/name"
            )
    found = {p.name[: -len(CHANNEL + ".png")] for p in (target / "imagesTr").glob(f"*{CHANNEL}.png")}
    found |= {p.stem for p in (target / "labelsTr").glob("*.png")}
    extra = sorted(found - cases)
    if extra:
        raise ConfigError(
            f"{target} holds cases not in this dataset (e.g. {extra[0]}): remove it or choose another dataset_id/name"
        )


def _copy(source: Path, destination: Path) -> None:
    data = source.read_bytes()
    if destination.is_file() and destination.read_bytes() == data:
        return
    io.write_bytes(destination, data)


def compose_config(overrides=()) -> DictConfig:
    """The composed config, e.g. for tests: ``compose_config(["data=DIR", "out=RAW"])``."""
    from drgan.launch.configs import compose

    return compose(overrides, config_name="export_nnunet")


@stage_main("conf/segmentation", "export_nnunet")
def main(cfg: DictConfig) -> None:
    export(ExportSettings.from_config(cfg))


if __name__ == "__main__":
    start(main)
