"""Frozen dataclass configs loaded from YAML; unknown keys are rejected with the list of valid ones."""

from __future__ import annotations

import dataclasses
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

from uniros_async.errors import ConfigError

__all__ = ["config_from_dict", "load_config", "load_yaml"]

T = TypeVar("T")


def load_yaml(path: str | Path) -> Any:
    """Read a YAML file with ``yaml.safe_load``; a missing file or bad YAML raises ConfigError naming the path."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise ConfigError(f"cannot read config file {str(p)!r}: {exc.strerror}") from exc
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{str(p)!r} is not valid YAML: {exc}") from exc


def config_from_dict(cls: type[T], data: Any, *, where: str = "") -> T:
    """Build the dataclass ``cls`` from a mapping, recursively for nested dataclass fields.

    Raises:
        ConfigError: ``data`` is not a mapping, has keys ``cls`` does not know (all valid keys are listed), or a
            field's own validation (``__post_init__``) failed.
    """
    label = where or cls.__name__
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{label}: expected a mapping, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{label}: unknown key(s) {unknown}; valid keys are {sorted(fields)}")
    hints = typing.get_type_hints(cls)
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        sub = _dataclass_in(hints.get(key))
        if sub is not None and isinstance(value, dict):
            value = config_from_dict(sub, value, where=f"{label}.{key}")
        elif isinstance(value, list) and _is_tuple(hints.get(key)):
            value = tuple(value)
        kwargs[key] = value
    try:
        return cls(**kwargs)
    except TypeError as exc:
        raise ConfigError(f"{label}: {exc}") from exc


def load_config(path: str | Path, cls: type[T]) -> T:
    """Load ``cls`` from the YAML file at ``path``; see config_from_dict for the errors."""
    return config_from_dict(cls, load_yaml(path), where=str(path))


def _dataclass_in(hint: Any) -> type | None:
    if hint is None:
        return None
    if dataclasses.is_dataclass(hint) and isinstance(hint, type):
        return hint
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        for arg in typing.get_args(hint):
            if dataclasses.is_dataclass(arg) and isinstance(arg, type):
                return arg
    return None


def _is_tuple(hint: Any) -> bool:
    return hint is tuple or typing.get_origin(hint) is tuple
