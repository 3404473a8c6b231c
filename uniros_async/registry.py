"""Registry: names mapped to values or to entry points, the one helper behind every registry of uniros_async.

Robots (``register_robot``), placements (``register_placement``), ROS driver defaults (``register_ros_driver``),
tasks and env ids (``register_task``, ``register_env_id``) and transport schemes (``register_scheme``) each keep
their own public functions and checks, and hold their entries in a ``Registry``, which does what gymnasium's env
registry does for ids:

- ``register`` stores a value, or an entry point string (``"module:attribute"``, or ``"module"`` for a registry of
  modules) that is imported on first lookup, so registering costs no import. Registering the same value again is
  a no-op (a module may register at import however often it is imported); a different value under a taken name is
  refused unless ``override=True``.
- ``get`` returns the value, importing and checking an entry point once; a name that misses raises ``ConfigError``
  naming the registered names and the closest one, as ``gymnasium.make`` does for an id.

>>> colours = Registry[str]("colour")
>>> colours.register("red", "#f00")
'#f00'
>>> colours.get("rde")
Traceback (most recent call last):
...
uniros_async.errors.ConfigError: unknown colour 'rde' (did you mean 'red'?); registered: ['red']
"""

from __future__ import annotations

import difflib
import importlib
from collections.abc import Callable, Iterable, Mapping
from types import MappingProxyType
from typing import Any, Generic, Literal, TypeVar

from uniros_async.errors import ConfigError

__all__ = ["Registry", "closest_name", "load_entry_point", "split_entry_point"]

T = TypeVar("T")


def split_entry_point(entry_point: object, what: str, *, attribute: bool = True) -> tuple[str, str]:
    """Split ``"module:attribute"`` into its module and attribute (a dotted path); ``("module", "")`` for a plain
    ``"module"`` when ``attribute`` is False.

    Args:
        entry_point: the string to split.
        what: what it is for, to start the error message (``"placement 'sim'"``).
        attribute: the attribute part is required.

    Raises:
        ConfigError: not a string of that form.
    """
    expected = "'module:attribute'" if attribute else "'module' or 'module:attribute'"
    if not isinstance(entry_point, str):
        raise ConfigError(f"{what}: expected an entry point {expected}, got {type(entry_point).__name__}")
    module, sep, attr = entry_point.partition(":")
    if not module or (sep and not attr) or (attribute and not sep) or ":" in attr:
        raise ConfigError(f"{what}: expected an entry point {expected}, got {entry_point!r}")
    return module, attr


def load_entry_point(entry_point: str, what: str, *, attribute: bool = True) -> Any:
    """Import what ``entry_point`` names: the attribute of ``"module:attribute"`` (dotted paths too), or the module
    of a plain ``"module"`` when ``attribute`` is False.

    Raises:
        ConfigError: a malformed entry point, a module that cannot be imported or an attribute it lacks (the
            message starts with ``what`` and names the entry point).
    """
    module_name, attr = split_entry_point(entry_point, what, attribute=attribute)
    try:
        value: Any = importlib.import_module(module_name)
    except ImportError as exc:
        raise ConfigError(f"{what}: cannot load {entry_point!r} (cannot import {module_name!r}: {exc})") from exc
    for part in attr.split(".") if attr else ():
        try:
            value = getattr(value, part)
        except AttributeError:
            raise ConfigError(f"{what}: cannot load {entry_point!r} ({module_name!r} has no {attr!r})") from None
    return value


def closest_name(name: object, names: Iterable[str]) -> str | None:
    """The registered name closest to ``name`` (difflib, as gymnasium's id lookup), or None when none is close."""
    close = difflib.get_close_matches(str(name), list(names), n=1)
    return close[0] if close else None


class Registry(Generic[T]):
    """Names mapped to values, or to entry points imported on first lookup.

    Args:
        kind: what an entry is, for messages (``"robot"``, ``"placement"``).
        entry_points: how a ``str`` value is read: ``"attribute"`` (``"module:attribute"``), ``"module"``
            (``"module"``, the module itself, or ``"module:attribute"``), or None: a str is a value like any other.
        check: called as ``check(name, loaded)`` on what an entry point loaded; returns the value to keep, or raises
            ConfigError (e.g. the object is not a RobotSpec).
        describe: how an entry reads in the "already registered" message (default: the entry point, or the
            value's ``entry_point`` attribute, or its type).
        note: the parenthesis ending a lookup's error, e.g. ``"register_robot adds one"``.
        overridable: the registering function takes ``override=True``, and the refusal says so.
    """

    def __init__(
        self,
        kind: str,
        *,
        entry_points: Literal["attribute", "module"] | None = None,
        check: Callable[[str, Any], T] | None = None,
        describe: Callable[[T | str], str] | None = None,
        note: str = "",
        overridable: bool = True,
    ) -> None:
        self.kind = kind
        self.note = note
        self._entry_points = entry_points
        self._check = check
        self._describe = describe
        self._overridable = overridable
        self._entries: dict[str, T | str] = {}
        self.entries: Mapping[str, T | str] = MappingProxyType(self._entries)
        """Every entry as registered (entry points not yet loaded stay strings), read-only."""

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def __len__(self) -> int:
        return len(self._entries)

    def names(self) -> tuple[str, ...]:
        """The registered names, sorted."""
        return tuple(sorted(self._entries))

    def is_entry_point(self, entry: T | str) -> bool:
        """True when ``entry`` is an entry point string that ``get`` imports."""
        return self._entry_points is not None and isinstance(entry, str)

    def register(self, name: str, value: T | str, *, override: bool = False) -> T | str:
        """Store ``value`` (or an entry point naming it) under ``name``; return the entry now stored.

        The same value again (equal, or an entry point that loads an equal value) is a no-op that returns the
        entry already there.

        Raises:
            ConfigError: a malformed entry point, or ``name`` holds another value and ``override`` is False.
        """
        if self.is_entry_point(value):
            split_entry_point(value, f"{self.kind} {name!r}", attribute=self._entry_points == "attribute")
        old = self._entries.get(name)
        if old is not None and (old == value or self._same(name, old, value)):
            return old
        if old is not None and not override:
            how = "; pass override=True to replace it" if self._overridable else ""
            raise ConfigError(f"{self.kind} {name!r} is already registered ({self.describe(old)}){how}")
        self._entries[name] = value
        return value

    def get(self, name: str) -> T:
        """The value registered as ``name``, importing (and checking) its entry point on the first lookup.

        Raises:
            ConfigError: nothing is registered as ``name`` (see ``unknown``), or its entry point does not load.
        """
        try:
            entry = self._entries[name]
        except (KeyError, TypeError):
            raise self.unknown(name) from None
        if not self.is_entry_point(entry):
            return entry  # type: ignore[return-value]  # a str only where strings are values
        value = self._load(name, entry)  # type: ignore[arg-type]
        if self._entries.get(name) is entry:
            self._entries[name] = value
        return value

    def unknown(self, name: object, *, message: str = "", among: Iterable[str] | None = None) -> ConfigError:
        """The error of a lookup that missed: ``message`` (default ``"unknown <kind> 'name'"``), the closest name
        of ``among`` (default: every registered name), the registered names and the note.

        Returns:
            The ConfigError, for the caller to raise.
        """
        names = sorted(self._entries if among is None else among)
        close = closest_name(name, names)
        hint = f" (did you mean {close!r}?)" if close is not None else ""
        note = f" ({self.note})" if self.note else ""
        return ConfigError(f"{message or f'unknown {self.kind} {name!r}'}{hint}; registered: {names}{note}")

    def describe(self, entry: T | str) -> str:
        """How ``entry`` reads in messages."""
        if self._describe is not None:
            return self._describe(entry)
        if isinstance(entry, str):
            return repr(entry)
        entry_point = getattr(entry, "entry_point", None)
        return repr(entry_point) if entry_point is not None else f"a {type(entry).__name__}"

    def _load(self, name: str, entry_point: str) -> T:
        what = f"{self.kind} {name!r}"
        value = load_entry_point(entry_point, what, attribute=self._entry_points == "attribute")
        return self._check(name, value) if self._check is not None else value

    def _same(self, name: str, old: T | str, new: T | str) -> bool:
        """Whether two entries are the same value once entry points are loaded (one that cannot load is no other)."""
        if not (self.is_entry_point(old) or self.is_entry_point(new)):
            return False
        try:
            a = self._load(name, old) if self.is_entry_point(old) else old  # type: ignore[arg-type]
            b = self._load(name, new) if self.is_entry_point(new) else new  # type: ignore[arg-type]
        except ConfigError:
            return False
        return bool(a == b)
