"""Which classes a segmenter checkpoint may name: building segmenters from ``_target_`` configs, and loading them back.

A segmenter is configured like any Hydra object, ``model: {_target_: drgan.segmenters.module.SegmenterModule,
depth: 4, ...}``, and ``build_segmenter`` writes the class's dotted name into the module's hyperparameters, so its
checkpoints hold the same node: ``_target_`` beside the keywords the class was built with. ``load_segmenter``
rebuilds that object, so the name inside a file decides which class is constructed. A checkpoint can come from
anyone, and importing a module runs its code, so the name is looked up in an allow-list of segmenter classes and
never imported: a name not on the list is refused (a ConfigError naming it) before any module is imported or any
object built. The class found is called directly with the saved keywords; these are plain values (the file is read
with ``weights_only=True``, drgan.core.checkpoint_io), and a nested ``_target_`` among them stays a dict: Hydra's
``instantiate`` never sees a checkpoint's content.

The allow-list holds
- classes decorated with ``register_segmenter`` in the modules drgan imports for a lookup (``BUILTIN_MODULES``);
  a segmenter added to drgan itself is decorated and its module named there;
- classes that installed packages declare as entry points of the group ``drgan.segmenters``
  (``my_unet = "mypkg.models:MyUNet"``): installing a package is the user's decision, a checkpoint's content is not.
  Only the entry point whose value is the requested name is loaded.

A segmenter class is a LightningModule that calls ``self.save_hyperparameters()`` with plain keyword values (so
that its checkpoint can be rebuilt and read without unpickling code) and maps a (B, 1, H, W) image batch to
(B, C, H, W) class logits (classes 0 background, 1 particle, 2 contour; drgan.segmenters.inference). It may
name the input normalisation its training used in an ``input_normalization`` attribute.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from importlib.metadata import entry_points
from pathlib import Path

from drgan.core.checkpoint_io import load_checkpoint
from drgan.core.errors import ConfigError, DataError
from drgan.core.targets import target_path
from drgan.segmenters.calibrate import stored_pixel_scale, stored_split, stored_working_diameter
from drgan.segmenters.closed_loop import stored_closed_loop
from drgan.segmenters.noise_match import stored_level

__all__ = [
    "ENTRY_POINT_GROUP",
    "build_segmenter",
    "load_segmenter",
    "register_segmenter",
    "registered_segmenters",
    "segmenter_class",
]

ENTRY_POINT_GROUP = "drgan.segmenters"
# Modules whose import registers drgan's own segmenters; a lookup imports them (constant names, never a file's).
BUILTIN_MODULES = ("drgan.segmenters.module", "drgan.segmenters.instances", "drgan.segmenters.star")
EXPECTED = "a segmenter checkpoint written by `python -m drgan.segment`"
# Checkpoints written before the package was named drgan.segmenters name their class by its old module path.
_OLD_PACKAGE, _PACKAGE = "drgan.segmentation.", "drgan.segmenters."

_REGISTRY: dict[str, type] = {}


def register_segmenter(cls: type) -> type:
    """Class decorator: allow checkpoints to name ``cls`` (under ``target_path(cls)``)."""
    if not isinstance(cls, type):
        raise TypeError(f"register_segmenter: expected a class, got {cls!r}")
    _REGISTRY[target_path(cls)] = cls
    return cls


def _import_builtins() -> None:
    for module in BUILTIN_MODULES:
        importlib.import_module(module)


def _from_entry_point(target: str) -> type | None:
    """The class an installed package declares under ``target`` in the ``drgan.segmenters`` group, registered
    now; None when no entry point's value is ``target``. Other entry points are not loaded."""
    for point in entry_points(group=ENTRY_POINT_GROUP):
        if point.value.replace(":", ".").strip() != target:
            continue
        try:
            cls = point.load()
        except Exception as error:
            raise ConfigError(
                f"segmenter entry point {point.name} = {point.value!r} (group {ENTRY_POINT_GROUP}) cannot be loaded: "
                f"{type(error).__name__}: {error}"
            ) from error
        if not isinstance(cls, type):
            raise ConfigError(f"segmenter entry point {point.name} = {point.value!r}: names {cls!r}, not a class")
        _REGISTRY[target] = cls  # the entry point's own spelling, as the lookup asked for it
        return register_segmenter(cls)
    return None


def registered_segmenters() -> list[str]:
    """The allow-listed names: drgan's own, those registered so far and those installed packages declare as entry
    points (read from the packages' metadata, not loaded)."""
    _import_builtins()
    declared = {point.value.replace(":", ".").strip() for point in entry_points(group=ENTRY_POINT_GROUP)}
    return sorted(set(_REGISTRY) | declared)


def segmenter_class(target: object, where: str, note: str = "") -> type:
    """The allow-listed class named ``target``, or a ConfigError that names it (``where``: the setting or file;
    ``note``: added after the name). Nothing that ``target`` names is imported unless it is on the list."""
    _import_builtins()
    if isinstance(target, str) and target.startswith(_OLD_PACKAGE):
        target = _PACKAGE + target.removeprefix(_OLD_PACKAGE)
    cls = _REGISTRY.get(target) if isinstance(target, str) else None
    if cls is None and isinstance(target, str):
        cls = _from_entry_point(target)
    if cls is None:
        raise ConfigError(
            f"{where}: _target_ {target!r} is not an allowed segmenter{note}. Allowed: "
            f"{registered_segmenters()} (a class joins with @drgan.segmenters.registry.register_segmenter in a "
            f"module drgan imports, or as an entry point of the group {ENTRY_POINT_GROUP!r} of an installed package)"
        )
    return cls


def _plain(value) -> bool:
    if value is None or isinstance(value, (bool, int, float, str)):
        return True
    if isinstance(value, (list, tuple)):
        return all(_plain(v) for v in value)
    if isinstance(value, dict):
        return all(isinstance(k, str) and _plain(v) for k, v in value.items())
    return False


def build_segmenter(node, where: str = "model"):
    """The segmenter a ``_target_`` config node describes, built with Hydra's ``instantiate``.

    The node comes from the user's own config, so its module may be imported to find the class; the class must
    then be allow-listed (else its checkpoints could not be loaded back), record every keyword of the node among its
    hyperparameters, as plain values (else its checkpoint could not be rebuilt, or not read without unpickling
    code). The class's name is added to the hyperparameters as ``_target_``, for ``load_segmenter``."""
    from hydra.utils import get_class, instantiate
    from omegaconf import DictConfig, OmegaConf

    settings = OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else dict(node or {})
    target = settings.get("_target_")
    if not target or not isinstance(target, str):
        raise ConfigError(
            f"{where}: no _target_ (expected a segmenter class, e.g. _target_: drgan.segmenters.module.SegmenterModule)"
        )
    try:
        cls = get_class(target)
    except Exception as error:
        raise ConfigError(f"{where}._target_={target}: no such class ({str(error).splitlines()[0]})") from None
    name = target_path(cls)
    if segmenter_class(name, where, "" if name == target else f" (given as {target})") is not cls:
        raise ConfigError(f"{where}._target_={target}: a different class is registered under {name!r}")
    try:
        model = instantiate(settings, _convert_="all")
    except Exception as error:  # Hydra wraps the class's own error (an unknown keyword, a bad value)
        detail = str(error.__cause__ or error).splitlines()[0]
        raise ConfigError(f"{where}._target_={target}: cannot be built from {where}'s keywords ({detail})") from None
    hparams = getattr(model, "hparams", None)
    keywords = [k for k in settings if not k.startswith("_")]
    if not isinstance(hparams, Mapping) or any(k not in hparams for k in keywords):
        raise ConfigError(
            f"{where}._target_={target}: the module does not record its keywords {keywords} with "
            "self.save_hyperparameters(), so its checkpoints could not be rebuilt"
        )
    bad = [k for k, v in hparams.items() if not _plain(v)]
    if bad:
        raise ConfigError(
            f"{where}._target_={target}: hyperparameters {bad} are not plain values (numbers, text, lists, dicts): "
            "a checkpoint holding them could not be read without unpickling code"
        )
    hparams["_target_"] = name
    return model


def load_segmenter(path: str | Path, setting: str = "model"):
    """A trained segmenter from a Lightning checkpoint, in eval mode on the CPU.

    Refuses (DataError) missing files, files that hold code (drgan.core.checkpoint_io: nothing in them runs), files that
    are not checkpoints, checkpoints of other models (e.g. a GAN checkpoint of drgan.train) and weights that do not
    fit the class; a ``_target_`` outside the allow-list is a ConfigError naming it, raised before anything is
    imported or built."""
    checkpoint = load_checkpoint(path, setting, expected=EXPECTED, error=DataError)
    hparams = checkpoint.get("hyper_parameters")
    target = hparams.get("_target_") if isinstance(hparams, dict) else None
    if target is None:
        raise DataError(f"{setting}={path}: not a drgan segmenter checkpoint (expected {EXPECTED})")
    cls = segmenter_class(target, f"{setting}={path}", " (refused: nothing the file names was imported or built)")
    keywords = {k: v for k, v in hparams.items() if not k.startswith("_")}
    try:
        model = cls(**keywords)
        model.load_state_dict(checkpoint["state_dict"])
    except (TypeError, ValueError, RuntimeError, KeyError) as error:
        raise DataError(
            f"{setting}={path}: its {target} cannot be rebuilt from the saved keywords and weights "
            f"({type(error).__name__}: {str(error).splitlines()[0] if str(error) else 'no detail'})"
        ) from None
    model.hparams["_target_"] = target_path(cls)  # as build_segmenter records it: a loaded model saves loadable
    # the touching-particle split drgan.segment chose on the validation pairs (inference split_* = auto reads it)
    model.split_calibration = stored_split(checkpoint, f"{setting}={path}")
    # image px per real px of its training pairs: inference resamples the images it is given by it
    model.pixel_scale = stored_pixel_scale(checkpoint, f"{setting}={path}")
    # the fine-noise level of its generated training images: inference brings cleaner images up to it (None: off)
    model.train_noise = stored_level(checkpoint)
    # its training pairs' median particle diameter (px at the network's scale): pixel_scale=per_image's target
    model.working_diameter = stored_working_diameter(checkpoint)
    # its closed-loop check on held-out generated pairs (drgan.segmenters.closed_loop): reports quote it
    model.closed_loop = stored_closed_loop(checkpoint)
    return model.eval()
