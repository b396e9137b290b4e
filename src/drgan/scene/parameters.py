"""Material parameters: which scene values (Principled-BSDF values, or the transmission scene's background,
absorption and floor) and noise level are learned, within which limits.

A parameter is *learned* when the configuration gives limits ``{min: a, max: b}`` and *fixed* when it
gives a value (``{value: v}`` or a bare number). Learned parameters are what the generator's FCN outputs,
squashed into [0, 1] by a sigmoid and rescaled into [min, max]; only they carry gradients in the scene.
Ordering follows the paper's reference implementation: stage parameters, particle parameters, noise sigma
(transmission: background, absorption, floor, noise sigma).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from drgan.errors import ConfigError, check_keys

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
SURFACES = ("stage", "particle", "transmission")
# Transmission imaging (drgan.scene.transmission): grey of the bare film, absorption per px of path length
# through a particle, and the grey behind an opaque particle (detector offset). Also the FCN output order.
TRANSMISSION_PARAMETERS = ("background", "absorption", "floor")
TRANSMISSION_DEFAULTS = {"floor": 0.0}  # absent: a detector without offset


@dataclass(frozen=True)
class Parameter:
    """One scalar of the scene: ``surface`` is 'stage', 'particle', 'transmission' or 'noise'."""

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

    def rescale(self, unit):
        """Map ``unit`` in [0, 1] (numbers, numpy or torch) into [low, high]."""
        return self.low + (self.high - self.low) * unit


def _parse_parameter(surface: str, name: str, spec, where: str) -> Parameter:
    if isinstance(spec, (int, float)) and not isinstance(spec, bool):
        spec = {"value": spec}
    if not isinstance(spec, Mapping):
        raise ConfigError(f"{where}: expected {{min: a, max: b}} (learned) or {{value: v}} (fixed), got {spec!r}")
    keys = set(spec)
    if "value" in keys and keys <= {"value", "min", "max"}:
        # A material that inherits another and fixes one of its learned parameters ({value: v} over the parent's
        # {min, max}): Hydra merges the two mappings into {min, max, value}; the value, written last, wins.
        value = float(spec["value"])
        if not math.isfinite(value) or value < 0:
            raise ConfigError(f"{where}.value={spec['value']!r}: expected a finite number >= 0")
        return Parameter(surface, name, value=value)
    if keys != {"min", "max"}:
        raise ConfigError(f"{where}: expected keys {{min, max}} or {{value}}, got {sorted(keys)}")
    low, high = float(spec["min"]), float(spec["max"])
    if not (math.isfinite(low) and math.isfinite(high)):
        raise ConfigError(f"{where}: limits must be finite, got min={low}, max={high}")
    if low < 0:
        raise ConfigError(f"{where}.min={low}: expected >= 0")
    if low > high:
        raise ConfigError(f"{where}: min={low} > max={high}; expected min <= max")
    return Parameter(surface, name, low=low, high=high)


def _parse_sigma(noise_sigma) -> Parameter:
    sigma = _parse_parameter("noise", "sigma", noise_sigma, "noise_sigma")
    if sigma.learned and sigma.high > 1.0:
        raise ConfigError(f"noise_sigma.max={sigma.high}: expected <= 1 (images are in [0, 1])")
    return sigma


@dataclass(frozen=True)
class MaterialParameters:
    """All scalars of a material: scene values per surface plus the noise sigma.

    ``bsdf`` holds the scene's values: Principled-BSDF values of the stage and particle surfaces
    (secondary-electron imaging) or the "transmission" surface's `TRANSMISSION_PARAMETERS`.
    """

    bsdf: tuple[Parameter, ...]
    noise_sigma: Parameter

    @classmethod
    def from_config(cls, particle_bsdf: Mapping, stage_bsdf: Mapping | None, noise_sigma) -> MaterialParameters:
        params: list[Parameter] = []
        for surface, table in (("stage", stage_bsdf or {}), ("particle", particle_bsdf or {})):
            for name, spec in table.items():
                if name not in PRINCIPLED_PARAMETERS:
                    raise ConfigError(
                        f"{surface}_bsdf.{name}: unknown Principled-BSDF parameter; expected one of "
                        f"{', '.join(PRINCIPLED_PARAMETERS)}"
                    )
                params.append(_parse_parameter(surface, name, spec, f"{surface}_bsdf.{name}"))
        return cls(tuple(params), _parse_sigma(noise_sigma))

    @classmethod
    def from_transmission(cls, transmission: Mapping, noise_sigma) -> MaterialParameters:
        """``material.transmission`` ({background, absorption, floor}, each {min, max} or {value}) and sigma."""
        if not isinstance(transmission, Mapping):
            raise ConfigError(
                f"material.transmission: expected a mapping of {', '.join(TRANSMISSION_PARAMETERS)}, "
                f"got {transmission!r}"
            )
        check_keys("material.transmission", transmission, TRANSMISSION_PARAMETERS, "parameter")
        params = []
        for name in TRANSMISSION_PARAMETERS:
            spec = transmission.get(name, TRANSMISSION_DEFAULTS.get(name))
            if spec is None:
                raise ConfigError(
                    f"material.transmission.{name}: missing; expected {{min: a, max: b}} (learned) or {{value: v}}"
                )
            params.append(_parse_parameter("transmission", name, spec, f"material.transmission.{name}"))
        return cls(tuple(params), _parse_sigma(noise_sigma))

    @property
    def learned_bsdf(self) -> tuple[Parameter, ...]:
        return tuple(p for p in self.bsdf if p.learned)

    @property
    def learned(self) -> tuple[Parameter, ...]:
        """Every learned scalar in FCN output order: stage, particle (or transmission), then sigma (when learned)."""
        return self.learned_bsdf + ((self.noise_sigma,) if self.noise_sigma.learned else ())

    def surface(self, surface: str) -> tuple[Parameter, ...]:
        return tuple(p for p in self.bsdf if p.surface == surface)
