"""From a composed configuration to the objects of the pipeline: meshes, layouts, scene, generator.

Every entry point (render, train, generate) builds through these functions, so one material config
means the same scene everywhere. Inputs are checked here, before any render is spent.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from omegaconf import DictConfig, OmegaConf

from drgan.errors import ConfigError, MeshError, check_keys, setting_float, setting_int
from drgan.resolvers import _USER_TRACKING_URI  # noqa: F401  (the resolvers are registered on import of drgan)
from drgan.scene import layout, meshes
from drgan.scene.parameters import MaterialParameters

if TYPE_CHECKING:
    from drgan.models.generator import BackgroundTexture


def _plain(cfg) -> dict:
    if isinstance(cfg, DictConfig):
        return OmegaConf.to_container(cfg, resolve=True)
    return dict(cfg or {})


def load_particle_meshes(mesh_cfg: Mapping, base_dir: str | Path | None = None) -> list:
    """The material's unit meshes: from ``dir`` when given, else from the procedural generator."""
    mesh_cfg = _plain(mesh_cfg)
    folder = mesh_cfg.get("dir")
    if folder:
        path = Path(folder)
        if not path.is_absolute() and base_dir is not None:
            path = Path(base_dir) / path
        if not path.exists():
            raise MeshError(f"material.meshes.dir={folder}: no such folder or mesh file ({path})")
        return meshes.load_mesh_set(path)
    params = mesh_cfg.get("params") or {}
    count = setting_int("material.meshes.count", mesh_cfg["count"], 1)
    return meshes.generate_meshes(
        mesh_cfg["kind"], count, setting_int("material.meshes.seed", mesh_cfg.get("seed", 0)), **params
    )


IMAGING = ("secondary", "transmission")
# Keys of a secondary-electron material that a transmission material has no use for (it has no BSDFs or lights).
SECONDARY_ONLY = ("particle_bsdf", "stage_bsdf", "scene")


def imaging(material: Mapping) -> str:
    """``material.imaging``: "secondary" (SEM/HIM surface contrast; the default) or "transmission"."""
    material = _plain(material)
    value = material.get("imaging") or "secondary"
    if value not in IMAGING:
        raise ConfigError(f"material.imaging={value!r}: expected one of {', '.join(IMAGING)}")
    if value == "transmission":
        present = [key for key in SECONDARY_ONLY if material.get(key) is not None]
        if present:
            raise ConfigError(
                f"material.{present[0]}: a transmission material (material.imaging=transmission) has no BSDFs, "
                f"stage or lights; remove {', '.join('material.' + key for key in present)} and set "
                "material.transmission {background, absorption, floor}"
            )
    elif material.get("transmission") is not None:
        raise ConfigError(
            f"material.transmission is set but material.imaging={value!r}; set material.imaging=transmission "
            "or remove material.transmission"
        )
    return value


def material_parameters(material: Mapping) -> MaterialParameters:
    material = _plain(material)
    sigma = material.get("noise_sigma", {"value": 0.0})
    if imaging(material) == "transmission":
        if material.get("transmission") is None:
            raise ConfigError(
                "material.transmission: missing; a transmission material needs {background, absorption, floor}"
            )
        return MaterialParameters.from_transmission(material["transmission"], sigma)
    return MaterialParameters.from_config(material.get("particle_bsdf") or {}, material.get("stage_bsdf"), sigma)


def render_settings(material: Mapping, renderer: Mapping):
    """RenderSettings from the renderer group (quality: spp, integrator, ...) and the material (the instrument's blur
    ``filter_stddev``, the view width). Checkpoints saved when the material held spp and the renderer a copy of the
    filter still load: a renderer key wins, the material's spp is the fallback."""
    from drgan.scene.scene import RenderSettings

    material, renderer = _plain(material), _plain(renderer)
    known = ("variant", *(field.name for field in fields(RenderSettings)))
    check_keys("renderer", renderer, sorted(known))
    # Every default lives in RenderSettings: only the keys given here are passed on.
    values = {key: renderer[key] for key in known if key != "variant" and renderer.get(key) is not None}
    for key, fallback in (("resolution", "view_width"), ("spp", "spp"), ("filter_stddev", "filter_stddev")):
        if key not in values and material.get(fallback) is not None:
            values[key] = material[fallback]
    for key in ("resolution", "max_depth"):
        if key in values:
            values[key] = setting_int(f"renderer.{key}", values[key], 1)
    for key in ("filter_stddev", "camera_distance"):
        if key in values:
            values[key] = float(values[key])
    return RenderSettings(**values)


def scene_spec(material: Mapping, renderer: Mapping):
    """SceneSpec (secondary imaging) or TransmissionSpec from the material and renderer groups (imports Mitsuba)."""
    from drgan.scene.scene import SceneSpec, TopLight, TorusLight

    material = _plain(material)
    kind = imaging(material)
    settings = render_settings(material, renderer)
    view_width = setting_float("material.view_width", material.get("view_width", 256))
    if kind == "transmission":
        from drgan.scene.transmission import TransmissionSpec

        return TransmissionSpec(parameters=material_parameters(material), render=settings, view_width=view_width)
    elements = material.get("scene") or {}
    check_keys("material.scene", elements, ("stage", "torus_light", "top_light"), "element")

    def light(cls, key):
        cfg = elements.get(key, {})
        if cfg is None or cfg is False:
            return None
        try:
            return cls(**cfg)
        except TypeError as error:
            raise ConfigError(f"material.scene.{key}: {error}") from None

    return SceneSpec(
        parameters=material_parameters(material),
        render=settings,
        view_width=view_width,
        stage=bool(elements.get("stage", True)),
        torus_light=light(TorusLight, "torus_light"),
        top_light=light(TopLight, "top_light"),
    )


def build_scene(cfg: DictConfig, base_dir: str | Path | None = None):
    """ParticleScene (material.imaging secondary) or TransmissionScene of ``cfg.material`` with ``cfg.renderer``."""
    spec = scene_spec(cfg.material, cfg.renderer)
    unit_meshes = load_particle_meshes(cfg.material.meshes, base_dir)
    n = setting_int("material.n_particles", cfg.material.n_particles, 1)
    if imaging(cfg.material) == "transmission":
        from drgan.scene.transmission import TransmissionScene as Scene
    else:
        from drgan.scene.scene import ParticleScene as Scene
    return Scene(unit_meshes, n, spec, variant=cfg.renderer.get("variant", "auto"))


def noise_grain_px(material: Mapping) -> float:
    """``material.noise_grain_px``: stddev (render px) of the Gaussian that correlates the noise; 0 = white."""
    value = _plain(material).get("noise_grain_px", 0.0)
    if value is None:
        return 0.0
    return setting_float("material.noise_grain_px", value, 0.0)


def build_generator(cfg: DictConfig, base_dir: str | Path | None = None, seed: int = 0):
    import torch

    from drgan.models.generator import Generator

    torch.manual_seed(seed)
    model = cfg.get("model") or {}
    return Generator(
        build_scene(cfg, base_dir),
        hidden=setting_int("model.hidden", model.get("hidden", 128), 1),
        blocks=setting_int("model.blocks", model.get("blocks", 4), 0),
        dropout=setting_float("model.dropout", model.get("dropout", 0.1), 0.0),
        seed=seed,
        noise_grain_px=noise_grain_px(cfg.material),
    )


def build_discriminator(model: Mapping | None):
    """The PatchGAN discriminator of the ``model`` group (``model.discriminator``: filters, n_layers, slope)."""
    from drgan.models.discriminator import PatchDiscriminator

    disc = _plain((model or {}).get("discriminator"))
    return PatchDiscriminator(
        1, int(disc.get("filters", 64)), int(disc.get("n_layers", 3)), float(disc.get("slope", 0.2))
    )


@dataclass(frozen=True)
class LayoutSampler:
    """Constellations Phi for a material: ``sampler(m, seed)`` -> (m, n, 4) with the size distribution and
    placement of the config; with ``n_min`` each constellation shows n_min..n of its n particles."""

    size: layout.SizeDistribution
    placement: layout.Placement
    n: int
    view_width: float
    n_min: int | None = None

    def __call__(self, m: int, seed: int) -> np.ndarray:
        return layout.sample_layouts(
            m, self.n, self.size, self.placement, view_width=self.view_width, seed=seed, n_min=self.n_min
        )


def layout_sampler(cfg: DictConfig) -> LayoutSampler:
    """The LayoutSampler of a composed config (``size``, ``placement``, ``material.n_particles[_min]``, view width)."""
    n, n_min = setting_int("material.n_particles", cfg.material.n_particles, 1), cfg.material.get("n_particles_min")
    if n_min is not None and (isinstance(n_min, bool) or not isinstance(n_min, int) or not 1 <= n_min <= n):
        raise ConfigError(
            f"material.n_particles_min={n_min!r}: expected null or an integer in 1..material.n_particles ({n})"
        )
    return LayoutSampler(
        size=layout.size_from_config(_plain(cfg.size)),
        placement=layout.placement_from_config(_plain(cfg.placement)),
        n=n,
        view_width=setting_float("material.view_width", cfg.material.view_width),
        n_min=n_min,
    )


def sample_phi(cfg: DictConfig, m: int, seed: int) -> np.ndarray:
    """Phi (m, n, 4) for the material with the configured size distribution and placement (`layout_sampler`)."""
    return layout_sampler(cfg)(m, seed)


def textured(material: Mapping) -> bool:
    """Whether the material adds real background texture to the stage (``material.background_texture``)."""
    return bool(_plain(material.get("background_texture")).get("enabled", False))


def texture_highpass_px(material: Mapping) -> float | None:
    """The high-pass width of the material's stage texture (``material.background_texture``); None: untextured."""
    if not textured(material):
        return None
    return float(_plain(material.get("background_texture")).get("highpass_px", 8.0))


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


def background_texture(material: Mapping, patches) -> BackgroundTexture | None:
    """The material's stage texture (``material.background_texture``) from real background patches, or None."""
    return make_background_texture(texture_highpass_px(material), patches)


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
