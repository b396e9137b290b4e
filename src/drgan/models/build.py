"""From a composed configuration to the objects of the pipeline: meshes, layouts, scene, generator.

Every entry point (render, train, generate) builds through these functions, so one material config means the same
scene everywhere. The material is read as a typed, checked `drgan.scene.config.Material`; its ``imaging._target_``
names the scene class (`drgan.scene.protocol`), which builds itself from it. Inputs are checked here, before any
render is spent.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from omegaconf import DictConfig, OmegaConf

from drgan.core import targets
from drgan.core.errors import ConfigError, MeshError, check_keys
from drgan.scene import layout, particle_meshes
from drgan.scene.config import Material, MeshSource, scene_class, typed_material
from drgan.scene.placements import Placement
from drgan.scene.sizes import SizeDistribution

if TYPE_CHECKING:
    from drgan.models.generator import BackgroundTexture
    from drgan.scene.protocol import Scene


def _plain(cfg) -> dict:
    if isinstance(cfg, DictConfig):
        return OmegaConf.to_container(cfg, resolve=True)
    return dict(cfg or {})


def load_particle_meshes(source: MeshSource, base_dir: str | Path | None = None) -> list:
    """The material's unit meshes: from ``source.dir`` when given (relative to ``base_dir``), else procedural."""
    if source.dir:
        path = Path(source.dir)
        if not path.is_absolute() and base_dir is not None:
            path = Path(base_dir) / path
        if not path.exists():
            raise MeshError(f"material.meshes.dir={source.dir}: no such folder or mesh file ({path})")
        return particle_meshes.load_mesh_set(path)
    return particle_meshes.generate_meshes(source.kind, source.count, source.seed, **source.params)


def render_settings(material: Material, renderer: Mapping):
    """RenderSettings from the renderer group (quality: resolution, spp, integrator, ...) and the material (the
    instrument's blur, ``filter_stddev``)."""
    from drgan.scene.scene import RenderSettings

    renderer = _plain(renderer)
    known = ("variant", *(field.name for field in fields(RenderSettings) if field.name != "filter_stddev"))
    check_keys("renderer", renderer, known)
    values = {key: value for key, value in renderer.items() if key != "variant" and value is not None}
    return RenderSettings(**values, filter_stddev=float(material.filter_stddev))


def scene_spec(material: Mapping | Material, renderer: Mapping):
    """The spec of the material's scene (its parameters, render settings, view; no Mitsuba scene is built)."""
    material = typed_material(material)
    return scene_class(material.imaging._target_).spec_from_config(material, render_settings(material, renderer))


def build_scene(cfg: DictConfig, base_dir: str | Path | None = None) -> Scene:
    """The scene of ``cfg.material`` (the class its ``imaging._target_`` names) with ``cfg.renderer``."""
    return material_scene(typed_material(cfg.material), cfg.renderer, base_dir)


def material_scene(material: Material, renderer: Mapping, base_dir: str | Path | None = None) -> Scene:
    """The scene of a typed material with the renderer group ``renderer``."""
    settings = render_settings(material, renderer)
    cls = scene_class(material.imaging._target_)
    unit_meshes = load_particle_meshes(material.meshes, base_dir)
    return cls.from_config(material, settings, unit_meshes, variant=str(renderer.get("variant") or "auto"))


def build_generator(
    cfg: DictConfig, base_dir: str | Path | None = None, seed: int = 0, material: Material | None = None
):
    """The generator of a composed config: the scene of ``cfg.material`` (``material``: it typed already), the FCN of
    ``cfg.model``."""
    import torch

    from drgan.models.generator import Generator

    torch.manual_seed(seed)
    material = typed_material(cfg.material if material is None else material)
    model = cfg.model
    return Generator(
        material_scene(material, cfg.renderer, base_dir),
        hidden=int(model.hidden),
        blocks=int(model.blocks),
        dropout=float(model.dropout),
        seed=seed,
        noise_grain_px=float(material.noise_grain_px),
    )


def build_discriminator(model: Mapping):
    """The discriminator of the ``model`` group: ``model.discriminator``, a ``_target_`` config naming one of the
    allowed classes (the PatchGAN)."""
    from drgan.models.discriminator import PatchDiscriminator

    return targets.build(_plain(model["discriminator"]), [PatchDiscriminator], "model.discriminator")


@dataclass(frozen=True)
class LayoutSampler:
    """Constellations Phi for a material: ``sampler(m, seed)`` -> (m, n, 4) with the size distribution and
    placement of the config; with ``n_min`` each constellation shows n_min..n of its n particles."""

    size: SizeDistribution
    placement: Placement
    n: int
    view_width: float
    n_min: int | None = None

    def __call__(self, m: int, seed: int) -> np.ndarray:
        return layout.sample_layouts(
            m, self.n, self.size, self.placement, view_width=self.view_width, seed=seed, n_min=self.n_min
        )


def layout_sampler(cfg: DictConfig, material: Material | None = None) -> LayoutSampler:
    """The LayoutSampler of a composed config (``size``, ``placement``, ``material.n_particles[_min]``, view width;
    ``material``: ``cfg.material`` typed already)."""
    material = typed_material(cfg.material if material is None else material)
    return LayoutSampler(
        size=layout.size_from_config(_plain(cfg.size)),
        placement=layout.placement_from_config(_plain(cfg.placement)),
        n=material.n_particles,
        view_width=float(material.view_width),
        n_min=material.n_particles_min,
    )


def sample_phi(cfg: DictConfig, m: int, seed: int, material: Material | None = None) -> np.ndarray:
    """Phi (m, n, 4) for the material with the configured size distribution and placement (`layout_sampler`)."""
    return layout_sampler(cfg, material)(m, seed)


def make_background_texture(highpass_px: float | None, patches) -> BackgroundTexture | None:
    """A stage texture from real background patches (k, H, W), or None when ``highpass_px`` is None."""
    from drgan.models.generator import BackgroundTexture

    if highpass_px is None:
        return None
    if patches is None or len(patches) == 0:
        raise ConfigError(
            "material.background_texture.enabled: no real background patches to take the texture from "
            "(set data.n_background > 0 for training, or give generate backgrounds=<run>/patches)"
        )
    return BackgroundTexture(patches, highpass_px)


def optimizer_factory(spec: Mapping, setting: str):
    """An optimiser config (``model.optimizer_g``: ``_target_`` a torch.optim class, ``_partial_: true``, its
    keywords) as a factory ``parameters -> optimizer``, checked now: the class must be a `torch.optim.Optimizer`
    (a config, e.g. one saved in a checkpoint, names no other code to run) and its keywords must build one."""
    import functools

    import torch
    from hydra.utils import get_class

    spec = _plain(spec)
    target = str(spec.get("_target_", ""))
    if not spec.get("_partial_", False):
        raise ConfigError(f"{setting}: expected _partial_: true (the parameters are given when training starts)")
    cls = None
    if target.startswith("torch.optim."):
        try:
            cls = get_class(target)
        except Exception:  # noqa: BLE001  (hydra wraps the import error; the message below says what to give)
            cls = None
    if not (isinstance(cls, type) and issubclass(cls, torch.optim.Optimizer)):
        raise ConfigError(
            f"{setting}._target_={target!r}: expected a torch.optim optimiser class, e.g. torch.optim.Adam"
        )
    keywords = {k: v for k, v in spec.items() if not k.startswith("_")}
    keywords = {k: tuple(v) if isinstance(v, list) else v for k, v in keywords.items()}
    factory = functools.partial(cls, **keywords)
    try:
        factory([torch.nn.Parameter(torch.zeros(1))])
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{setting}: {target}({', '.join(f'{k}={v}' for k, v in keywords.items())}): {err}") from None
    return factory
