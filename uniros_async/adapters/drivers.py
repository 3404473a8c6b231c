"""ROS driver defaults: for each ROS version and robot, the topics and message type its driver speaks.

A bridge between the bus and a ROS arm driver (``ros1_bridge``, and a ROS 2 bridge alike) fills every setting the
user left out from here, so ``robot="ros1://HOST:PORT"`` drives a known arm with no settings at all. The registry
is keyed by ``(ros, robot, driver)``: ``ros`` is ``"ros1"`` or ``"ros2"``, ``robot`` a registered robot name,
and ``driver`` names one of the arm's drivers (an arm may have several: the vendor SDK, a ros_control
controller). The first driver registered for a ``(ros, robot)`` pair is its default unless another is
registered with ``default=True``.

This module imports nothing of ROS, so any adapter can read it. A package of your own registers its arm's driver
at import, next to its robot::

    from uniros_async.adapters.drivers import register_ros_driver

    register_ros_driver(
        "ros1", "myarm", driver="ros_control",
        joint_states="/joint_states",
        command="/arm_controller/command",
        command_type="trajectory_msgs/JointTrajectory",
    )
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

from uniros_async.errors import ConfigError
from uniros_async.registry import Registry

__all__ = [
    "ROS_VERSIONS",
    "RosDriverDefaults",
    "register_ros_driver",
    "ros_driver_defaults",
    "ros_drivers",
]

ROS_VERSIONS = ("ros1", "ros2")


@dataclasses.dataclass(frozen=True, kw_only=True)
class RosDriverDefaults:
    """What one ROS driver of one arm speaks.

    Attributes:
        ros: ``"ros1"`` or ``"ros2"``.
        robot: the robot's registered name.
        driver: the driver's name, e.g. ``"xs_sdk"`` or ``"ros_control"``.
        joint_states: the driver's ``sensor_msgs/JointState`` topic.
        command: the topic the driver takes position commands on.
        command_type: that topic's message type, e.g. ``"trajectory_msgs/JointTrajectory"`` (each bridge lists
            the types it can send and checks it).
        settings: further bridge settings by name (e.g. an Interbotix joint ``group``); a bridge takes the ones
            it knows.
    """

    ros: str
    robot: str
    driver: str
    joint_states: str
    command: str
    command_type: str
    settings: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    def as_settings(self) -> dict[str, Any]:
        """The defaults as bridge settings: ``joint_states``, ``command``, ``command_type``, then ``settings``."""
        return {
            "joint_states": self.joint_states,
            "command": self.command,
            "command_type": self.command_type,
            **self.settings,
        }


# "ros/robot/driver" -> its defaults (a robot's name has no "/": it is a topic namespace)
_DRIVERS = Registry[RosDriverDefaults]("ROS driver", describe=str)
_DEFAULT: dict[tuple[str, str], str] = {}  # (ros, robot) -> its default driver


def _key(ros: str, robot: str, driver: str) -> str:
    return f"{ros}/{robot}/{driver}"


def _check_ros(ros: str) -> None:
    if ros not in ROS_VERSIONS:
        raise ConfigError(f"ROS version: expected one of {ROS_VERSIONS}, got {ros!r}")


def register_ros_driver(
    ros: str,
    robot: str,
    *,
    driver: str,
    joint_states: str,
    command: str,
    command_type: str,
    settings: Mapping[str, Any] | None = None,
    default: bool = False,
    override: bool = False,
) -> RosDriverDefaults:
    """Register the topics of one ROS driver of ``robot``.

    Registering the same defaults again is a no-op, so a module may register at import however often it runs.

    Args:
        ros: ``"ros1"`` or ``"ros2"``.
        robot: the robot's name (as ``register_robot`` registered it; not checked here, so a driver may be
            registered before its robot).
        driver: the driver's name.
        joint_states: the driver's joint-state topic (absolute, ``/a/b``).
        command: the driver's command topic (absolute).
        command_type: the command topic's message type, ``package/Type``.
        settings: further bridge settings (see ``RosDriverDefaults.settings``).
        default: make it the robot's default driver for ``ros`` (the first one registered is, otherwise).
        override: replace other defaults already registered under ``(ros, robot, driver)``.

    Returns:
        The registered defaults.

    Raises:
        ConfigError: a bad argument, or the key is taken by other defaults and ``override`` is False.
    """
    _check_ros(ros)
    for what, value in (("robot", robot), ("driver", driver)):
        if not isinstance(value, str) or not value:
            raise ConfigError(f"register_ros_driver: {what} must be a non-empty string, got {value!r}")
    if "/" in robot:
        raise ConfigError(f"register_ros_driver: robot must be a robot's name (no '/'), got {robot!r}")
    for what, topic in (("joint_states", joint_states), ("command", command)):
        if not isinstance(topic, str) or not topic.startswith("/") or len(topic) < 2:
            raise ConfigError(f"register_ros_driver: {what} must be an absolute topic like /a/b, got {topic!r}")
    if not isinstance(command_type, str) or command_type.count("/") != 1:
        raise ConfigError(f"register_ros_driver: command_type must be 'package/Type', got {command_type!r}")
    entry = RosDriverDefaults(
        ros=ros,
        robot=robot,
        driver=driver,
        joint_states=joint_states,
        command=command,
        command_type=command_type,
        settings=MappingProxyType(dict(settings or {})),
    )
    registered = _DRIVERS.register(_key(ros, robot, driver), entry, override=override)
    if default or (ros, robot) not in _DEFAULT:
        _DEFAULT[ros, robot] = driver
    return registered  # type: ignore[return-value]  # no entry points


def ros_drivers(ros: str, robot: str | None = None) -> list[RosDriverDefaults]:
    """The drivers registered for ``ros`` (and ``robot``, when given), sorted by robot and driver."""
    _check_ros(ros)
    found = [d for d in _DRIVERS.entries.values() if isinstance(d, RosDriverDefaults) and d.ros == ros]
    return sorted((d for d in found if robot is None or d.robot == robot), key=lambda d: (d.robot, d.driver))


def ros_driver_defaults(ros: str, robot: str, driver: str | None = None) -> RosDriverDefaults | None:
    """The defaults of ``robot``'s ``driver`` on ``ros``; None when the robot has no driver registered there (a
    bridge then needs every setting given).

    Args:
        ros: ``"ros1"`` or ``"ros2"``.
        robot: the robot's name.
        driver: a driver's name; None: the robot's default driver.

    Raises:
        ConfigError: ``driver`` is given and not registered for the robot (the message names its drivers and the
            closest one).
    """
    _check_ros(ros)
    if driver is None:
        driver = _DEFAULT.get((ros, robot))
        if driver is None:
            return None
    key = _key(ros, robot, driver)
    if key not in _DRIVERS:
        known = [d.driver for d in ros_drivers(ros, robot)]
        raise _DRIVERS.unknown(driver, message=f"no {ros} driver {driver!r} is registered for {robot!r}", among=known)
    return _DRIVERS.get(key)


def _register_builtins() -> None:
    # Interbotix X-series SDK (xs_sdk): joint_states and the group command in the robot's own namespace
    register_ros_driver(
        "ros1",
        "rx200",
        driver="xs_sdk",
        joint_states="/rx200/joint_states",
        command="/rx200/commands/joint_group",
        command_type="interbotix_xs_msgs/JointGroupCommand",
        settings={"group": "arm"},
    )
    # Niryo's ned_ros stack: a ros_control JointTrajectoryController
    register_ros_driver(
        "ros1",
        "ned2",
        driver="ned_ros",
        joint_states="/joint_states",
        command="/niryo_robot_follow_joint_trajectory_controller/command",
        command_type="trajectory_msgs/JointTrajectory",
    )

    # ROS 2 (adapters/ros2_bridge.py). ``namespace`` is the prefix the driver's topics share: a ros2:// URI with
    # another namespace moves them there. Interbotix xs_sdk: topics in the robot's own namespace.
    register_ros_driver(
        "ros2",
        "rx200",
        driver="xs_sdk",
        joint_states="/rx200/joint_states",
        command="/rx200/commands/joint_group",
        command_type="interbotix_xs_msgs/JointGroupCommand",
        settings={"group": "arm", "namespace": "/rx200"},
    )
    # ros2_control: joint_state_broadcaster's /joint_states; the controllers' ~/joint_trajectory and ~/commands
    for robot in ("ned2", "rx200"):
        register_ros_driver(
            "ros2",
            robot,
            driver="joint_trajectory_controller",
            joint_states="/joint_states",
            command="/joint_trajectory_controller/joint_trajectory",
            command_type="trajectory_msgs/JointTrajectory",
            settings={"namespace": "/"},
        )
        register_ros_driver(
            "ros2",
            robot,
            driver="forward_position_controller",
            joint_states="/joint_states",
            command="/forward_position_controller/commands",
            command_type="std_msgs/Float64MultiArray",
            settings={"namespace": "/"},
        )


_register_builtins()
