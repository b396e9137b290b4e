"""Typed settings: the one way a stage's keys become a typed object (`read_settings`), each field with its type, its
default and its check (`setting`), a bad value named with its key and what was expected before any work starts."""

from __future__ import annotations

import dataclasses
import types
import typing
from pathlib import Path
from typing import Any

from drgan.core.errors import ConfigError


def given(cfg, key: str, why: str):
    """``cfg[key]``, or a ConfigError saying ``why`` where the key is absent, null or empty (a required setting)."""
    value = cfg.get(key) if cfg is not None else None
    if value is None or value == "":
        raise ConfigError(why)
    return value


_REQUIRED = object()  # `setting`'s default where a key has none


def checks(*, ge: float | None = None, gt: float | None = None, le: float | None = None, expected: str | None = None,
           check=None) -> dict:  # fmt: skip
    """The field metadata `read_settings` reads: bounds (``expected``: the words of the error, else derived from the
    type and the bounds), or ``check(stage, value)``, which returns the typed value or raises a ConfigError itself."""
    return {"ge": ge, "gt": gt, "le": le, "expected": expected, "check": check}


def setting(default: Any = _REQUIRED, *, ge: float | None = None, gt: float | None = None, le: float | None = None,
            expected: str | None = None, check=None):  # fmt: skip
    """A settings field with its default (none: a required key) and what `read_settings` checks (`checks`)."""
    metadata = checks(ge=ge, gt=gt, le=le, expected=expected, check=check)
    if default is _REQUIRED:
        return dataclasses.field(metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def typed(cls: type) -> type:
    """Resolve the settings dataclass ``cls``'s field types now, where its module's names are at hand, and keep them
    on the class (use under ``@dataclass``). A stage's classes live in its ``__main__`` module: a sweep's worker process
    (Hydra's joblib or submitit launchers) receives them by value, without that module's names to resolve
    ``from __future__`` annotations with."""
    cls.__typed_hints__ = typing.get_type_hints(cls)
    return cls


def read_settings(cls: type, cfg, stage: str, *, prefix: str = "", **resolved):
    """A stage's typed settings ``cls`` (a dataclass) from its composed config ``cfg``, the one way drgan types a
    stage's keys: ``resolved`` fields as the stage's own checks made them (folders, merged lists), every other field
    read from the key of its name (absent: the field's default), checked against the field's type and bounds
    (`setting`); a ConfigError naming ``stage``, the key (after ``prefix``, e.g. ``data.``) and what was expected
    otherwise. An empty string in a field that may be null is null (``model=`` on a command line)."""
    from omegaconf import DictConfig, ListConfig, OmegaConf

    hints = cls.__dict__.get("__typed_hints__") or typing.get_type_hints(cls)
    values = dict(resolved)
    for f in dataclasses.fields(cls):
        if f.name in resolved or not f.init:
            continue
        where = f"{stage}: {prefix}{f.name}"
        if cfg is None or f.name not in cfg or (isinstance(cfg, DictConfig) and OmegaConf.is_missing(cfg, f.name)):
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
    low, above, high = bounds.get("ge"), bounds.get("gt"), bounds.get("le")
    if ok and isinstance(typed, (int, float)) and not isinstance(typed, bool):
        ok = (low is None or typed >= low) and (above is None or typed > above) and (high is None or typed <= high)
    if not ok:
        limit = f" >= {low:g}" if low is not None else f" > {above:g}" if above is not None else ""
        limit += f"{' and' if limit else ''} <= {high:g}" if high is not None else ""
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
    if hint is str:  # a number where text is expected is its text (name=2024), as OmegaConf reads it
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        return isinstance(value, str) or number, str(value) if number else value
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
