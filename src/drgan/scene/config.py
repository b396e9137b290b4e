"""The material, typed: what a ``material`` config group may hold, checked when a config is composed.

These dataclasses are the schema Hydra merges every material file into (registered by `drgan.launch.configs.setup`), so a
misspelt key (``n_particles_mn: 8``) or a value of the wrong type (``n_particles: many``) fails at compose time,
naming it. `typed_material` turns a composed or saved ``material`` node into a checked `Material` object, which is
what the code reads: no ``.get(key, default)`` on raw mappings, each default once, here.

``material.imaging`` is the scene's own config: its ``_target_`` names the scene class (registered with
`register_scene` below; the interface: `drgan.scene.protocol.Scene`), the rest are that class's settings, typed by its ``Config`` dataclass
(`SecondaryImaging`, `TransmissionImaging`, or a user's). Nothing here imports Mitsuba.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Dict, List, Optional  # noqa: UP035  (OmegaConf reads these annotations at run time)

from omegaconf import MISSING

from drgan.core.errors import ConfigError
from drgan.core.targets import target_path
from drgan.scene.parameters import MaterialParameters, Parameter, noise_parameter, parse_parameter

POLARITIES = ("bright", "dark")
LIGHT_SHAPES = ("band", "torus")

# Principled-BSDF parameters (Mitsuba's names) that may be learned or fixed. base_color is grey: the
# microscope images have one channel.
PRINCIPLED_PARAMETERS = (
    "base_color",
    "roughness",
    "metallic",
    "specular",
    "spec_tint",
    "sheen",
    "sheen_tint",
    "clearcoat",
    "clearcoat_gloss",
    "anisotropic",
    "spec_trans",
)


# Optional[...] rather than `X | None` in the dataclasses below: OmegaConf reads their annotations at run time.
@dataclass
class ParameterRange:
    """One scalar of the scene: learned within ``{min, max}`` (the FCN's sigmoid is rescaled into them) or fixed
    at ``{value}`` (or a bare number). A material that fixes a parameter its parent learns writes ``{value: v}``;
    Hydra merges that into ``{min, max, value}`` and the value wins.

    The material's parameter settings are typed ``Any`` rather than ``ParameterRange``: OmegaConf refuses a mapping
    or a number added from the command line (``+material.imaging.particle_bsdf.metallic={min: 0, max: 1}``,
    ``material.noise_sigma=0.05``) into a structured value. `typed_material` checks them all instead
    (`drgan.scene.parameters.parse_parameter`), before anything is built."""

    min: Optional[float] = None  # noqa: UP045
    max: Optional[float] = None  # noqa: UP045
    value: Optional[float] = None  # noqa: UP045


@dataclass
class MeshSource:
    """``material.meshes``: a folder of PLY/OBJ/STL meshes (``dir``), else ``count`` procedural meshes of ``kind``
    (`drgan.scene.particle_meshes.generate_meshes`, keywords in ``params``)."""

    kind: str = "sphere"
    count: int = 20
    seed: int = 0
    dir: Optional[str] = None  # noqa: UP045
    params: Dict[str, Any] = field(default_factory=dict)  # noqa: UP006


@dataclass
class TextureSettings:
    """``material.background_texture``: the fine texture of real background patches (each minus its Gaussian blur
    of ``highpass_px``) added to the background pixels of every synthetic image. A constant: no gradient or label
    changes; needs real background patches (data.n_background > 0 in training, the run's patches/ in generate)."""

    enabled: bool = False
    highpass_px: float = 8.0


@dataclass
class TorusLight:
    """Ring-shaped area light around the stage (SEM/HIM detectors collect electrons from the side). Lengths are
    multiples of the view width."""

    radiance: float = 1.0
    # A ring at 45 degrees seen from the view centre (the paper's): it puts the real TiO2 SEM background grey (0.13)
    # mid-range of the paper's stage limits. A weaker ring drives every learned value to its upper limit.
    major_radius: float = 1.0
    minor_radius: float = 0.3
    height: float = 1.0  # centre above the stage
    # Emitting surface: "band", a conical strip of width 2 x minor_radius facing the view centre, or "torus", the
    # paper's tube. Same ring of directions; the band wastes no light samples on surface facing away, so a
    # light-sampling integrator renders the particles with less Monte Carlo noise (`torus_light_mesh`).
    shape: str = "band"
    segments: int = 128  # around the ring

    def __post_init__(self):
        if self.shape not in LIGHT_SHAPES:
            raise ConfigError(
                f"material.imaging.torus_light.shape={self.shape!r}: expected one of {', '.join(LIGHT_SHAPES)}"
            )
        for name in ("radiance", "major_radius", "minor_radius", "height"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ConfigError(f"material.imaging.torus_light.{name}={value!r}: expected a finite number >= 0")
        if self.minor_radius >= self.major_radius:
            raise ConfigError(
                f"material.imaging.torus_light.minor_radius={self.minor_radius} must be < major_radius={self.major_radius}"
            )
        if int(self.segments) < 8:
            raise ConfigError(f"material.imaging.torus_light.segments={self.segments}: expected >= 8")


@dataclass
class TopLight:
    """Rectangle area light above the camera, facing down; lengths are multiples of the camera's height."""

    radiance: float = 0.1
    size: float = 1.0  # half side
    height: float = 1.1


class ImagingConfig:
    """What every ``material.imaging`` dataclass gives: its scene's parameters, in the FCN's output order, and
    whether its renders are free of Monte Carlo grain (``noiseless``: then all of an image's noise is the
    detector's, which a real image's background shows, and `drgan.profile` bounds the learned noise by it), and
    whether it renders an edge fringe (``renders_fringe``: it has a ``fringe`` key, `EdgeFringe`, which
    `drgan.profile` sets when it measures a fringe at the particles' edges)."""

    noiseless: ClassVar[bool] = False
    renders_fringe: ClassVar[bool] = False

    def scene_parameters(self) -> tuple[Parameter, ...]:
        raise NotImplementedError

    def material_parameters(self, noise_sigma=None) -> MaterialParameters:
        """The scene's parameters and the noise sigma (a `ParameterRange` or mapping; None: no noise)."""
        return MaterialParameters(self.scene_parameters(), noise_parameter(noise_sigma))


@dataclass
class SecondaryImaging(ImagingConfig):
    """``material.imaging`` of secondary-electron contrast (SEM, HIM): Principled BSDFs on particles and stage,
    a ring light and a top light (`drgan.scene.scene.ParticleScene`). ``torus_light: null`` / ``top_light: null``
    leave a light out; ``stage: false`` the stage."""

    _target_: str = "drgan.scene.scene.ParticleScene"
    stage: bool = True
    torus_light: Optional[TorusLight] = field(default_factory=TorusLight)  # noqa: UP045
    top_light: Optional[TopLight] = field(default_factory=TopLight)  # noqa: UP045
    # Principled-BSDF parameters by name ({min, max}, {value} or a number; `ParameterRange`), in the FCN's output
    # order (stage first, then particles).
    particle_bsdf: Dict[str, Any] = field(default_factory=dict)  # noqa: UP006
    stage_bsdf: Dict[str, Any] = field(default_factory=dict)  # noqa: UP006
    # Secondary electrons recaptured: the share of those a surface emits towards another surface that the detector
    # loses (drgan.scene.direct, `escape`): crevices and the necks between touching particles image darker, as SEM
    # contacts do. 0: none (the images of before). Needs renderer.integrator=direct_light or direct_light_mis.
    recapture: float = 0.0

    def __post_init__(self):
        check_recapture(self.recapture)

    def scene_parameters(self) -> tuple[Parameter, ...]:
        """The stage's, then the particles' BSDF parameters (the reference implementation's order)."""
        if not self.stage and self.stage_bsdf:
            raise ConfigError("material.imaging.stage_bsdf is set but material.imaging.stage is false; remove one")
        return principled_parameters(self.stage_bsdf, self.particle_bsdf)


def check_recapture(value) -> None:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and 0.0 <= value <= 1.0):
        raise ConfigError(f"material.imaging.recapture={value!r}: expected a share in [0, 1] (0: none)")


def principled_parameters(stage_bsdf: Mapping, particle_bsdf: Mapping) -> tuple[Parameter, ...]:
    """The stage's, then the particles' Principled-BSDF parameters, each table in its own order."""
    params = []
    for surface, table in (("stage", stage_bsdf), ("particle", particle_bsdf)):
        for name, spec in (table or {}).items():
            if name not in PRINCIPLED_PARAMETERS:
                raise ConfigError(
                    f"material.imaging.{surface}_bsdf.{name}: unknown Principled-BSDF parameter; expected one of "
                    f"{', '.join(PRINCIPLED_PARAMETERS)}"
                )
            params.append(parse_parameter(surface, name, spec, f"material.imaging.{surface}_bsdf.{name}"))
    return tuple(params)


@dataclass
class OfficialImaging(ImagingConfig):
    """``material.imaging`` of the official DiffRenderGAN scene (`drgan.scene.official.OfficialScene`), as
    `drgan.import_official` writes it from an official experiment: the official stage and light meshes, its camera
    (perspective, 40 degrees, 6 units above the particles' plane) and its units. A constellation row is
    (x, y, z, r) in layout units (`drgan.scene.placements.OfficialPlacement`): the particle's file mesh, scaled by
    r x ``mesh_scale`` about the file's origin, sits at (x, y, z) x ``mesh_unit`` (z up, towards the camera)."""

    _target_: str = "drgan.scene.official.OfficialScene"
    mesh_unit: float = MISSING  # scene length of one layout unit (official mesh_unit)
    mesh_scale: float = MISSING  # a mesh file's scale at r = 1 (official mesh_scale)
    # Per mesh of material.meshes.dir (sorted by file name): the centre of its file's bounding box (x, y, z) and its
    # largest extent, in file units (`drgan.scene.particle_meshes.mesh_frame`): the loader normalises meshes, this
    # undoes it.
    mesh_frames: List[List[float]] = MISSING  # noqa: UP006
    stage_mesh: str = MISSING  # the official stage.ply (its placement is the official scene's)
    ring_light_mesh: str = MISSING  # light_source.ply: the ring light around the scene
    top_light_mesh: str = MISSING  # light_source2.ply: the light above the camera
    ring_radiance: float = 1.0  # official emission1
    top_radiance: float = 0.1  # official emission2
    particle_bsdf: Dict[str, Any] = field(default_factory=dict)  # noqa: UP006  (as SecondaryImaging's)
    stage_bsdf: Dict[str, Any] = field(default_factory=dict)  # noqa: UP006
    recapture: float = 0.0  # as SecondaryImaging's (the paper's scene has none)

    def __post_init__(self):
        check_recapture(self.recapture)
        for name in ("mesh_unit", "mesh_scale"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ConfigError(f"material.imaging.{name}={value!r}: expected a finite number > 0")
        for frame in self.mesh_frames:
            if len(frame) != 4 or not frame[3] > 0:
                raise ConfigError(
                    f"material.imaging.mesh_frames: {list(frame)}: expected [centre x, y, z, largest extent > 0]"
                )

    def scene_parameters(self) -> tuple[Parameter, ...]:
        """The stage's, then the particles' BSDF parameters: the official network's output order."""
        return principled_parameters(self.stage_bsdf, self.particle_bsdf)


@dataclass
class EdgeFringe:
    """``material.imaging.fringe`` of a transmission material: the bright or dark ring that defocus puts at the
    particles' edges in TEM bright field (a Fresnel fringe), `drgan.scene.transmission.edge_fringe`. In the
    weak-phase picture defocus adds a term proportional to the Laplacian of the projected sample; the scene adds
    ``amplitude`` x w^2 / phi(1) x Laplacian(G_w * contrast) to the grey, where contrast is the rendered darkening
    (background minus grey) and phi(1) = 0.242 scales the ring outside a straight edge to a peak of ``amplitude``
    (in units of the particle's contrast at its edge) at w px from it, with the opposite ring w px inside.

    ``amplitude`` (a `ParameterRange`, signed): > 0 a ring of the opposite grey to the particles just outside them
    (bright around dark particles: underfocus), < 0 a ring like the particles (overfocus). ``width_px``: w, the
    Gaussian's stddev in px of the real image (> 0). Written by `drgan.profile` only when it measured a fringe."""

    amplitude: Any = MISSING
    width_px: float = MISSING

    def __post_init__(self):
        if not (isinstance(self.width_px, (int, float)) and math.isfinite(self.width_px) and self.width_px > 0):
            raise ConfigError(
                f"material.imaging.fringe.width_px={self.width_px!r}: expected a finite number > 0 (px of the real "
                "image: the Gaussian stddev of the fringe)"
            )

    def parameter(self) -> Parameter:
        """The amplitude, learned or fixed (signed: a negative amplitude is a ring like the particles)."""
        return parse_parameter(
            "transmission", "fringe_amplitude", self.amplitude, "material.imaging.fringe.amplitude", minimum=None
        )


def fringe_setting(value) -> EdgeFringe | None:
    """``material.imaging.fringe`` as an `EdgeFringe` (None: no fringe); unknown or missing keys are ConfigErrors
    naming them."""
    if value is None or isinstance(value, EdgeFringe):
        return value
    if not isinstance(value, Mapping):
        raise ConfigError(
            f"material.imaging.fringe={value!r}: expected null or {{amplitude: {{min, max}} or {{value}}, width_px}}"
        )
    keys = [f.name for f in dataclasses.fields(EdgeFringe)]
    for key in value:
        if key not in keys:
            raise ConfigError(f"material.imaging.fringe.{key}: unknown key; expected {', '.join(keys)}")
    for key in keys:
        if value.get(key) is None or value.get(key) == MISSING:
            raise ConfigError(f"material.imaging.fringe.{key}: missing (the fringe needs {', '.join(keys)})")
    width = value["width_px"]
    if isinstance(width, bool) or not isinstance(width, (int, float)):
        raise ConfigError(f"material.imaging.fringe.width_px={width!r}: expected a number of px > 0")
    return EdgeFringe(amplitude=value["amplitude"], width_px=float(width))


@dataclass
class TransmissionImaging(ImagingConfig):
    """``material.imaging`` of transmission contrast (TEM, STEM bright field, transmission SEM): dark particles on
    a bright film, no lights or BSDFs (`drgan.scene.transmission.TransmissionScene`). ``background``: grey of the
    bare film; ``absorption``: attenuation per px of path length inside a particle; ``floor``: grey behind an
    opaque particle (a detector offset; fixed at 0 unless set); ``fringe``: the defocus fringe at the edges
    (`EdgeFringe`; null: none, the default)."""

    _target_: str = "drgan.scene.transmission.TransmissionScene"
    noiseless: ClassVar[bool] = True  # path lengths through the particles: no sampling
    renders_fringe: ClassVar[bool] = True
    background: Any = MISSING  # each a `ParameterRange`: {min, max}, {value} or a number
    absorption: Any = MISSING
    floor: Any = None  # null: fixed at 0, a detector without offset
    # null: no fringe term and no parameter; else {amplitude, width_px} (`EdgeFringe`). Typed Any, as the
    # parameter ranges are: OmegaConf refuses a mapping given on the command line to a structured value that is
    # null (``material.imaging.fringe={amplitude: {min: 0, max: 0.3}, width_px: 1.5}``); checked below instead.
    fringe: Any = None

    def __post_init__(self):
        self.fringe = fringe_setting(self.fringe)

    def scene_parameters(self) -> tuple[Parameter, ...]:
        """background, absorption, floor, then the fringe's amplitude when there is a fringe: the FCN's order."""
        floor = self.floor if self.floor is not None else 0.0
        params = tuple(
            parse_parameter("transmission", name, spec, f"material.imaging.{name}")
            for name, spec in (("background", self.background), ("absorption", self.absorption), ("floor", floor))
        )
        return params + ((self.fringe.parameter(),) if self.fringe is not None else ())


@dataclass
class Material:
    """A ``material`` config: particles (meshes, count, size), the imaging mode (``imaging``, the scene's config)
    and the detector's noise. Sizes and widths are in px of the real image."""

    name: str = MISSING
    made_for: Optional[str] = None  # noqa: UP045  (what images it was made for: shown when data.dir is not set)
    polarity: str = "bright"  # bright: particles brighter than the background; dark: darker
    # The real particles' arrangement, Clark-Evans ratio of their centroids as drgan.profile measured it (< 1
    # clustered, 1 random, > 1 regular); null: not measured. Renders ignore it: it tells a segmenter trained on the
    # material's pairs whether touching particles are agglomerates (drgan.segment, model.contact_weight=auto).
    clark_evans: Optional[float] = None  # noqa: UP045
    n_particles: int = MISSING
    n_particles_min: Optional[int] = None  # noqa: UP045  (null: every scene holds n_particles; k: k..n_particles)
    view_width: int = 256  # px of the real image seen by the camera (= the training window)
    particle_size_px: float = MISSING  # typical largest extent (the size groups scale with it)
    size_spread: float = 0.25  # relative spread of sizes (lognormal sigma; normal std / mean)
    contour_px: int = 1  # width of the contour class in masks
    filter_stddev: float = 0.5  # px: the instrument's blur (the render's reconstruction filter)
    noise_sigma: Any = None  # the detector's noise, a `ParameterRange`; null: none
    noise_grain_px: float = 0.0  # stddev (render px) of the noise's spatial correlation; 0 = white noise
    background_texture: TextureSettings = field(default_factory=TextureSettings)
    meshes: MeshSource = field(default_factory=MeshSource)
    imaging: Any = MISSING  # the scene's config: _target_ names its class, the rest is typed by that class's Config

    def __post_init__(self):
        if self.polarity not in POLARITIES:
            raise ConfigError(f"material.polarity={self.polarity!r}: expected one of {', '.join(POLARITIES)}")
        if self.clark_evans is not None and not (math.isfinite(self.clark_evans) and self.clark_evans > 0):
            raise ConfigError(f"material.clark_evans={self.clark_evans}: expected null or a finite number > 0")
        if self.n_particles < 1:
            raise ConfigError(f"material.n_particles={self.n_particles}: expected >= 1")
        if self.n_particles_min is not None and not 1 <= self.n_particles_min <= self.n_particles:
            raise ConfigError(
                f"material.n_particles_min={self.n_particles_min}: expected null or an integer in "
                f"1..material.n_particles ({self.n_particles})"
            )
        for key in ("view_width", "particle_size_px", "filter_stddev"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"material.{key}={value}: expected a finite number > 0")
        for key in ("size_spread", "noise_grain_px"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"material.{key}={value}: expected a finite number >= 0")
        if self.contour_px < 0:
            raise ConfigError(f"material.contour_px={self.contour_px}: expected >= 0")
        if self.meshes.count < 1:
            raise ConfigError(f"material.meshes.count={self.meshes.count}: expected >= 1")
        if self.background_texture.enabled and not self.background_texture.highpass_px > 0:
            raise ConfigError(
                f"material.background_texture.highpass_px={self.background_texture.highpass_px}: expected > 0 (px)"
            )

    @property
    def texture_highpass_px(self) -> float | None:
        """The high-pass width of the background texture; None for an untextured material."""
        return self.background_texture.highpass_px if self.background_texture.enabled else None


# -- the scene registry ----------------------------------------------------------------------------------
# The scene classes a config may name (an allow-list): drgan's own, those registered in this process, and those an
# installed package declares as entry points of the group ENTRY_POINT_GROUP (`name = "module:Class"`; loaded only
# when a config names exactly that class, so a user's imaging mode works from every CLI and in checkpoints).
# drgan's own, by import path -> (module, Config): their modules import Mitsuba, so they are imported when a config
# first needs the class, not when configs are checked.
ENTRY_POINT_GROUP = "drgan.scenes"
BUILTIN_SCENES = {
    SecondaryImaging._target_: ("drgan.scene.scene", SecondaryImaging),
    TransmissionImaging._target_: ("drgan.scene.transmission", TransmissionImaging),
    OfficialImaging._target_: ("drgan.scene.official", OfficialImaging),
}
_REGISTERED: dict[str, type] = {}


def register_scene(cls: type) -> type:
    """Allow configs to name scene class ``cls`` (use as a class decorator). It needs a ``Config`` dataclass whose
    ``_target_`` defaults to the class's import path, a ``from_config`` classmethod, and the `Scene` members."""
    target = target_path(cls)
    config = getattr(cls, "Config", None)
    if not (isinstance(config, type) and dataclasses.is_dataclass(config)):
        raise ConfigError(f"register_scene({target}): expected a Config dataclass on the class (its imaging keys)")
    default = {f.name: f.default for f in dataclasses.fields(config)}.get("_target_")
    if default != target:
        raise ConfigError(
            f"register_scene({target}): {config.__name__}._target_ defaults to {default!r}, not {target!r}"
        )
    missing = [
        name for name in ("from_config", "set_layout", "render", "instance_labels", "learned") if not hasattr(cls, name)
    ]
    if missing:
        raise ConfigError(
            f"register_scene({target}): the class lacks {', '.join(missing)} (drgan.scene.protocol.Scene)"
        )
    _REGISTERED[target] = cls
    return cls


def _declared() -> dict[str, object]:
    """Entry points of ENTRY_POINT_GROUP by the import path they name (read from package metadata, not loaded)."""
    from importlib.metadata import entry_points

    return {point.value.replace(":", ".").strip(): point for point in entry_points(group=ENTRY_POINT_GROUP)}


def registered_scenes() -> Sequence[str]:
    """Every scene class a config may name: drgan's, those registered, those installed packages declare."""
    return sorted({*BUILTIN_SCENES, *_REGISTERED, *_declared()})


def _unknown(target: str) -> ConfigError:
    return ConfigError(
        f"material.imaging._target_={target!r}: not a registered scene class; expected one of "
        f"{', '.join(registered_scenes())} (a scene class of your own: drgan.scene.config.register_scene, and an "
        f"entry point of the group {ENTRY_POINT_GROUP!r} so that every drgan command finds it)"
    )


def _load_declared(target: str) -> None:
    """Load the entry point that names ``target`` (its class registers itself, or is registered here)."""
    point = _declared().get(target)
    if point is None:
        return
    try:
        cls = point.load()
    except Exception as error:
        raise ConfigError(
            f"scene entry point {point.name} = {point.value!r} (group {ENTRY_POINT_GROUP}) cannot be loaded: "
            f"{type(error).__name__}: {error}"
        ) from error
    if target not in _REGISTERED:
        register_scene(cls)


def imaging_config(target: str) -> type:
    """The ``Config`` dataclass of the scene class ``target`` names (without importing drgan's scene modules)."""
    if target in BUILTIN_SCENES:
        return BUILTIN_SCENES[target][1]
    if target not in _REGISTERED:
        _load_declared(target)
    if target in _REGISTERED:
        return _REGISTERED[target].Config
    raise _unknown(target)


def scene_class(target: str) -> type:
    """The registered scene class ``target`` names (drgan's own are imported on first use)."""
    if target not in _REGISTERED and target in BUILTIN_SCENES:
        importlib.import_module(BUILTIN_SCENES[target][0])  # its classes register themselves
    if target not in _REGISTERED:
        _load_declared(target)
    if target not in _REGISTERED:
        raise _unknown(target)
    return _REGISTERED[target]


def typed_material(node: Any) -> Material:
    """``material`` (a composed config node, or the plain mapping a checkpoint saved) as a checked `Material`.

    The imaging node is typed by the ``Config`` of the scene class its ``_target_`` names (an allow-list: only
    registered scene classes, `register_scene`); unknown keys and wrong types are ConfigErrors naming the
    key, and the dataclasses' own checks run (ranges, polarity)."""
    from omegaconf import DictConfig, OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    if isinstance(node, Material):
        return node
    if isinstance(node, DictConfig):
        node = OmegaConf.to_container(node, resolve=True)
    if not isinstance(node, Mapping):
        raise ConfigError(f"material: expected a mapping (a material config), got {type(node).__name__}")
    imaging = node.get("imaging")
    if not isinstance(imaging, Mapping) or not imaging.get("_target_"):
        raise ConfigError(
            "material.imaging._target_: missing; a material names its scene class, e.g. "
            f"{SecondaryImaging._target_} (secondary electrons) or {TransmissionImaging._target_} (transmission). "
            "A checkpoint or dataset written before materials named their scene class cannot be read: train anew"
        )
    schema = OmegaConf.structured(Material)
    schema.imaging = OmegaConf.structured(imaging_config(str(imaging["_target_"])))
    try:
        material = OmegaConf.to_object(OmegaConf.merge(schema, node))
    except OmegaConfBaseException as error:
        key = getattr(error, "full_key", None)
        message = str(error).splitlines()[0]
        raise ConfigError(f"material.{key}: {message}" if key else f"material: {message}") from None
    material.imaging.material_parameters(material.noise_sigma)  # every limit checked now, before anything is built
    return material
