"""Material parameters: which scene values and noise level are learned, within which limits.

A parameter is *learned* when the configuration gives limits ``{min: a, max: b}`` and *fixed* when it
gives a value (``{value: v}``). Learned parameters are what the generator's FCN outputs, squashed into [0, 1]
by a sigmoid and rescaled into [min, max]; only they carry gradients in the scene. Which parameters a scene has,
and in which order, is the scene's config's business (``scene_parameters`` of `drgan.scene.config`'s imaging
configs); the noise sigma comes last.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from drgan.core.errors import ConfigError, setting_float


@dataclass(frozen=True)
class Parameter:
    """One scalar of the scene: ``surface`` names what it belongs to ('stage', 'particle', 'transmission', ...; the
    noise sigma's is 'noise'), ``name`` the value."""

    surface: str
    name: str
    low: float | None = None
    high: float | None = None
    value: float | None = None

    @property
    def learned(self) -> bool:
        return self.value is None

    @property
    def key(self) -> str:
        return f"{self.surface}.{self.name}"


def parse_parameter(surface: str, name: str, spec, where: str, minimum: float | None = 0.0) -> Parameter:
    """A Parameter from ``spec``: a number (fixed), or a mapping or object with ``min``, ``max``, ``value``
    (`drgan.scene.config.ParameterRange`), unset ones None. ``where`` names the setting in errors; values below
    ``minimum`` are refused (None: signed values allowed, e.g. a fringe's amplitude)."""
    if isinstance(spec, (int, float)) and not isinstance(spec, bool):
        spec = {"value": spec}
    if not isinstance(spec, Mapping):
        if not all(hasattr(spec, key) for key in ("min", "max", "value")):
            raise ConfigError(f"{where}: expected {{min: a, max: b}} (learned) or {{value: v}} (fixed), got {spec!r}")
        spec = {key: getattr(spec, key) for key in ("min", "max", "value")}
    spec = {key: value for key, value in spec.items() if value is not None}
    keys = set(spec)
    if "value" in keys and keys <= {"value", "min", "max"}:
        # A material that inherits another and fixes one of its learned parameters ({value: v} over the parent's
        # {min, max}): Hydra merges the two mappings into {min, max, value}; the value, written last, wins.
        return Parameter(surface, name, value=setting_float(f"{where}.value", spec["value"], minimum))
    if keys != {"min", "max"}:
        raise ConfigError(f"{where}: expected keys {{min, max}} or {{value}}, got {sorted(keys)}")
    low, high = setting_float(f"{where}.min", spec["min"], minimum), setting_float(f"{where}.max", spec["max"], minimum)
    if low > high:
        raise ConfigError(f"{where}: min={low} > max={high}; expected min <= max")
    return Parameter(surface, name, low=low, high=high)


def noise_parameter(noise_sigma) -> Parameter:
    """The noise sigma (``material.noise_sigma``; None: no noise) as a Parameter; images are in [0, 1], so at most 1."""
    if noise_sigma is None:
        return Parameter("noise", "sigma", value=0.0)
    sigma = parse_parameter("noise", "sigma", noise_sigma, "material.noise_sigma")
    if sigma.learned and sigma.high > 1.0:
        raise ConfigError(f"material.noise_sigma.max={sigma.high}: expected <= 1 (images are in [0, 1])")
    return sigma


@dataclass(frozen=True)
class MaterialParameters:
    """All scalars of a material: the scene's values (``bsdf``, in the scene's order: for secondary electrons the
    Principled-BSDF values of stage and particles, for transmission background, absorption, floor) and the noise
    sigma."""

    bsdf: tuple[Parameter, ...]
    noise_sigma: Parameter

    @property
    def learned_bsdf(self) -> tuple[Parameter, ...]:
        return tuple(p for p in self.bsdf if p.learned)

    @property
    def learned(self) -> tuple[Parameter, ...]:
        """Every learned scalar in FCN output order: stage, particle (or transmission), then sigma (when learned)."""
        return self.learned_bsdf + ((self.noise_sigma,) if self.noise_sigma.learned else ())

    def surface(self, surface: str) -> tuple[Parameter, ...]:
        return tuple(p for p in self.bsdf if p.surface == surface)
