"""Compose drgan's Hydra configs from Python (benchmarks, notebooks, tests) without a ``@hydra.main`` entry point.

    from drgan.launch.configs import compose
    cfg = compose(["material=tio2_sem", "renderer.spp=16"], config_name="train")

The entry points read their configs from the package, so an installed drgan works from any folder. Two roots, one
per family of entry points, so that a key of one family never meets a group of the other (``data=DIR`` is a folder
for drgan.segment but a config group for drgan.train):

- ``drgan/conf/gan/``: train, generate, render, profile, realism, meshes (groups: material, renderer, model, ...);
- ``drgan/conf/segmentation/``: segment, evaluate, analyze, export_nnunet;
- ``drgan/conf/common/``: the groups both use (paths, logger), put in Hydra's ConfigStore by `register_configs`, so
  that every root finds them whatever search path a user gives (``hydra.searchpath=[...]`` replaces the list).

Groups whose values the code reads as typed settings have a schema, registered with Hydra's ConfigStore as
``drgan_schema/<group>`` (a group name no entry point's setting uses) and named first in the group's defaults list
(``- /drgan_schema/renderer@_here_``; a material file: ``- /drgan_schema/material@material`` and its imaging mode's
``- /drgan_schema/imaging/secondary@material.imaging``): a value of the wrong type (``renderer.spp=abc``,
``n_particles: many`` in a material's file) or a key the schema lacks (``sppp: 4``, ``n_particles_mn: 8``) fails
when the config is composed, naming the key, before anything is built. Each schema comes from the typed object the
code reads, the one place a key is declared (its type, its default, its check):

- ``renderer``: derived (`renderer_schema`) from `drgan.scene.render_settings.RenderSettings`, every field that is
  a renderer key (all but the material's ``filter_stddev``), in its order, typed Optional (null = RenderSettings'
  default; drgan.generate's ``renderer``: the checkpoint's) with RenderSettings' default, so a key without a line in
  ``conf/gan/renderer/default.yaml`` composes to it; plus the Mitsuba ``variant``. A new renderer key is one field
  there (tests/test_settings_source.py adds one and checks the YAML's defaults against the fields');
- ``material``: the typed material itself (`drgan.scene.config.Material`, defaults and checks included);
- ``model``: `ModelSchema` below, types only (every field MISSING; the defaults are the group's YAML, the value
  checks in the objects built from it: `drgan.models.gan_module.GANTraining` and `drgan.models.build`).

Nothing is registered on import: `setup` does it (schemas, shared groups, resolvers), called by `compose` and by
every entry point before Hydra composes.
"""

from __future__ import annotations

import dataclasses
import types
import typing
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

from omegaconf import MISSING

from drgan.core.errors import ConfigError

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"


@dataclass
class LRDecaySchema:
    start_step: Optional[int] = MISSING  # noqa: UP045
    steps: int = MISSING
    final_factor: float = MISSING


@dataclass
class DiscriminatorSchema:
    _target_: str = MISSING
    filters: int = MISSING
    n_layers: int = MISSING
    slope: float = MISSING


@dataclass
class ModelSchema:
    """``model``: the FCN, the discriminator and how both learn (`drgan.models.gan_module.GANTraining`)."""

    hidden: int = MISSING
    blocks: int = MISSING
    dropout: float = MISSING
    loss: str = MISSING
    lr_g: float = MISSING
    lr_d: float = MISSING
    betas: list[float] = MISSING
    optimizer_g: dict[str, Any] = MISSING  # `_target_` a torch.optim class, `_partial_: true`, its keywords
    optimizer_d: dict[str, Any] = MISSING
    lr_decay: LRDecaySchema = MISSING
    n_constellations: Optional[int] = MISSING  # noqa: UP045
    max_consecutive_nonfinite: int = MISSING
    discriminator: DiscriminatorSchema = MISSING


def _optional(hint) -> Any:
    """``Optional[X]`` for an annotation ``X`` or ``X | None``: OmegaConf reads typing's Optional at run time, not
    ``X | None``."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        rest = tuple(arg for arg in typing.get_args(hint) if arg is not type(None))
        hint = rest[0] if len(rest) == 1 else typing.Union[rest]  # noqa: UP007
    return Optional[hint]  # noqa: UP045


def given(cfg, key: str, why: str):
    """``cfg[key]``, or a ConfigError saying ``why`` where the key is absent, null or empty (a required setting)."""
    value = cfg.get(key) if cfg is not None else None
    if value is None or value == "":
        raise ConfigError(why)
    return value


_REQUIRED = object()  # `setting`'s default where a key has none


def setting(default: Any = _REQUIRED, *, ge: float | None = None, gt: float | None = None, expected: str | None = None,
            check=None):  # fmt: skip
    """A settings field with its default (none: a required key) and what `read_settings` checks: bounds
    (``expected``: the words of the error, else derived from the type and the bounds), or ``check(stage, value)``,
    which returns the typed value or raises a ConfigError itself."""
    import dataclasses

    metadata = {"ge": ge, "gt": gt, "expected": expected, "check": check}
    if default is _REQUIRED:
        return dataclasses.field(metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def read_settings(cls: type, cfg, stage: str, *, prefix: str = "", **resolved):
    """A stage's typed settings ``cls`` (a dataclass) from its composed config ``cfg``, the one way drgan types a
    stage's keys: ``resolved`` fields as the stage's own checks made them (folders, merged lists), every other field
    read from the key of its name (absent: the field's default), checked against the field's type and bounds
    (`setting`); a ConfigError naming ``stage``, the key (after ``prefix``, e.g. ``data.``) and what was expected
    otherwise. An empty string in a field that may be null is null (``model=`` on a command line)."""
    import dataclasses

    from omegaconf import DictConfig, ListConfig, OmegaConf

    hints = typing.get_type_hints(cls)
    values = dict(resolved)
    for f in dataclasses.fields(cls):
        if f.name in resolved or not f.init:
            continue
        where = f"{stage}: {prefix}{f.name}"
        if cfg is None or f.name not in cfg:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(f"{where} is not set")
            continue
        raw = cfg[f.name]
        if isinstance(raw, (DictConfig, ListConfig)):
            raw = OmegaConf.to_container(raw, resolve=True)
        check = f.metadata.get("check")
        values[f.name] = check(stage, raw) if check else _checked(raw, hints[f.name], f.metadata, where)
    return cls(**values)


def _checked(value, hint, bounds, where: str):
    ok, typed = _as_type(value, hint)
    low, above = bounds.get("ge"), bounds.get("gt")
    if ok and isinstance(typed, (int, float)) and not isinstance(typed, bool):
        ok = (low is None or typed >= low) and (above is None or typed > above)
    if not ok:
        limit = f" >= {low:g}" if low is not None else f" > {above:g}" if above is not None else ""
        raise ConfigError(f"{where}={value!r}: expected {bounds.get('expected') or _describe(hint) + limit}")
    return typed


def _as_type(value, hint) -> tuple[bool, Any]:
    """(whether ``value`` is of the annotation ``hint``, the value as that type)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any:
        return True, value
    if origin in (typing.Union, types.UnionType):
        if type(None) in args and (value is None or value == ""):
            return True, None
        for arm in (a for a in args if a is not type(None)):
            ok, typed = _as_type(value, arm)
            if ok:
                return True, typed
        return False, value
    if hint is bool:
        return isinstance(value, bool), value
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool), value
    if hint is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        return ok, float(value) if ok else value
    if hint is str:
        return isinstance(value, str), value
    if hint is Path:
        return isinstance(value, (str, Path)), Path(str(value))
    if origin is tuple and isinstance(value, (list, tuple)):
        arms = [args[0]] * len(value) if len(args) == 2 and args[1] is Ellipsis else list(args)
        if len(arms) != len(value):
            return False, value
        items = [_as_type(v, arm) for v, arm in zip(value, arms)]
        return all(ok for ok, _ in items), tuple(typed for _, typed in items)
    if hint is dict or origin is dict:
        return isinstance(value, dict), dict(value) if isinstance(value, dict) else value
    if origin is tuple:
        return False, value
    raise TypeError(f"read_settings: no check for the annotation {hint!r}")


def _describe(hint) -> str:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        words = [_describe(a) for a in args if a is not type(None)]
        return " or ".join(words) + (" or null" if type(None) in args else "")
    names = {bool: "true or false", int: "an integer", float: "a number", str: "a string", Path: "a path",
             dict: "a mapping"}  # fmt: skip
    if origin is tuple:
        return f"a list of {len(args)}" if args and args[-1] is not Ellipsis else "a list"
    return names.get(hint, names.get(origin, str(hint)))


def renderer_schema(overrides: bool = False) -> type:
    """``renderer``: the Mitsuba ``variant`` (``auto``; drgan.core.backend's choices), then every renderer key of
    `drgan.scene.render_settings.RenderSettings` (`renderer_fields`: its type, Optional, and its default). Every
    key may be null (= RenderSettings' default), so that generate's overrides can merge over a preset a material
    picks. ``overrides``: drgan.generate's ``renderer``, every key default null (= the checkpoint's).

    RenderSettings is looked up when called (by `setup`), so a class put in its place is the schema."""
    from drgan.scene import render_settings

    settings = render_settings.RenderSettings
    hints = typing.get_type_hints(settings)
    fields = [("variant", Optional[str], dataclasses.field(default=None if overrides else "auto"))]  # noqa: UP045
    for key in render_settings.renderer_fields(settings):
        if overrides:
            default = dataclasses.field(default=None)
        elif key.default_factory is not dataclasses.MISSING:
            default = dataclasses.field(default_factory=key.default_factory)
        else:
            default = dataclasses.field(default=key.default)
        fields.append((key.name, _optional(hints[key.name]), default))
    return dataclasses.make_dataclass("RendererOverrides" if overrides else "RendererSchema", fields)


def schemas() -> dict[str, type]:
    """The typed groups: ConfigStore name under ``drgan_schema/`` -> dataclass."""
    from drgan.scene import config

    return {
        "renderer": renderer_schema(),
        "renderer_overrides": renderer_schema(overrides=True),
        "model": ModelSchema,
        "material": config.Material,
        "imaging/secondary": config.SecondaryImaging,
        "imaging/transmission": config.TransmissionImaging,
        "imaging/official": config.OfficialImaging,
    }


def setup() -> None:
    """Register drgan's config resolvers, the schemas (`schemas`) and the shared groups of ``conf/common/`` with
    Hydra's ConfigStore (idempotent): what composing any of drgan's configs needs."""
    from hydra.core.config_store import ConfigStore
    from omegaconf import OmegaConf

    from drgan.core.resolvers import register_resolvers

    # The configs put ./drgan_conf (users' own materials, e.g. from `python -m drgan.profile`) on Hydra's search
    # path; Hydra warns on every run in a folder that has none, which is the usual case and nothing to act on.
    warnings.filterwarnings("ignore", message=r"provider=hydra\.searchpath in main, path=drgan_conf is not available")
    register_resolvers()
    store = ConfigStore.instance()
    for name, schema in schemas().items():
        group, _, leaf = f"drgan_schema/{name}".rpartition("/")
        store.store(group=group, name=leaf, node=schema)
    for path in sorted((CONF_DIR / "common").glob("*/*.yaml")):
        store.store(group=path.parent.name, name=path.stem, node=OmegaConf.load(path))


ROOTS = ("gan", "segmentation")


def shipped_materials() -> list[str]:
    """The names of the materials drgan ships (conf/gan/material/NAME.yaml): a user's material of the same name would
    be shadowed by, or shadow, the shipped one on Hydra's search path, so no user material may take one."""
    return sorted(p.stem for p in (CONF_DIR / "gan" / "material").glob("*.yaml"))


def conf_dir(root: str = "gan") -> Path:
    """The config root ``root`` (one of `ROOTS`); a clear error when the package was installed without its configs."""
    if root not in ROOTS:
        raise ConfigError(f"config root {root!r}: expected one of {ROOTS}")
    folder = CONF_DIR / root
    if not any(folder.glob("*.yaml")):
        raise ConfigError(
            f"drgan's config folder {folder} has no configs: the package was installed without them "
            "(reinstall it: `pip install .` from a checkout includes drgan/conf)"
        )
    return folder


def config_root(config_name: str) -> Path:
    """The root that holds the primary config ``config_name`` (e.g. "train", "segment")."""
    folders = [conf_dir(root) for root in ROOTS]
    for folder in folders:
        if (folder / f"{config_name}.yaml").is_file():
            return folder
    names = sorted(p.stem for folder in folders for p in folder.glob("*.yaml"))
    raise ConfigError(f"config_name={config_name!r}: expected one of {names}")


def compose(overrides: Sequence[str] = (), config_name: str = "render"):
    """The composed config ``config_name`` (e.g. "render", "train", "segment") with Hydra ``overrides`` applied.

    Works inside a running Hydra app too (an entry point composing a parent material): Hydra's global state is
    set aside for the call and restored after it."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.initialize import get_gh_backup, restore_gh_from_backup

    setup()
    if isinstance(overrides, str):
        raise ConfigError(f"overrides={overrides!r}: expected a list of strings such as ['renderer.spp=16']")
    running = get_gh_backup() if GlobalHydra.instance().is_initialized() else None
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(version_base="1.3", config_dir=str(config_root(config_name))):
            return hydra_compose(config_name=config_name, overrides=list(overrides))
    finally:
        if running is not None:
            restore_gh_from_backup(running)
