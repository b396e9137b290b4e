"""Objects from ``_target_`` configs, the one way drgan wires configs to code: Hydra's `instantiate`, behind an
allow-list.

A config can be a file a user wrote or the config saved in a checkpoint someone sent, so the class it names must be
one drgan expects there (a size distribution, a discriminator, ...): `build` refuses any other name before anything
is imported or called, checks the keywords against the class's signature (an unknown or missing one is named with
the valid ones), and lets the class's own checks speak (a `ConfigError` it raises is not wrapped by Hydra).
"""

from __future__ import annotations

import inspect
from collections.abc import Iterable, Mapping

from drgan.core.errors import ConfigError, DrganError, check_keys


def target_path(cls: type) -> str:
    """The import path a config's ``_target_`` uses for ``cls``."""
    return f"{cls.__module__}.{cls.__qualname__}"


def allowed_class(target: object, allowed: Iterable[type], setting: str) -> type:
    """The class of ``allowed`` whose import path is ``target``, or a ConfigError naming ``setting`` and the choices."""
    paths = {target_path(cls): cls for cls in allowed}
    if target not in paths:
        raise ConfigError(f"{setting}._target_ must be one of {sorted(paths)}, got {target!r}")
    return paths[target]


def build(node: Mapping, allowed: Iterable[type], setting: str, **given):
    """``instantiate(node, **given)`` for a node whose ``_target_`` is one of ``allowed`` and whose keywords (with
    ``given``) fit the class's signature."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    if not isinstance(node, Mapping):
        raise ConfigError(f"{setting}: expected a mapping with a '_target_' key, got {type(node).__name__}")
    values = {key: value for key, value in dict(node).items() if not key.startswith("_")}
    nested = _nested_target(values, setting)
    if nested:
        raise ConfigError(f"{nested}._target_: a value here cannot name a class (only {setting}._target_ may)")
    cls = allowed_class(node.get("_target_"), allowed, setting)
    parameters = inspect.signature(cls).parameters
    accepted = [name for name, p in parameters.items() if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
    check_keys(f"{setting} ({target_path(cls)})", [*values, *given], accepted, "field")
    required = [name for name in accepted if parameters[name].default is inspect.Parameter.empty]
    missing = [name for name in required if name not in values and name not in given]
    if missing:
        raise ConfigError(f"{setting} ({target_path(cls)}): missing field(s) {missing}; fields are {accepted}")
    try:  # not recursive: a nested mapping stays a plain value, never another object to build
        return instantiate({"_target_": target_path(cls), **values}, **given, _recursive_=False, _convert_="all")
    except InstantiationException as error:
        if isinstance(error.__cause__, DrganError):
            raise error.__cause__ from None
        raise


def _nested_target(value, where: str) -> str | None:
    """The first setting below ``where`` that is a mapping with a ``_target_`` key, or None."""
    if isinstance(value, Mapping):
        if "_target_" in value:
            return where
        items = value.items()
    elif isinstance(value, (list, tuple)):
        items = enumerate(value)
    else:
        return None
    for key, item in items:
        found = _nested_target(item, f"{where}.{key}")
        if found:
            return found
    return None
