"""Run a callback once a module has been imported, without importing it ourselves (wrapt's post-import hooks).

``import uniros_async`` registers its gymnasium ids, but gymnasium costs a quarter of a second to import, and a
process that only uses the bus or the transports should not pay it. So the ids are registered at once if gymnasium
is already loaded, and otherwise right after whoever imports it first has finished importing it.
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import importlib.util
import sys
import threading
from collections.abc import Callable, Sequence
from types import ModuleType
from typing import Any

__all__ = ["when_imported"]

_lock = threading.Lock()


def when_imported(name: str, callback: Callable[[ModuleType], None]) -> None:
    """Call ``callback(module)`` now if top-level module ``name`` is loaded, else right after its first import.

    Args:
        name: a top-level module name, such as ``"gymnasium"``.
        callback: runs once, in the importing thread, after the module's code has run; an error it raises
            propagates out of that ``import`` statement.
    """
    module = sys.modules.get(name)
    if module is not None:
        callback(module)
        return
    with _lock:
        sys.meta_path.insert(0, _Finder(name, callback))


class _Finder(importlib.abc.MetaPathFinder):
    """Finds ``name`` with the other finders and wraps its loader so that ``callback`` runs after it."""

    def __init__(self, name: str, callback: Callable[[ModuleType], None]) -> None:
        self._name = name
        self._callback = callback

    def find_spec(
        self, fullname: str, path: Sequence[str] | None, target: ModuleType | None = None
    ) -> importlib.machinery.ModuleSpec | None:
        if fullname != self._name:
            return None
        with _lock:
            if self in sys.meta_path:  # one shot: the next lookup (or a reload) goes straight to the real finders
                sys.meta_path.remove(self)
        spec = importlib.util.find_spec(fullname)
        if spec is None or spec.loader is None:
            return spec
        spec.loader = _Loader(spec.loader, self._callback)
        return spec


class _Loader(importlib.abc.Loader):
    """Delegates to the real loader, then calls the callback with the fully executed module."""

    def __init__(self, loader: importlib.abc.Loader, callback: Callable[[ModuleType], None]) -> None:
        self._loader = loader
        self._callback = callback

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType | None:
        return self._loader.create_module(spec)

    def exec_module(self, module: ModuleType) -> None:
        module.__loader__ = self._loader  # the module sees its own loader (resources, reload), not this wrapper
        if module.__spec__ is not None:
            module.__spec__.loader = self._loader
        self._loader.exec_module(module)
        self._callback(module)

    def __getattr__(self, attr: str) -> Any:
        return getattr(self._loader, attr)
