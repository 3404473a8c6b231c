"""Robot descriptions: one subpackage per arm (MJCF model + RobotSpec), and a registry by name open to user code.

>>> from uniros_async.robots import get_robot_spec
>>> get_robot_spec("rx200").hardware_rate_hz
10.0

A package of your own adds an arm without touching this one, as gymnasium's ``register`` adds an env: it builds a
``RobotSpec`` whose ``mjcf_path`` is a file it ships (``packaged_file("my_pkg", "myarm.xml")``) and calls
``register_robot(MYARM)`` at import, or ``register_robot("my_pkg.config:MYARM", name="myarm")`` to import the
spec on first use. Every consumer (envs, sims, kinematics, the ``uniros robot`` commands) looks robots up here when
it needs one, so a registered arm is known everywhere in that process; ``"my_pkg:myarm"`` imports ``my_pkg``
first, so a CLI or another process finds the arm by that name alone.
"""

from __future__ import annotations

import importlib
from typing import Any

from uniros_async.errors import ConfigError
from uniros_async.registry import Registry
from uniros_async.robots.spec import RobotSpec, ServoProfile

__all__ = ["ROBOT_NAMES", "RobotSpec", "ServoProfile", "get_robot_spec", "register_robot", "robot_names"]


def _check_spec(name: str, spec: object) -> RobotSpec:
    if not isinstance(spec, RobotSpec):
        raise ConfigError(f"robot {name!r}: its entry point is a {type(spec).__name__}, not a RobotSpec")
    if spec.name != name:
        raise ConfigError(f"robot {name!r}: its entry point is the spec of {spec.name!r}")
    return spec


def _describe(entry: RobotSpec | str) -> str:
    return repr(entry) if isinstance(entry, str) else f"a RobotSpec with model {entry.mjcf_path}"


# name -> the spec, or "module:attribute" naming it (imported on first use, so importing this package stays cheap)
_ROBOTS = Registry[RobotSpec](
    "robot", entry_points="attribute", check=_check_spec, describe=_describe, note="register_robot adds one"
)
_ROBOTS.register("rx200", "uniros_async.robots.rx200.config:RX200")
_ROBOTS.register("ned2", "uniros_async.robots.ned2.config:NED2")


def register_robot(spec: RobotSpec | str, *, name: str | None = None, override: bool = False) -> None:
    """Register a robot so that every part of uniros_async finds it by name (``arm="myarm"``).

    Registering the same spec (or entry point) again is a no-op, so a module may register at import however often
    it is imported.

    Args:
        spec: the robot's RobotSpec, or ``"module:attribute"`` naming one (imported on first lookup).
        name: the registry name; for a RobotSpec, None means ``spec.name`` and anything else must equal it. An
            entry point needs it.
        override: replace another robot already registered under the name.

    Raises:
        ConfigError: no name for an entry point, a name that differs from the spec's, a malformed entry point, or
            the name is taken by another robot and ``override`` is False.
    """
    if isinstance(spec, RobotSpec):
        if name is not None and name != spec.name:
            raise ConfigError(f"register_robot: name={name!r} differs from the spec's name {spec.name!r}")
        name = spec.name
    elif isinstance(spec, str):
        if ":" not in spec:
            raise ConfigError(f"register_robot: expected a RobotSpec or 'module:attribute', got {spec!r}")
        if name is None:
            raise ConfigError(f"register_robot({spec!r}): an entry point needs name=, the robot's name")
    else:
        raise ConfigError(f"register_robot: expected a RobotSpec or 'module:attribute', got {type(spec).__name__}")
    if not name or ":" in name or "/" in name or name != name.strip():
        raise ConfigError(f"register_robot: the name must be a plain word (a topic namespace), got {name!r}")
    _ROBOTS.register(name, spec, override=override)


def robot_names() -> tuple[str, ...]:
    """The registered robots' names, sorted (built-in and user-registered, as of this call)."""
    return _ROBOTS.names()


def get_robot_spec(name: str) -> RobotSpec:
    """Return the spec of the robot registered as ``name``.

    Args:
        name: a registered robot name, e.g. ``"rx200"`` or ``"ned2"``; or ``"module:name"``, which imports
            ``module`` (that registers the robot) first.

    Returns:
        The robot's RobotSpec.

    Raises:
        ConfigError: ``name`` is not registered (the message lists the registered names and the closest one), or
            its module cannot be imported or registers no such robot.
    """
    if not isinstance(name, str):
        raise ConfigError(f"robot: expected a registered robot's name, got {type(name).__name__} {name!r}")
    if ":" in name:
        module, _, name = name.rpartition(":")
        try:
            importlib.import_module(module)
        except ImportError as exc:
            raise ConfigError(
                f"robot '{module}:{name}': cannot import {module!r}, which should register it: {exc}"
            ) from exc
    return _ROBOTS.get(name)


def __getattr__(name: str) -> Any:
    # ROBOT_NAMES is read from the registry when asked for, so it lists the robots registered by then
    if name == "ROBOT_NAMES":
        return robot_names()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
