"""The ROS 2 bridge: an arm whose driver is a ROS 2 node, on the uniros bus, with no rclpy in this process.

    uniros robot bridge rx200 --ros2 0                      # prints the domain URI, serves until SIGINT
    env = gym.make("uniros/Rx200Reach-v0", robot="tcp://127.0.0.1:PORT")         # that URI
    env = gym.make("uniros/Rx200Reach-v0", robot="ros2://0")                     # or the bridge in the env's process

It is the ROS 1 bridge's twin (``ros1_bridge.py``): the same translation, joint order, limit checks (a command a
hair past a joint limit is clamped, one further out refused and counted, never sent), ``hold`` and ``stats``
services; ``Ros2Bridge`` shares them with ``Ros1Bridge`` (both derive from ``_bridge.Bridge``) and only builds
ROS 2 messages. The ROS side is a DDS participant (``adapters/ros2``): joint states are read best effort (matching
any driver's publisher), commands sent reliable.

Where the driver is: ``ros2://[DOMAIN_ID][/NAMESPACE][?driver=NAME&discovery=localhost|subnet&SETTING=VALUE]``.

- ``DOMAIN_ID``: the ROS 2 domain (``ROS_DOMAIN_ID``); empty: ``$ROS_DOMAIN_ID``, else 0.
- ``NAMESPACE``: the driver's namespace: its default topics move there from the driver's own (``/rx200`` for the
  rx200's xs_sdk, ``/`` for ros2_control); empty: the driver's own.
- ``driver``: one of the robot's ROS 2 drivers registered in ``adapters.drivers``; empty: the robot's default.
- ``discovery``: ``localhost`` (default: this host only, as ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``) or
  ``subnet`` (a driver on another machine).
- ``insecure=1``: required with ``discovery=subnet`` (DDS without SROS2 cannot authenticate its peers).
- any of ``ROS2_SETTINGS`` (``joint_states``, ``command``, ``command_type``, ``group``, ``state_timeout_s``).

The built-in drivers (``adapters/drivers.py``), for the rx200 and the Ned2:

- ``xs_sdk`` (the rx200's default): the Interbotix X-series SDK for ROS 2 (Humble / Jazzy):
  ``/rx200/joint_states`` and ``/rx200/commands/joint_group`` (``interbotix_xs_msgs/msg/JointGroupCommand``;
  ``name`` the group, ``cmd`` the positions).
- ``joint_trajectory_controller`` (the Ned2's default): any ros2_control arm: ``/joint_states``
  (joint_state_broadcaster) and ``/joint_trajectory_controller/joint_trajectory``
  (``trajectory_msgs/msg/JointTrajectory``: one point reached ``max(duration_s, one hardware period)`` from now).
- ``forward_position_controller``: ros2_control's position forwarder: ``/joint_states`` and
  ``/forward_position_controller/commands`` (``std_msgs/msg/Float64MultiArray``).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import time
import urllib.parse
from collections.abc import AsyncIterator, Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from uniros_async.adapters._bridge import Bridge, serve_bridge
from uniros_async.bus import open_domain, open_node
from uniros_async.bus.messages import JointState
from uniros_async.bus.qos import latest
from uniros_async.errors import ConfigError, RobotError
from uniros_async.robots import get_robot_spec
from uniros_async.robots.spec import RobotSpec

if TYPE_CHECKING:
    from uniros_async.envs.config import EnvConfig
    from uniros_async.placements import ArmLink, PlacementRequest
    from uniros_async.transports.base import TransportOptions

__all__ = [
    "COMMAND_TYPES",
    "ROS2_SETTINGS",
    "Ros2Bridge",
    "Ros2BridgeConfig",
    "check_ros2_placement",
    "open_ros2_bridge",
    "open_ros2_placement",
    "parse_ros2_uri",
    "serve_ros2_bridge",
]

logger = logging.getLogger(__name__)

COMMAND_TYPES = (
    "interbotix_xs_msgs/msg/JointGroupCommand",
    "trajectory_msgs/msg/JointTrajectory",
    "std_msgs/msg/Float64MultiArray",
)

ROS2_SETTINGS = ("driver", "joint_states", "command", "command_type", "group", "state_timeout_s", "insecure")
"""The bridge settings a ``ros2://`` URI takes as query parameters, besides ``discovery``."""


@dataclasses.dataclass(frozen=True)
class Ros2Uri:
    """A parsed ``ros2://`` URI (``parse_ros2_uri``); None: the default.

    Attributes:
        domain_id: the ROS 2 domain id.
        namespace: the driver's namespace.
        localhost_only: discovery on this host only.
        settings: bridge settings from the query (``ROS2_SETTINGS``), as strings but ``state_timeout_s``.
    """

    domain_id: int | None
    namespace: str | None
    localhost_only: bool
    settings: dict[str, Any]


_URI_FORM = (
    "ros2://[DOMAIN_ID][/NAMESPACE][?driver=NAME&discovery=localhost|subnet&...] (e.g. ros2://0, ros2://3/arm1 or "
    "ros2://0?driver=forward_position_controller)"
)


def parse_ros2_uri(uri: str) -> Ros2Uri:
    """``ros2://[DOMAIN_ID][/NAMESPACE][?driver=NAME&discovery=localhost|subnet&SETTING=VALUE]`` -> its parts.

    Raises:
        ConfigError: not of that form (says what is expected).
    """
    if not isinstance(uri, str) or not uri.startswith("ros2://"):
        raise ConfigError(f"expected a ROS 2 arm as {_URI_FORM}, got {uri!r}")
    rest, _, query = uri.removeprefix("ros2://").partition("?")
    head, slash, ns = rest.partition("/")
    if head and (not head.isdigit() or not 0 <= int(head) <= 232):
        raise ConfigError(f"{uri!r}: the domain id must be an integer in 0..232; expected {_URI_FORM}")
    namespace = ("/" + ns.strip("/")) if slash else None
    if namespace is not None and ("//" in namespace or " " in namespace):
        raise ConfigError(f"{uri!r}: bad namespace {namespace!r}; expected {_URI_FORM}")
    params = {k: v[-1] for k, v in urllib.parse.parse_qs(query, keep_blank_values=True).items()} if query else {}
    unknown = sorted(set(params) - {"discovery", *ROS2_SETTINGS})
    if unknown:
        raise ConfigError(f"{uri!r}: unknown parameter(s) {unknown}; expected some of {['discovery', *ROS2_SETTINGS]}")
    discovery = params.pop("discovery", "localhost")
    if discovery not in ("localhost", "subnet"):
        raise ConfigError(f"{uri!r}: discovery must be localhost or subnet, got {discovery!r}")
    settings: dict[str, Any] = dict(params)
    if "insecure" in settings:
        if settings["insecure"] not in ("1", "true", "0", "false"):
            raise ConfigError(f"{uri!r}: insecure must be 1, true, 0 or false, got {settings['insecure']!r}")
        settings["insecure"] = settings["insecure"] in ("1", "true")
    if "state_timeout_s" in settings:
        try:
            settings["state_timeout_s"] = float(settings["state_timeout_s"])
        except ValueError:
            raise ConfigError(f"{uri!r}: state_timeout_s must be a number, got {params['state_timeout_s']!r}") from None
    return Ros2Uri(int(head) if head else None, namespace, discovery == "localhost", settings)


def _resolve(topic: str, namespace: str) -> str:
    return topic if topic.startswith("/") else namespace.rstrip("/") + "/" + topic


@dataclasses.dataclass(frozen=True, kw_only=True)
class Ros2BridgeConfig:
    """What the bridge connects: a robot of ours to the topics of its ROS 2 driver.

    Attributes:
        robot: robot name (``rx200``, ``ned2``); its spec gives the joint names, order and limits.
        domain_id: the ROS 2 domain; None: ``$ROS_DOMAIN_ID``, else 0.
        namespace: the driver's namespace: the driver's default topics move from its own namespace (its
            ``namespace`` setting: ``/rx200`` for xs_sdk, ``/`` for ros2_control) to this one, and relative topics
            given here resolve in it; None: the driver's own.
        driver: which of the robot's registered ROS 2 drivers (``adapters.drivers``) gives the defaults of the
            settings below; None: the robot's default driver.
        joint_states: the driver's ``sensor_msgs/msg/JointState`` topic; None: the driver's.
        command: the driver's command topic; None: the driver's.
        command_type: one of ``COMMAND_TYPES`` (``pkg/Name`` is read as ``pkg/msg/Name``); None: the driver's.
        group: the joint group of a ``JointGroupCommand``; None: the driver's, else ``arm`` (Interbotix).
        localhost_only: discover peers on this host only (default) or on the subnet.
        state_timeout_s: how long to wait for the driver's first joint state and its command subscription.
        max_command_age_s: refuse commands and ``hold`` while the newest joint state is older than this (the link or
            the driver is gone: they would only queue); None (default): never refuse.
        node_name: the bridge's name on the bus.
        insecure: allow discovery beyond this host (``localhost_only=False``). DDS without SROS2 cannot
            authenticate its peers: anyone on the subnet can read the arm's state and command it; without this the
            bridge refuses to start.
    """

    robot: str
    domain_id: int | None = None
    namespace: str | None = None
    driver: str | None = None
    joint_states: str | None = None
    command: str | None = None
    command_type: str | None = None
    group: str | None = None
    max_command_age_s: float | None = None
    localhost_only: bool = True
    state_timeout_s: float = 10.0
    node_name: str = "ros2_bridge"
    insecure: bool = False

    def __post_init__(self) -> None:
        from uniros_async.adapters.drivers import ros_driver_defaults
        from uniros_async.adapters.ros2.msgs import ros_type_name

        spec = get_robot_spec(self.robot)  # ConfigError listing the robots
        driver = ros_driver_defaults("ros2", spec.name, self.driver)  # ConfigError naming the robot's drivers
        defaults: dict[str, Any] = {} if driver is None else driver.as_settings()
        if driver is not None:
            object.__setattr__(self, "driver", driver.driver)
        own_ns = str(defaults.get("namespace", "/"))
        if self.namespace is None:
            object.__setattr__(self, "namespace", own_ns)
        ns = str(self.namespace)
        if not ns.startswith("/") or "//" in ns or (len(ns) > 1 and ns.endswith("/")):
            raise ConfigError(f"Ros2BridgeConfig.namespace must be absolute like /rx200 (or /), got {ns!r}")
        for key in ("joint_states", "command", "command_type"):
            if getattr(self, key) is None and key not in defaults:
                raise ConfigError(
                    f"Ros2BridgeConfig: robot {self.robot!r} has no ROS 2 driver registered "
                    f"(adapters.drivers.register_ros_driver), so {key} has no default; give one"
                )
        for key in ("joint_states", "command"):
            topic = getattr(self, key)
            if topic is None:  # the driver's own topic, moved from its namespace to ours
                topic = str(defaults[key])
                if own_ns != "/" and topic.startswith(own_ns + "/"):
                    topic = topic[len(own_ns) :]
                topic = ns.rstrip("/") + topic
            if not isinstance(topic, str) or not topic.strip("/") or "//" in topic or topic.endswith("/"):
                raise ConfigError(f"Ros2BridgeConfig.{key} must be a ROS topic name like /a/b or a/b, got {topic!r}")
            object.__setattr__(self, key, _resolve(topic, ns))
        ctype = ros_type_name(str(self.command_type or defaults["command_type"]))
        if ctype not in COMMAND_TYPES:
            raise ConfigError(f"Ros2BridgeConfig.command_type must be one of {COMMAND_TYPES}, got {ctype!r}")
        object.__setattr__(self, "command_type", ctype)
        if self.group is None:
            object.__setattr__(self, "group", str(defaults.get("group", "arm")))
        if self.domain_id is not None and not 0 <= self.domain_id <= 232:
            raise ConfigError(f"Ros2BridgeConfig.domain_id must be in 0..232, got {self.domain_id}")
        if not self.state_timeout_s > 0:
            raise ConfigError(f"Ros2BridgeConfig.state_timeout_s must be > 0, got {self.state_timeout_s}")
        if not self.localhost_only and not self.insecure:
            raise ConfigError(
                "ROS 2 discovery beyond this host (discovery=subnet): DDS without SROS2 cannot authenticate its peers, "
                "so anyone on the subnet could read the arm's state and command it; give insecure=1 in the ros2:// URI "
                "(or --insecure) to accept that"
            )

    @classmethod
    def from_uri(cls, robot: str, uri: str, **settings: Any) -> Ros2BridgeConfig:
        """The config for ``robot`` behind the driver ``uri`` names (``parse_ros2_uri``); ``settings``
        (``ROS2_SETTINGS``; None values ignored) override the URI's.

        Raises:
            ConfigError: a bad URI or setting.
        """
        unknown = sorted(set(settings) - set(ROS2_SETTINGS))
        if unknown:
            raise ConfigError(f"ros2: unknown setting(s) {unknown}; expected some of {list(ROS2_SETTINGS)}")
        parsed = parse_ros2_uri(uri)
        merged = {**parsed.settings, **{k: v for k, v in settings.items() if v is not None}}
        return cls(
            robot=robot,
            domain_id=parsed.domain_id,
            namespace=parsed.namespace,
            localhost_only=parsed.localhost_only,
            **merged,
        )

    @property
    def spec(self) -> RobotSpec:
        return get_robot_spec(self.robot)


class Ros2Bridge(Bridge[Ros2BridgeConfig]):
    """The translation both ways, for one arm, with ROS 2 messages (built by ``open_ros2_bridge``).

    ``on_ros_state`` takes a rosbags ``sensor_msgs/msg/JointState`` as it is.
    """

    def __init__(
        self,
        config: Ros2BridgeConfig,
        send: Callable[[Any], None],
        publish: Callable[[JointState], None],
        now_ns: Callable[[], int],
    ) -> None:
        super().__init__(config, publish, now_ns)
        self._send = send  # our DDS publisher's, for the bridge's life (the ROS 1 bridge swaps its own on resets)
        from uniros_async.adapters.ros2 import msgs

        self._cls = msgs.message_class
        self.last_state_s = time.monotonic()  # when the driver's newest joint state came

    def driver_stamp_ns(self, msg: Any) -> int:
        """The driver's stamp of a ``sensor_msgs/msg/JointState`` (``builtin_interfaces/Time``: sec, nanosec)."""
        return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)

    def on_ros_state(self, msg: Any) -> None:
        """A ``sensor_msgs/msg/JointState`` from the driver: republished as ours (``Bridge.on_ros_state``)."""
        self.last_state_s = time.monotonic()
        super().on_ros_state(msg)

    async def watch_driver(self, domain_id: int, silent_s: float) -> None:
        """Log, naming the driver's topic and domain, when its joint states stop for ``silent_s`` (the env's robot
        timeout then stops the episode and holds the arm) and when they come back; runs until cancelled."""
        silent = False
        while True:
            await asyncio.sleep(min(silent_s / 4, 0.25))
            quiet_s = time.monotonic() - self.last_state_s
            if quiet_s > silent_s and not silent:
                silent = True
                logger.warning(
                    "%s: no sensor_msgs/msg/JointState on %s in ROS 2 domain %d for %.1f s: the driver stopped or "
                    "left (commands still go to %s)",
                    self.spec.name,
                    self.config.joint_states,
                    domain_id,
                    quiet_s,
                    self.config.command,
                )
            elif quiet_s <= silent_s and silent:
                silent = False
                logger.warning("%s: joint states on %s flow again", self.spec.name, self.config.joint_states)

    def ros_command(self, q: np.ndarray, duration_s: float = 0.0) -> Any:
        """The driver's ROS 2 command message (a rosbags message) for arm positions ``q``."""
        cls, kind = self._cls, str(self.config.command_type)
        if kind == "interbotix_xs_msgs/msg/JointGroupCommand":
            return cls(kind)(name=str(self.config.group), cmd=q.astype(np.float32))
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
    config: Ros2BridgeConfig,
    *,
    domain: Any,
    namespace: str | None = None,
    transport: str = "auto",
    options: TransportOptions | None = None,
) -> AsyncIterator[Ros2Bridge]:
    """Run the bridge for ``config.robot`` as a node of ``domain`` (an open Domain or a URI) until the block ends;
    the node joins with ``transport`` and ``options`` (``open_node``'s).

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
            open_node(config.node_name, domain=domain, namespace=ns, transport=transport, options=options)
        )
        pub = await node.create_publisher(JointState, "joint_states", qos=latest())
        ros_pub = ros.create_publisher(config.command, config.command_type, qos=COMMANDS)
        bridge = Ros2Bridge(config, ros_pub.publish, pub.publish, node.now_ns)
        await bridge.serve_on(node)
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
        tasks = await stack.enter_async_context(asyncio.TaskGroup())
        watch = tasks.create_task(bridge.watch_driver(ros.domain_id, max(1.0, 5 * bridge.period_s)))
        stack.callback(watch.cancel)  # runs before the task group's exit, which then reaps it
        bridge.log_bridged(ns, t0, f" in ROS 2 domain {ros.domain_id}")
        yield bridge


async def serve_ros2_bridge(
    config: Ros2BridgeConfig,
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    namespace: str | None = None,
    on_ready: Callable[[str], Any] | None = None,
    options: TransportOptions | None = None,
    tls: bool = False,
) -> None:
    """Run the bridge in an own domain on ``tcp://host:port`` (``tls``: ``tls://host:port``) until cancelled
    (``uniros robot bridge --ros2``).

    Args:
        on_ready: called with the domain URI once the arm's joint states flow (the CLI prints it).
        options: the domain's and the bridge node's transport options (``auth_key``; ``insecure`` for a non-loopback
            host without one; ``tls_*`` files, else ``$UNIROS_TLS_*``).
        tls: serve the domain on ``tls://`` (mutual TLS; the certificate must name ``host``).
    """
    await serve_bridge(
        open_ros2_bridge, config, host=host, port=port, namespace=namespace, on_ready=on_ready, options=options, tls=tls
    )


# ------------------------------------------------------------------------------------------------ the placement


def check_ros2_placement(robot: str, config: EnvConfig) -> None:
    """The ``ros2://`` placement's check of an env config: the URI and its settings.

    Raises:
        ConfigError: a malformed URI or an unknown setting.
    """
    parse_ros2_uri(robot)
    if config.ros1 is not None:
        raise ConfigError("ros1 settings do not apply to a ros2:// arm; give its settings in the URI's query")


@contextlib.asynccontextmanager
async def open_ros2_placement(request: PlacementRequest[EnvConfig]) -> AsyncIterator[ArmLink]:
    """``robot="ros2://..."``: the bridge in the env's process, on a memory domain the env joins as it joins an
    in-process sim; the bridge's settings are the URI's over the driver's defaults."""
    from uniros_async.placements import ArmLink

    bridge_cfg = Ros2BridgeConfig.from_uri(request.robot.name, request.uri)
    async with open_domain("memory://") as domain, open_ros2_bridge(bridge_cfg, domain=domain):
        yield ArmLink(domain=domain)
