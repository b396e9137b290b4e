"""One way from what a user names as ``model=`` to class maps: ``load_predictor``.

What a user gives is either
- a segmenter checkpoint (a file written by ``python -m drgan.segment``, or by another registered segmenter): each
  image is predicted with sliding windows and the ``inference:`` settings (drgan.segmenters.inference), the
  class rebuilt through the allow-list of drgan.segmenters.registry; or
- a folder of predicted masks, e.g. nnU-Net's output folder: one ``<id>.png`` (or another image type) per image,
  named by the image's id (a split id for drgan.evaluate, the file stem for drgan.analyze), with values 0 background,
  1 particle, 2 contour (the classes of drgan's masks and of export_nnunet's labels; a 0/1 mask is the same without
  contours). A mask of the image file's full size loses the info-bar rows its image loses. Files of other types
  (nnU-Net's dataset.json, plans.json, predict_from_raw_data_args.json) are ignored.

- ``classical``: no training at all, the baseline a materials scientist runs in ImageJ/Fiji (threshold + distance
  transform watershed): drgan's own classical segmentation (drgan.data.classical.segment_particles), the polarity
  detected from the evaluated images themselves.

Each becomes a ``Predictor``: ``check(items)`` compares it with every image before anything is computed (for a
folder: each missing, extra, misshapen or wrongly valued mask, all in one message, so that an evaluation does not
stop at its last image), then ``predictor(item)`` returns the (H, W) uint8 class map of one ImageItem.
drgan.evaluate and drgan.analyze score and measure whatever a predictor returns, so checkpoint runs and mask folders
end up in the same tables.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Protocol

import numpy as np

from drgan.core.errors import DataError
from drgan.data.images import IMAGE_SUFFIXES
from drgan.segmenters.pairs import ImageItem, drop_mask_rows, read_raw_mask

__all__ = [
    "CLASSES",
    "FunctionPredictor",
    "MaskFolder",
    "Predictor",
    "SegmenterPredictor",
    "ClassicalPredictor",
    "as_predictor",
    "load_predictor",
]

CLASSES = {0: "background", 1: "particle", 2: "contour"}
EXPECTED = "a segmenter checkpoint (python -m drgan.segment) or a folder of predicted masks, one <id>.png per image"
_SHOWN = 10  # names listed per kind of problem


class Predictor(Protocol):
    """Class maps of images. ``source``: what the user named (the tables' model column); ``how``: one line on how
    the maps are made (empty: nothing to say)."""

    source: str
    how: str

    def check(self, items: Sequence[ImageItem]) -> None:
        """Raise a DrganError, before any image is predicted, when this predictor cannot serve ``items``."""

    def __call__(self, item: ImageItem) -> np.ndarray:
        """The (H, W) class map of ``item.image``: 0 background, 1 particle, 2 contour."""


class FunctionPredictor:
    """A plain function image -> class map (tests, notebooks) as a Predictor."""

    def __init__(self, source: str, function: Callable[[np.ndarray], np.ndarray], how: str = ""):
        self.source, self.function, self.how = source, function, how

    def check(self, items: Sequence[ImageItem]) -> None:
        pass

    def __call__(self, item: ImageItem) -> np.ndarray:
        return np.asarray(self.function(item.image))


class SegmenterPredictor(FunctionPredictor):
    """A loaded segmenter with its inference settings (``make_predictor``: checked when made)."""

    def __init__(self, source: str, model, inference: Mapping):
        from drgan.segmenters.calibrate import resolve_auto
        from drgan.segmenters.inference import PER_IMAGE, make_predictor, resolve_pixel_scale

        inference, note = resolve_auto(inference, getattr(model, "split_calibration", None), source)
        own = ("pixel_scale", "noise_match")  # null: the model's own, said below
        shown = {k: v for k, v in inference.items() if not (k in own and v is None)}
        how = ", ".join(f"{k} {v}" for k, v in shown.items()) + (f" (split {note})" if note else "")
        scale = getattr(model, "pixel_scale", 1.0)
        chosen = resolve_pixel_scale(model, inference.get("pixel_scale"))
        if chosen is None and scale != 1.0:
            how += f"; images resampled by {scale:g} (the pixel scale of its training pairs)"
        elif chosen == PER_IMAGE:
            how += (
                f"; each image resampled so that its particles span {getattr(model, 'working_diameter', 0):.0f} px "
                "(its training pairs' area-weighted median; measured on a first pass)"
            )
        level = getattr(model, "train_noise", None)
        if inference.get("noise_match") is None and level:
            how += f"; cleaner images brought up to its training pairs' fine-noise level {level:.4f}"
        super().__init__(source, make_predictor(model, inference), how)
        self.model = model


def _listed(names: Sequence[str]) -> str:
    return ", ".join(names[:_SHOWN]) + (f" and {len(names) - _SHOWN} more" if len(names) > _SHOWN else "")


def _size(shape) -> str:
    return f"{shape[1]} x {shape[0]} px (W x H)"


class MaskFolder:
    """Class maps read from a folder of predicted masks (module docstring). ``check`` reads and checks them all."""

    def __init__(self, folder: Path, setting: str = "model"):
        self.folder, self.setting = Path(folder), setting
        self.source, self.how = str(folder), f"class maps read from {folder}"
        self.files: dict[str, list[Path]] = {}
        for path in sorted(self.folder.iterdir()):
            if path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES:
                self.files.setdefault(path.stem, []).append(path)
        if not self.files:
            hint = (
                f"; it looks like a run folder of drgan.segment: give {setting}={folder / 'checkpoints' / 'last.ckpt'}"
                if (self.folder / "checkpoints").is_dir()
                else ""
            )
            raise DataError(
                f"{setting}={folder}: a folder without predicted masks (expected one <id>.png per image, values 0 "
                f"background, 1 particle, 2 contour, e.g. nnU-Net's output folder){hint}"
            )
        self.maps: dict[str, np.ndarray] = {}

    def _read(self, item: ImageItem, path: Path) -> tuple[np.ndarray | None, str | None]:
        """(class map, None) or (None, what is wrong with the file)."""
        try:
            raw = read_raw_mask(path)
        except DataError as error:
            return None, f"{path.name}: {str(error).removeprefix(f'mask {path}: ')}"
        image_shape = item.image.shape
        if raw.shape != image_shape:
            if item.rows is None or raw.shape != item.file_shape:
                also = f" (its file, with the info bar: {_size(item.file_shape)})" if item.rows else ""
                return None, f"{path.name}: size {_size(raw.shape)}, its image {item.id} is {_size(image_shape)}{also}"
            raw = drop_mask_rows(raw, item.rows, path)  # predicted on the whole file: the info bar goes
        bad = sorted(set(np.unique(raw).tolist()) - set(CLASSES))
        if bad:
            return None, f"{path.name}: values {bad[:5]} (expected classes 0 background, 1 particle, 2 contour)"
        return raw.astype(np.uint8), None

    def check(self, items: Sequence[ImageItem]) -> None:
        ids = [item.id for item in items]
        problems = []
        missing = [i for i in ids if i not in self.files]
        if missing:
            problems.append(f"missing: no mask for {len(missing)} image(s): {_listed(missing)}")
        wanted = set(ids)
        extra = sorted(p.name for stem, paths in self.files.items() if stem not in wanted for p in paths)
        if extra:
            problems.append(f"extra: {len(extra)} mask(s) of no image to score: {_listed(extra)}")
        for item in items:
            paths = self.files.get(item.id, [])
            if len(paths) > 1:
                problems.append(f"{item.id}: several masks ({', '.join(p.name for p in paths)})")
            elif paths:
                class_map, problem = self._read(item, paths[0])
                if problem:
                    problems.append(problem)
                else:
                    self.maps[item.id] = class_map
        if problems:
            raise DataError(
                f"{self.setting}={self.folder}: the predicted masks do not match the {len(items)} image(s) "
                "(expected one <id>.png per image, named by its id, of its size, with values 0 background, "
                "1 particle, 2 contour):\n  " + "\n  ".join(problems)
            )

    def __call__(self, item: ImageItem) -> np.ndarray:
        if item.id not in self.maps:
            self.check([item])
        return self.maps[item.id]


CLASSICAL = "classical"


class ClassicalPredictor:
    """The classical baseline (module docstring): segments of `segment_particles`, written as particle class with the
    pixels where two segments meet as contour, so that the instances scored are the watershed's."""

    source, how = CLASSICAL, "classical segmentation (threshold + distance-transform watershed), no training"

    def __init__(self):
        self.polarity: str | None = None

    def check(self, items: Sequence[ImageItem]) -> None:
        from drgan.data.polarity import detect_polarity

        self.polarity = detect_polarity([item.image for item in items]).polarity

    def __call__(self, item: ImageItem) -> np.ndarray:
        from skimage.segmentation import find_boundaries

        from drgan.data.classical import segment_particles

        if self.polarity is None:
            self.check([item])
        labels, _ = segment_particles(item.image, polarity=self.polarity)
        class_map = (labels > 0).astype(np.uint8)
        class_map[find_boundaries(labels, connectivity=1, mode="inner") & (labels > 0)] = 2
        return class_map


def load_predictor(source, inference: Mapping | None = None, setting: str = "model") -> Predictor:
    """The Predictor for what the user named: ``classical`` -> `ClassicalPredictor`; a folder -> ``MaskFolder``; a file
    -> the segmenter checkpoint it holds (``load_segmenter``: read without running code, its class allow-listed) with
    ``inference`` settings. ``setting`` names the key that gave ``source`` in every message."""
    if str(source) == CLASSICAL:
        return ClassicalPredictor()
    path = Path(str(source)).expanduser()
    if path.is_dir():
        return MaskFolder(path, setting)
    if not path.exists():
        raise DataError(f"{setting}={source}: no such file or folder (expected {EXPECTED})")
    from drgan.segmenters.registry import load_segmenter

    return SegmenterPredictor(str(source), load_segmenter(path, setting), inference or {})


def as_predictor(predictor, source: str) -> Predictor:
    """A Predictor as it is; a plain function image -> class map wrapped as one named ``source``."""
    if hasattr(predictor, "check") and hasattr(predictor, "source"):
        return predictor
    if not callable(predictor):
        raise TypeError(f"{source}: expected a Predictor or a function image -> class map, got {predictor!r}")
    return FunctionPredictor(source, predictor)
