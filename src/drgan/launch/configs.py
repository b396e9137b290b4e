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
import re
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


def material_name(stage: str, name, why: str) -> str:
    """``name`` checked as the name of a user's material: a file name of letters, digits, _ or - (its config is
    drgan_conf/material/NAME.yaml) and none of `shipped_materials`; a ConfigError naming ``stage`` and ``why`` the
    name is a material's name otherwise."""
    if not name or not re.fullmatch(r"[A-Za-z0-9_\-]+", str(name)):
        raise ConfigError(
            f"{stage}: name={name!r}: expected a name of letters, digits, _ or - (e.g. name=my_tem): {why} "
            "drgan_conf/material/NAME.yaml"
        )
    if str(name) in shipped_materials():
        raise ConfigError(
            f"{stage}: name={name}: a material drgan ships has that name ({', '.join(shipped_materials())}); {why} "
            f"drgan_conf/material/NAME.yaml and would be confused with it. Choose another name, e.g. name={name}_mine"
        )
    return str(name)


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
