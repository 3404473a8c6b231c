"""Lazy package exports (PEP 562): a package lists which submodule holds each public name, and a name's submodule
is imported only when the name is first asked for (so ``import uniros_async.sim`` does not load MuJoCo, nor
``import uniros_async.training`` torch)."""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

__all__ = ["lazy_exports"]


def lazy_exports(package: str, where: dict[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module-level ``__getattr__`` and ``__dir__`` of ``package`` whose public names live in the submodules
    ``where`` maps them to (``{"ServoSim": "servo"}``: ``package.servo.ServoSim``)."""

    def __getattr__(name: str) -> Any:
        module = where.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(f"{package}.{module}"), name)

    def __dir__() -> list[str]:
        return sorted(where)

    return __getattr__, __dir__
