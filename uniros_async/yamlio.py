"""YAML files read as users write them: safe loading, and numbers such as ``3e-4`` and ``1e4`` read as numbers.

PyYAML follows YAML 1.1, where a float needs a dot (``3.0e-4``), so ``3e-4`` and ``1e4`` come out as strings;
``load_yaml`` also resolves YAML 1.2's floats. This module imports no pydantic (the bus reads parameter files
with it); config models are in config.py.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

from uniros_async.errors import ConfigError

__all__ = ["load_yaml", "loads_yaml"]


class _Loader(yaml.SafeLoader):  # type: ignore[misc]
    """yaml.SafeLoader that also reads YAML 1.2 floats (``3e-4``, ``1e4``, ``1E+6``: no dot needed) as floats."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def loads_yaml(text: str) -> Any:
    """Parse YAML text (safe loading; ``3e-4`` and ``1e4`` are numbers).

    Raises:
        yaml.YAMLError: the text is not valid YAML.
    """
    return yaml.load(text, Loader=_Loader)  # a SafeLoader subclass: no arbitrary objects


def load_yaml(path: str | Path) -> Any:
    """Read a YAML file (safe loading; ``3e-4`` and ``1e4`` are numbers); errors name the path.

    Raises:
        ConfigError: the file cannot be read or is not valid YAML.
    """
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise ConfigError(f"cannot read config file {str(p)!r}: {exc.strerror}") from exc
    try:
        return loads_yaml(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{str(p)!r} is not valid YAML: {exc}") from exc
