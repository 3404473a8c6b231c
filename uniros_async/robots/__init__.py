"""Robot descriptions: one subpackage per arm (MJCF model + RobotSpec), and a registry by name.

>>> from uniros_async.robots import get_robot_spec
>>> get_robot_spec("rx200").hardware_rate_hz
10.0
"""

from __future__ import annotations

import importlib

from uniros_async.errors import ConfigError
from uniros_async.robots.spec import RobotSpec, ServoProfile

__all__ = ["ROBOT_NAMES", "RobotSpec", "ServoProfile", "get_robot_spec"]

# name -> "module:attribute"; modules are imported on first use, so importing this package stays cheap.
_REGISTRY: dict[str, str] = {
    "rx200": "uniros_async.robots.rx200.config:RX200",
    "ned2": "uniros_async.robots.ned2.config:NED2",
}

ROBOT_NAMES: tuple[str, ...] = tuple(sorted(_REGISTRY))


def get_robot_spec(name: str) -> RobotSpec:
    """Return the spec of the robot registered as ``name``.

    Args:
        name: a registered robot name, e.g. ``"rx200"`` or ``"ned2"``.

    Returns:
        The robot's RobotSpec.

    Raises:
        ConfigError: ``name`` is not registered; the message lists the valid names.
    """
    try:
        target = _REGISTRY[name]
    except (KeyError, TypeError):
        raise ConfigError(f"unknown robot {name!r}; valid names are {list(ROBOT_NAMES)}") from None
    module_name, attribute = target.split(":")
    spec = getattr(importlib.import_module(module_name), attribute)
    if not isinstance(spec, RobotSpec):
        raise TypeError(f"{target} is {type(spec).__name__}, not a RobotSpec")
    return spec
