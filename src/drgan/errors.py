"""Errors a user can cause. Each message names the input and what was expected."""


class DrganError(ValueError):
    """Base class: bad input detected before compute is spent."""


class ConfigError(DrganError):
    """A configuration value is out of range or inconsistent (e.g. a limit with min > max)."""


class MeshError(DrganError):
    """A mesh file or mesh object is unusable (empty, non-finite, degenerate)."""


class DataError(DrganError):
    """An input image, mask or split file is missing, unreadable or of the wrong kind."""
