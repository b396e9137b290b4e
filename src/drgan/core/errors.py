"""Errors a user can cause. Each message names the input and what was expected."""

import math
import numbers


class DrganError(ValueError):
    """Base class: bad input detected before compute is spent."""


class ConfigError(DrganError):
    """A configuration value is out of range or inconsistent (e.g. a limit with min > max)."""


class MeshError(DrganError):
    """A mesh file or mesh object is unusable (empty, non-finite, degenerate)."""


class DataError(DrganError):
    """An input image, mask or split file is missing, unreadable or of the wrong kind."""


def check_keys(where: str, given, known, what: str = "key") -> None:
    """A ConfigError when ``given`` (keys of a config mapping) has names outside ``known``, naming ``where``,
    the unknown names (sorted) and the known ones (in ``known``'s order): the one spelling of every "unknown key"
    check, so that a typo in any group reads alike."""
    known = list(known)
    unknown = sorted(set(given) - set(known), key=str)
    if unknown:
        raise ConfigError(f"{where}: unknown {what}(s) {unknown}; expected some of {known}")


def setting_int(key: str, value: object, minimum: int | None = None) -> int:
    """A user setting as an int, or a ConfigError naming ``key``: a bare ``int("abc")`` names neither the key
    nor what was expected. Whole-number floats (3.0) pass; 3.5, booleans and non-numeric text do not."""
    number = None
    if not isinstance(value, bool):
        if isinstance(value, int):
            number = value
        elif isinstance(value, float) and value.is_integer():
            number = int(value)
        elif isinstance(value, str):
            try:
                number = int(value.strip())
            except ValueError:
                number = None
        elif hasattr(value, "__index__"):  # numpy integers
            number = int(value)
    bound = "" if minimum is None else f" >= {minimum}"
    if number is None or (minimum is not None and number < minimum):
        raise ConfigError(f"{key}={value!r}: expected an integer{bound}")
    return number


def setting_float(key: str, value: object, minimum: float | None = None) -> float:
    """A user setting as a finite float, or a ConfigError naming ``key`` (see ``setting_int``)."""
    number = None
    if not isinstance(value, bool):
        try:
            number = float(value)  # int, float, numpy scalars, numeric text
        except (TypeError, ValueError):
            number = None
    bound = "" if minimum is None else f" >= {minimum}"
    finite = number is not None and number == number and number not in (float("inf"), float("-inf"))
    if not finite or (minimum is not None and number < minimum):
        raise ConfigError(f"{key}={value!r}: expected a finite number{bound}")
    return number


def pixel_size(stage: str, value: object) -> float | None:
    """A stage's ``nm_per_px`` setting: None (not given) or a positive finite size in nm, else a ConfigError naming
    the stage and the key (before any image is read)."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not 0 < float(value) < math.inf:
        raise ConfigError(f"{stage}: nm_per_px={value!r}: expected a positive pixel size in nm")
    return float(value)


def check_spp(spp, name: str = "spp") -> int:
    """Samples per pixel for the stratified sampler: a positive perfect square, or a ConfigError naming ``name``
    (rather than silently rounding up)."""
    if isinstance(spp, bool) or not isinstance(spp, int) and not hasattr(spp, "__index__") or int(spp) < 1:
        raise ConfigError(f"{name}={spp!r}: expected a positive integer")
    root = math.isqrt(int(spp))
    if root * root != spp:
        raise ConfigError(
            f"{name}={spp}: the stratified sampler needs a perfect square; use {root * root} or {(root + 1) ** 2}"
        )
    return int(spp)


# The checks of a dataclass field ``owner.name`` (a size distribution's, a placement's), run at construction.


def finite_field(owner: str, name: str, value: object) -> float:
    """``value`` as a float, or a ConfigError naming ``owner.name``: booleans, non-numbers, inf and nan fail."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(float(value)):
        raise ConfigError(f"{owner}.{name} must be a finite number, got {value!r}")
    return float(value)


def check_positive(owner: str, name: str, value: object) -> None:
    if finite_field(owner, name, value) <= 0.0:
        raise ConfigError(f"{owner}.{name} must be > 0, got {value!r}")


def check_non_negative(owner: str, name: str, value: object) -> None:
    if finite_field(owner, name, value) < 0.0:
        raise ConfigError(f"{owner}.{name} must be >= 0, got {value!r}")


def check_int_at_least(owner: str, name: str, value: object, lowest: int) -> None:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or int(value) < lowest:
        raise ConfigError(f"{owner}.{name} must be an integer >= {lowest}, got {value!r}")
