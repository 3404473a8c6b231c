"""The ROS 2 bridge: an arm whose driver is a ROS 2 node, on the uniros bus, with no rclpy in this process.

    uniros robot bridge rx200 --ros2 0                      # prints the domain URI, serves until SIGINT
    env = gym.make("uniros/Rx200Reach-v0", robot="tcp://127.0.0.1:PORT")         # that URI
    env = gym.make("uniros/Rx200Reach-v0", robot="ros2://0")                     # or the bridge in the env's process

It is the ROS 1 bridge's twin (``ros1_bridge.py``): the same translation, joint order, limit checks (a command a
hair past a joint limit is clamped, one further out refused and counted, never sent), ``hold`` and ``stats``
services; ``Ros2Bridge`` inherits them and only builds ROS 2 messages. The ROS side is a DDS participant
(``adapters/ros2``): joint states are read best effort (matching any driver's publisher), commands sent reliable.

Where the driver is: ``ros2://[DOMAIN_ID][/NAMESPACE][?driver=NAME&discovery=localhost|subnet]``.

- ``DOMAIN_ID``: the ROS 2 domain (``ROS_DOMAIN_ID``); empty: ``$ROS_DOMAIN_ID``, else 0.
- ``NAMESPACE``: the driver's namespace, which its relative topics resolve in; empty: the driver's default
  (``/rx200`` for the rx200's xs_sdk, ``/`` for a ros2_control arm).
- ``driver``: one of ``ROS2_DRIVERS``; empty: the robot's default (``ROS2_DEFAULTS``).
- ``discovery``: ``localhost`` (default: this host only, as ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``) or
  ``subnet`` (a driver on another machine).

Drivers (``ROS2_DRIVERS``), with their topics relative to the namespace:

- ``xs_sdk``: Interbotix X-series SDK for ROS 2 (Humble / Jazzy), the ReactorX-200's: ``joint_states`` and
  ``commands/joint_group`` (``interbotix_xs_msgs/msg/JointGroupCommand``; ``name`` the group, ``cmd`` positions).
- ``joint_trajectory_controller``: any ros2_control arm: ``/joint_states`` (joint_state_broadcaster) and
  ``joint_trajectory_controller/joint_trajectory`` (``trajectory_msgs/msg/JointTrajectory``, one point reached
  ``max(duration_s, one hardware period)`` from now). The Ned2's default.
- ``forward_position_controller``: ros2_control's position forwarder: ``/joint_states`` and
  ``forward_position_controller/commands`` (``std_msgs/msg/Float64MultiArray``).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import time
import urllib.parse
from collections.abc import AsyncIterator, Callable
from typing import Any, cast

import numpy as np

from uniros_async.adapters.ros1_bridge import Ros1Bridge
from uniros_async.bus import open_domain, open_node
from uniros_async.bus.messages import Data, Empty, JointCommand, JointState, Trigger
from uniros_async.bus.qos import latest
from uniros_async.errors import ConfigError, RobotError
from uniros_async.robots import get_robot_spec
from uniros_async.robots.spec import RobotSpec

__all__ = [
    "COMMAND_TYPES",
    "ROS2_DEFAULTS",
    "ROS2_DRIVERS",
    "ROS2_SETTINGS",
    "Ros2Bridge",
    "Ros2BridgeConfig",
    "open_ros2_bridge",
    "parse_ros2_uri",
    "serve_ros2_bridge",
]

logger = logging.getLogger(__name__)

COMMAND_TYPES = (
    "interbotix_xs_msgs/msg/JointGroupCommand",
    "trajectory_msgs/msg/JointTrajectory",
    "std_msgs/msg/Float64MultiArray",
)

ROS2_DRIVERS: dict[str, dict[str, str]] = {
    # Interbotix xs_sdk (ROS 2): topics in the robot's own namespace
    "xs_sdk": {
        "joint_states": "joint_states",
        "command": "commands/joint_group",
        "command_type": "interbotix_xs_msgs/msg/JointGroupCommand",
    },
    # ros2_control: joint_state_broadcaster publishes /joint_states; the controller listens on ~/joint_trajectory
    "joint_trajectory_controller": {
        "joint_states": "joint_states",
        "command": "joint_trajectory_controller/joint_trajectory",
        "command_type": "trajectory_msgs/msg/JointTrajectory",
    },
    # ros2_control's forward_command_controller as a position forwarder: ~/commands
    "forward_position_controller": {
        "joint_states": "joint_states",
        "command": "forward_position_controller/commands",
        "command_type": "std_msgs/msg/Float64MultiArray",
    },
}
"""Per driver: its joint-state topic, command topic and command type (topics relative to the namespace)."""

ROS2_DEFAULTS: dict[str, dict[str, str]] = {
    "rx200": {"driver": "xs_sdk", "namespace": "/rx200"},
    "ned2": {"driver": "joint_trajectory_controller", "namespace": "/"},
}
"""Per robot: its usual ROS 2 driver and that driver's namespace."""

ROS2_SETTINGS = ("joint_states", "command", "command_type", "group", "state_timeout_s")
"""The bridge settings an env takes in its ``ros2`` dict (``EnvConfig.ros2``); the URI gives the rest."""


@dataclasses.dataclass(frozen=True)
class Ros2Uri:
    """A parsed ``ros2://`` URI (``parse_ros2_uri``); None: the default."""

    domain_id: int | None
    namespace: str | None
    driver: str | None
    localhost_only: bool


def parse_ros2_uri(uri: str) -> Ros2Uri:
    """``ros2://[DOMAIN_ID][/NAMESPACE][?driver=NAME&discovery=localhost|subnet]`` -> its parts.

    Raises:
        ConfigError: not of that form (says what is expected).
    """
    form = "ros2://[DOMAIN_ID][/NAMESPACE][?driver=NAME&discovery=localhost|subnet] (e.g. ros2://0 or ros2://3/arm1)"
    if not uri.startswith("ros2://"):
        raise ConfigError(f"expected a ROS 2 arm as {form}, got {uri!r}")
    rest, _, query = uri.removeprefix("ros2://").partition("?")
    head, slash, ns = rest.partition("/")
    if head and (not head.isdigit() or not 0 <= int(head) <= 232):
        raise ConfigError(f"{uri!r}: the domain id must be an integer in 0..232; expected {form}")
    namespace = "/" + ns.strip("/") if slash and ns.strip("/") else ("/" if slash and not ns.strip("/") else None)
    if namespace is not None and ("//" in namespace or " " in namespace):
        raise ConfigError(f"{uri!r}: bad namespace {namespace!r}; expected {form}")
    params = urllib.parse.parse_qs(query, keep_blank_values=True) if query else {}
    unknown = sorted(set(params) - {"driver", "discovery"})
    if unknown:
        raise ConfigError(f"{uri!r}: unknown parameter(s) {unknown}; expected {form}")
    driver = params.get("driver", [None])[-1]
    if driver is not None and driver not in ROS2_DRIVERS:
        raise ConfigError(f"{uri!r}: driver must be one of {sorted(ROS2_DRIVERS)}, got {driver!r}")
    discovery = params.get("discovery", ["localhost"])[-1]
    if discovery not in ("localhost", "subnet"):
        raise ConfigError(f"{uri!r}: discovery must be localhost or subnet, got {discovery!r}")
    return Ros2Uri(int(head) if head else None, namespace, driver, discovery == "localhost")


def _resolve(topic: str, namespace: str) -> str:
    return topic if topic.startswith("/") else namespace.rstrip("/") + "/" + topic


@dataclasses.dataclass(frozen=True, kw_only=True)
class Ros2BridgeConfig:
    """What the bridge connects: a robot of ours to the topics of its ROS 2 driver.

    Attributes:
        robot: robot name (``rx200``, ``ned2``); its spec gives the joint names, order and limits.
        domain_id: the ROS 2 domain; None: ``$ROS_DOMAIN_ID``, else 0.
        namespace: the driver's namespace; None: ``ROS2_DEFAULTS`` (``/`` for a robot without one).
        driver: one of ``ROS2_DRIVERS``; None: ``ROS2_DEFAULTS``.
        joint_states: the driver's ``sensor_msgs/msg/JointState`` topic (relative: in ``namespace``); None: the
            driver's.
        command: the driver's command topic (relative: in ``namespace``); None: the driver's.
        command_type: one of ``COMMAND_TYPES``; None: the driver's.
        group: the joint group of a ``JointGroupCommand`` (Interbotix: ``arm``).
        localhost_only: discover peers on this host only (default) or on the subnet.
        state_timeout_s: how long to wait for the driver's first joint state and its command subscription.
        node_name: the bridge's name on the bus.
    """

    robot: str
    domain_id: int | None = None
    namespace: str | None = None
    driver: str | None = None
    joint_states: str | None = None
    command: str | None = None
    command_type: str | None = None
    group: str = "arm"
    localhost_only: bool = True
    state_timeout_s: float = 10.0
    node_name: str = "ros2_bridge"

    def __post_init__(self) -> None:
        from uniros_async.adapters.ros2.msgs import ros_type_name

        spec = get_robot_spec(self.robot)  # ConfigError listing the robots
        defaults = ROS2_DEFAULTS.get(spec.name, {})
        if self.driver is None:
            object.__setattr__(self, "driver", defaults.get("driver", "joint_trajectory_controller"))
        if self.driver not in ROS2_DRIVERS:
            raise ConfigError(f"Ros2BridgeConfig.driver must be one of {sorted(ROS2_DRIVERS)}, got {self.driver!r}")
        if self.namespace is None:
            object.__setattr__(self, "namespace", defaults.get("namespace", "/"))
        ns = str(self.namespace)
        if not ns.startswith("/") or "//" in ns:
            raise ConfigError(f"Ros2BridgeConfig.namespace must be absolute like /rx200 (or /), got {ns!r}")
        preset = ROS2_DRIVERS[str(self.driver)]
        for key in ("joint_states", "command"):
            topic = getattr(self, key) or preset[key]
            if not isinstance(topic, str) or not topic.strip("/") or "//" in topic or topic.endswith("/"):
                raise ConfigError(f"Ros2BridgeConfig.{key} must be a ROS topic name like /a/b or a/b, got {topic!r}")
            object.__setattr__(self, key, _resolve(topic, ns))
        ctype = ros_type_name(self.command_type or preset["command_type"])
        if ctype not in COMMAND_TYPES:
            raise ConfigError(f"Ros2BridgeConfig.command_type must be one of {COMMAND_TYPES}, got {ctype!r}")
        object.__setattr__(self, "command_type", ctype)
        if self.domain_id is not None and not 0 <= self.domain_id <= 232:
            raise ConfigError(f"Ros2BridgeConfig.domain_id must be in 0..232, got {self.domain_id}")
        if not self.state_timeout_s > 0:
            raise ConfigError(f"Ros2BridgeConfig.state_timeout_s must be > 0, got {self.state_timeout_s}")

    @classmethod
    def from_uri(cls, robot: str, uri: str, **settings: Any) -> Ros2BridgeConfig:
        """The config for ``robot`` behind the driver ``uri`` names (``parse_ros2_uri``), plus ``settings``
        (``ROS2_SETTINGS``).

        Raises:
            ConfigError: a bad URI, or a setting that is not one of ``ROS2_SETTINGS``.
        """
        unknown = sorted(set(settings) - set(ROS2_SETTINGS))
        if unknown:
            raise ConfigError(f"ros2: unknown setting(s) {unknown}; expected some of {list(ROS2_SETTINGS)}")
        parsed = parse_ros2_uri(uri)
        return cls(
            robot=robot,
            domain_id=parsed.domain_id,
            namespace=parsed.namespace,
            driver=parsed.driver,
            localhost_only=parsed.localhost_only,
            **settings,
        )

    @property
    def spec(self) -> RobotSpec:
        return get_robot_spec(self.robot)


class Ros2Bridge(Ros1Bridge):
    """The ROS 1 bridge's translation and checks, with ROS 2 command messages (built by ``open_ros2_bridge``).

    ``Ros1Bridge`` reads only ``spec``, ``joint_states``, ``command``, ``command_type`` and ``group`` of its config,
    which ``Ros2BridgeConfig`` has too; ``on_ros_state`` takes a rosbags ``sensor_msgs/msg/JointState`` as it is.
    """

    def __init__(
        self,
        config: Ros2BridgeConfig,
        send: Callable[[Any], None],
        publish: Callable[[JointState], None],
        now_ns: Callable[[], int],
    ) -> None:
        super().__init__(cast(Any, config), send, publish, now_ns)
        from uniros_async.adapters.ros2 import msgs

        self._cls = msgs.message_class

    def ros_command(self, q: np.ndarray, duration_s: float = 0.0) -> Any:
        """The driver's ROS 2 command message (a rosbags message) for arm positions ``q``."""
        cls, kind = self._cls, self.config.command_type
        if kind == "interbotix_xs_msgs/msg/JointGroupCommand":
            return cls(kind)(name=self.config.group, cmd=q.astype(np.float32))
        if kind == "std_msgs/msg/Float64MultiArray":
            layout = cls("std_msgs/msg/MultiArrayLayout")(dim=[], data_offset=0)
            return cls(kind)(layout=layout, data=q.astype(np.float64))
        t_ns = round(max(float(duration_s), self.period_s) * 1e9)
        empty = np.zeros(0)
        duration = cls("builtin_interfaces/msg/Duration")(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
        point = cls("trajectory_msgs/msg/JointTrajectoryPoint")(
            positions=q.astype(np.float64),
            velocities=empty,
            accelerations=empty,
            effort=empty,
            time_from_start=duration,
        )
        # stamp 0: start at once (joint_trajectory_controller's convention)
        stamp = cls("builtin_interfaces/msg/Time")(sec=0, nanosec=0)
        header = cls("std_msgs/msg/Header")(stamp=stamp, frame_id="")
        return cls(kind)(header=header, joint_names=list(self.spec.arm_joint_names), points=[point])


@contextlib.asynccontextmanager
async def open_ros2_bridge(
    config: Ros2BridgeConfig, *, domain: Any, namespace: str | None = None, transport: str = "auto"
) -> AsyncIterator[Ros2Bridge]:
    """Run the bridge for ``config.robot`` as a node of ``domain`` (an open Domain or a URI) until the block ends.

    Returns once the driver's first joint state has been republished and its command subscription matched, so an
    env joining next finds the arm and its commands go somewhere.

    Raises:
        ConfigError: bad settings, or cyclonedds / rosbags missing.
        RobotError: no joint state on ``config.joint_states`` or no subscription on ``config.command`` within
            ``config.state_timeout_s`` (names the topic and the domain id), or a driver's type or type hash differs
            from ours (names both; nothing was sent).
    """
    from uniros_async.adapters.ros2 import COMMANDS, SENSOR_DATA, open_ros2_node

    spec = config.spec
    assert config.command_type is not None and config.joint_states is not None and config.command is not None
    ns = namespace or f"/{spec.name}"
    async with contextlib.AsyncExitStack() as stack:
        ros = await stack.enter_async_context(
            open_ros2_node(
                f"uniros_{config.node_name}", domain_id=config.domain_id, localhost_only=config.localhost_only
            )
        )
        node = await stack.enter_async_context(
            open_node(config.node_name, domain=domain, namespace=ns, transport=transport)
        )
        pub = await node.create_publisher(JointState, "joint_states", qos=latest())
        ros_pub = ros.create_publisher(config.command, config.command_type, qos=COMMANDS)
        bridge = Ros2Bridge(config, ros_pub.publish, pub.publish, node.now_ns)
        await node.create_subscription(JointCommand, "command", bridge.on_command, qos=latest())
        await node.create_service(Empty, Trigger, "hold", bridge.srv_hold)
        await node.create_service(Empty, Data, "stats", bridge.srv_stats)
        ros_sub = ros.create_subscription(
            config.joint_states, "sensor_msgs/msg/JointState", bridge.on_ros_state, qos=SENSOR_DATA
        )
        t0 = time.monotonic()

        async def first_state() -> None:
            while not bridge.first_state.is_set():
                ros_sub.check_peers()  # a publisher of another type there: say so now, not at the timeout
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(bridge.first_state.wait(), 0.05)

        try:
            await asyncio.wait_for(first_state(), config.state_timeout_s)
        except TimeoutError:
            raise RobotError(
                f"{spec.name}: no sensor_msgs/msg/JointState on {config.joint_states} in ROS 2 domain "
                f"{ros.domain_id} within {config.state_timeout_s} s (is the arm's driver running, in that domain"
                f"{', on this host' if config.localhost_only else ''}? `ros2 topic list` there shows its topics; "
                f"--joint-states / the ros2 settings pick another)"
            ) from None
        try:
            await ros_pub.wait_for_subscribers(1, timeout_s=max(config.state_timeout_s - (time.monotonic() - t0), 0.5))
        except TimeoutError:
            raise RobotError(
                f"{spec.name}: nothing in ROS 2 domain {ros.domain_id} subscribes to {config.command} "
                f"({config.command_type}), so commands would go nowhere (is that the driver's command topic? "
                f"`ros2 topic info {config.command}` shows its subscribers; --command / the ros2 settings pick another)"
            ) from None
        logger.info(
            "%s: bridged %s -> %s/joint_states and %s/command -> %s (%s) in ROS 2 domain %d in %.2f s",
            spec.name,
            config.joint_states,
            ns,
            ns,
            config.command,
            config.command_type,
            ros.domain_id,
            time.monotonic() - t0,
        )
        yield bridge


async def serve_ros2_bridge(
    config: Ros2BridgeConfig,
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    namespace: str | None = None,
    on_ready: Callable[[str], Any] | None = None,
) -> None:
    """Run the bridge in an own tcp domain on ``host:port`` until cancelled (``uniros robot bridge --ros2``).

    Args:
        on_ready: called with the domain URI once the arm's joint states flow (the CLI prints it).
    """
    async with (
        open_domain(f"tcp://{host}:{port}") as dom,
        open_ros2_bridge(config, domain=dom, namespace=namespace, transport="tcp"),
    ):
        if on_ready is not None:
            on_ready(dom.uri)
        await asyncio.Event().wait()  # until cancelled
