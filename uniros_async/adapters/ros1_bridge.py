"""The ROS 1 bridge: an arm whose driver is a ROS 1 node, on the uniros bus, with no rospy in this process.

    uniros robot bridge rx200 --ros-master http://robot-pc:11311/   # prints the domain URI, serves until SIGINT
    env = gym.make("uniros/Rx200Reach-v0", robot="tcp://127.0.0.1:PORT")        # that URI
    env = gym.make("uniros/Rx200Reach-v0", robot="ros1://robot-pc:11311")       # or the bridge in the env's process

The bridge is to a real arm what the servo sim node is to a simulated one, its hardware interface on the bus: in
namespace ``/<robot>`` it publishes ``joint_states`` (our ``JointState``, in the robot's ``joint_state_names``
order, stamped on arrival less the time it waited on the way, ``Ros1Bridge.queued_ns``) for every
``sensor_msgs/JointState`` the driver publishes, and turns every ``command`` (our ``JointCommand``) into one
message on the driver's command topic. The env reaches the arm only through those two topics (``envs/robot.py``),
so the same TaskEnv code runs on the sim, the emulated real arm and a ROS 1 arm.

Command types (``command_type``), each what a common ROS 1 arm driver listens to:

- ``interbotix_xs_msgs/JointGroupCommand`` on ``/<robot>/commands/joint_group``: the Interbotix X-series SDK
  (``xs_sdk``) of the ReactorX-200; ``name`` is the joint group (``arm``), ``cmd`` the positions. The rx200's
  default: the servos' time-based profile (2 s moves) then shapes the motion, as in our servo sim.
- ``trajectory_msgs/JointTrajectory`` on a ros_control JointTrajectoryController's ``command`` topic: one point,
  reached ``max(duration_s, one hardware period)`` from now. The Ned2's default
  (``/niryo_robot_follow_joint_trajectory_controller/command``).
- ``std_msgs/Float64MultiArray`` on a ros_control JointGroupPositionController's ``command`` topic: the positions.

The env already refuses unsafe targets; the bridge checks joint limits once more. A command a hair past a limit
(``_bridge.LIMIT_CLAMP_RAD``) is clamped to it, as the servos would; one further out, or of the wrong length, is
dropped and counted, never sent. It serves ``hold`` (command the newest measured position) and ``stats``
(counters), like the servo sim. Joint states that lack an arm joint are dropped and counted (the first such message
logs which names were missing and which came); a missing non-arm joint (a gripper finger) reads 0.0, logged once.

No command older than ``max_command_age_s`` reaches the driver. The drivers' command messages carry no stamp (an
Interbotix ``JointGroupCommand`` has no header), so the driver cannot drop an old one: in a partition the commands
wait in the kernel's send queue of the TCPROS connection, and TCP delivers them when the link heals. So the bridge
guards them itself, every ``check_s``:

- a connection to the driver still holding a command published more than ``max_command_age_s - check_s`` ago that
  the driver's kernel has not acknowledged (``SIOCOUTQ``) is reset (``SO_LINGER`` 0: the kernel discards what it
  holds); so is any connection holding an unacknowledged command while the joint states are stale;
- while the newest joint state is older than ``max_command_age_s`` (the link or the driver is gone), commands and
  ``hold`` are refused (counted in ``commands_stale``): they would only queue;
- once joint states arrive again, a bridge that reset a connection publishes its commands from a new ROS node (the
  old one unregisters): the master tells the driver of the new publisher, and it connects at once. The reset never
  reached the driver while the link was cut, so its end of the old connection stays open, with nothing more on it,
  until its keepalive notices (rospy: after 60 s idle) or, in roscpp, at once, as the old publisher left the list.

The commands' publisher therefore lives in a ROS node of its own (``<name>_cmd<N>``), beside the one that
subscribes to the joint states.

The env's placement sets ``max_command_age_s`` to its ``robot_timeout_s``.

The translation, the checks and the ``hold`` and ``stats`` services are the ROS 2 bridge's too (``_bridge.Bridge``,
which ``Ros1Bridge`` and ``Ros2Bridge`` derive from); this module holds the ROS 1 messages, the command guard and
the ROS 1 node that carries them.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import itertools
import logging
import math
import os
import time
from collections.abc import AsyncIterator, Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from uniros_async.adapters._bridge import Bridge, serve_bridge
from uniros_async.adapters.drivers import ros_driver_defaults
from uniros_async.backoff import Backoff
from uniros_async.bus import open_domain, open_node
from uniros_async.bus.messages import JointState
from uniros_async.bus.qos import latest
from uniros_async.errors import ConfigError, RobotError
from uniros_async.robots import get_robot_spec
from uniros_async.robots.spec import RobotSpec
from uniros_async.transports.base import TransportOptions

if TYPE_CHECKING:
    from uniros_async.adapters.ros1 import Ros1Publisher
    from uniros_async.envs.config import EnvConfig
    from uniros_async.placements import ArmLink, PlacementRequest

__all__ = [
    "COMMAND_TYPES",
    "ROS1_SETTINGS",
    "Ros1Bridge",
    "Ros1BridgeConfig",
    "check_ros1_placement",
    "open_ros1_bridge",
    "open_ros1_placement",
    "parse_ros1_uri",
    "serve_ros1_bridge",
]

logger = logging.getLogger(__name__)

COMMAND_TYPES = (
    "interbotix_xs_msgs/JointGroupCommand",
    "trajectory_msgs/JointTrajectory",
    "std_msgs/Float64MultiArray",
)

_instances = itertools.count(1)
ROS1_SETTINGS = (
    "driver",
    "joint_states",
    "command",
    "command_type",
    "group",
    "ros_host",
    "state_timeout_s",
    "max_command_age_s",
    "insecure",
)
"""The bridge settings an env takes in its ``ros1`` dict (``EnvConfig.ros1``)."""


def parse_ros1_uri(uri: str) -> str:
    """``ros1://HOST:PORT`` (an env's ``robot``) -> the master's XML-RPC URI ``http://HOST:PORT/``.

    Raises:
        ConfigError: not of that form.
    """
    rest = uri.removeprefix("ros1://").rstrip("/")
    host, sep, port = rest.rpartition(":")
    if not uri.startswith("ros1://") or not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigError(f"expected a ROS 1 master as ros1://HOST:PORT (e.g. ros1://127.0.0.1:11311), got {uri!r}")
    return f"http://{host}:{int(port)}/"


@dataclasses.dataclass(frozen=True, kw_only=True)
class Ros1BridgeConfig:
    """What the bridge connects: a robot of ours to the topics of its ROS 1 driver.

    Attributes:
        robot: robot name (``rx200``, ``ned2``); its spec gives the joint names, order and limits.
        master_uri: the ROS master (``http://HOST:PORT/``); None: ``$ROS_MASTER_URI``, else
            ``http://127.0.0.1:11311/``.
        driver: which of the robot's registered ROS 1 drivers (``adapters.drivers``) gives the defaults of the
            settings below; None: the robot's default driver.
        joint_states: the driver's ``sensor_msgs/JointState`` topic; None: the driver's default.
        command: the driver's command topic; None: the driver's default.
        command_type: one of ``COMMAND_TYPES``; None: the driver's default.
        group: the joint group of a ``JointGroupCommand``; None: the driver's default, else ``arm`` (Interbotix).
        ros_host: the address ROS peers reach this process at (its XML-RPC and TCPROS servers); None:
            ``$ROS_IP``, else ``$ROS_HOSTNAME`` (as rospy reads them), else ``127.0.0.1``.
        state_timeout_s: how long to wait for the driver's first joint state before giving up.
        max_command_age_s: no command published longer ago than this reaches the driver, and none is sent while
            the newest joint state is older (see the module docstring); None: unguarded. An env's ``ros1://``
            placement sets it to the env's ``robot_timeout_s``.
        node_name: the bridge's name, on the ROS graph and on the bus.
        insecure: allow a ``ros_host`` beyond loopback. ROS 1 cannot authenticate its peers, so its XML-RPC and
            TCPROS listeners on a network address accept anyone who reaches them; without this they refuse to start.
    """

    robot: str
    master_uri: str | None = None
    driver: str | None = None
    joint_states: str | None = None
    command: str | None = None
    command_type: str | None = None
    group: str | None = None
    ros_host: str | None = None
    state_timeout_s: float = 10.0
    max_command_age_s: float | None = 2.0
    node_name: str = "ros1_bridge"
    insecure: bool = False

    def __post_init__(self) -> None:
        spec = get_robot_spec(self.robot)  # ConfigError listing the robots
        driver = ros_driver_defaults("ros1", spec.name, self.driver)  # ConfigError naming the robot's drivers
        defaults = {} if driver is None else driver.as_settings()
        for key in ("joint_states", "command", "command_type"):
            if getattr(self, key) is None:
                if key not in defaults:
                    raise ConfigError(
                        f"Ros1BridgeConfig: robot {self.robot!r} has no ROS 1 driver registered "
                        f"(adapters.drivers.register_ros_driver), so {key} has no default; give one"
                    )
                object.__setattr__(self, key, defaults[key])
        if self.group is None:
            object.__setattr__(self, "group", str(defaults.get("group", "arm")))
        if self.command_type not in COMMAND_TYPES:
            raise ConfigError(
                f"Ros1BridgeConfig.command_type must be one of {COMMAND_TYPES}, got {self.command_type!r}"
            )
        for key in ("joint_states", "command"):
            topic = getattr(self, key)
            if not isinstance(topic, str) or not topic.startswith("/") or len(topic) < 2:
                raise ConfigError(f"Ros1BridgeConfig.{key} must be an absolute ROS topic name like /a/b, got {topic!r}")
        if self.ros_host is None:
            host = os.environ.get("ROS_IP") or os.environ.get("ROS_HOSTNAME") or "127.0.0.1"
            object.__setattr__(self, "ros_host", host)
        if not self.state_timeout_s > 0:
            raise ConfigError(f"Ros1BridgeConfig.state_timeout_s must be > 0, got {self.state_timeout_s}")
        if self.max_command_age_s is not None and not self.max_command_age_s > 0:
            raise ConfigError(
                f"Ros1BridgeConfig.max_command_age_s must be > 0 seconds (or None: unguarded), got "
                f"{self.max_command_age_s}"
            )

    @property
    def spec(self) -> RobotSpec:
        return get_robot_spec(self.robot)


class Ros1Bridge(Bridge[Ros1BridgeConfig]):
    """The translation both ways, for one arm, with ROS 1 messages and the command guard (built by
    ``open_ros1_bridge``)."""

    def __init__(
        self, config: Ros1BridgeConfig, publish: Callable[[JointState], None], now_ns: Callable[[], int]
    ) -> None:
        from uniros_async.adapters.ros1 import msgs

        super().__init__(config, publish, now_ns)
        self.ros_pub: Ros1Publisher[Any] | None = None  # ``run_commands``'s, while it has one (and ``_send``)
        self._msgs = msgs
        self.check_s = min(self.period_s, (config.max_command_age_s or self.period_s) / 4)
        """How often ``run_commands`` looks at the connections to the driver."""

    def driver_stamp_ns(self, msg: Any) -> int:
        """The driver's stamp of a joint state (ROS time, ns; 0 if unstamped)."""
        return int(msg.header.stamp_ns)

    def ros_command(self, q: np.ndarray, duration_s: float = 0.0) -> Any:
        """The driver's command message for arm positions ``q``."""
        m, kind = self._msgs, self.config.command_type
        if kind == "interbotix_xs_msgs/JointGroupCommand":
            return m.JointGroupCommand(name=str(self.config.group), cmd=q.astype(np.float32))
        if kind == "std_msgs/Float64MultiArray":
            return m.Float64MultiArray(data=q.astype(np.float64))
        t_ns = round(max(float(duration_s), self.period_s) * 1e9)
        empty = np.zeros(0)
        point = m.JointTrajectoryPoint(
            positions=q.astype(np.float64), velocities=empty, accelerations=empty, effort=empty, time_from_start_ns=t_ns
        )
        header = m.RosHeader(seq=0, stamp_ns=0, frame_id="")  # stamp 0: start at once (ros_control's convention)
        return m.JointTrajectory(header=header, joint_names=list(self.spec.arm_joint_names), points=[point])

    # ------------------------------------------------------------------------------------------- the guard

    async def run_commands(
        self,
        open_publisher: Callable[[int], contextlib.AbstractAsyncContextManager[Ros1Publisher[Any]]],
        ready: asyncio.Future[None],
    ) -> None:
        """Own the command publisher until cancelled: ``open_publisher(n)`` opens the ``n``-th (a ROS node of its
        own); ``ready`` is resolved once the first is up (or fails with the ``RobotError`` that kept it from
        starting). Guarded (``max_command_age_s``), every ``check_s`` it resets connections whose commands grew
        too old undelivered, and after a reset, once joint states are fresh again, replaces the publisher (the
        module docstring)."""
        generation = 0
        # replacements in quick succession (a link that carries states but not commands) back off, up to 5 s
        backoff = Backoff(first_s=0.5, max_s=5.0)
        replaced = -math.inf  # when the previous replacement was
        while True:
            try:
                async with open_publisher(generation) as pub:
                    self.ros_pub = pub
                    self._send = pub.publish
                    if not ready.done():
                        ready.set_result(None)
                    try:
                        await self._watch(pub)
                    finally:
                        # before the publisher closes: closing its node unregisters it with the master, which can
                        # take seconds while the master is cut off, and a command meanwhile must not reach it
                        self._send = None
            except RobotError as exc:
                if not ready.done():
                    ready.set_exception(exc)
                    return
                logger.warning("%s: cannot publish %s anew (%s); retrying", self.spec.name, self.config.command, exc)
            except Exception as exc:
                if not ready.done():  # open_ros1_bridge raises it
                    ready.set_exception(exc)
                    return
                raise
            finally:
                self._send = None
            generation += 1
            self.stats.command_node_restarts += 1
            if time.monotonic() - replaced > 30.0:
                backoff.reset()
            else:
                await backoff.sleep()
            replaced = time.monotonic()

    async def _watch(self, pub: Ros1Publisher[Any]) -> None:
        """Return when a connection of ``pub`` was reset and the joint states are fresh again; never when
        unguarded."""
        if self.max_age_ns is None:
            await asyncio.Event().wait()
            return
        max_age_s = self.max_age_ns / 1e9
        limit_s = max(max_age_s - self.check_s, max_age_s / 2)
        reset_any = False
        while True:
            await asyncio.sleep(self.check_s)
            stale = self.states_stale()
            reset = pub.abort_undelivered(None if stale else limit_s)
            if reset:
                self.stats.connections_reset += reset
                reset_any = True
                logger.warning(
                    "%s: reset %d connection(s) to %s holding commands the driver had not received (newest joint "
                    "state %.2f s old); they are discarded, never delivered late",
                    self.spec.name,
                    reset,
                    self.config.command,
                    self.state_age_s() or float("inf"),
                )
            if reset_any and not stale:
                return


@contextlib.asynccontextmanager
async def open_ros1_bridge(
    config: Ros1BridgeConfig,
    *,
    domain: Any,
    namespace: str | None = None,
    transport: str = "auto",
    options: TransportOptions | None = None,
) -> AsyncIterator[Ros1Bridge]:
    """Run the bridge for ``config.robot`` as a node of ``domain`` (an open Domain or a URI) until the block ends;
    the node joins with ``transport`` and ``options`` (``open_node``'s).

    Returns once the driver's first joint state has been republished, so an env joining next finds the arm.

    Raises:
        ConfigError: bad settings, or the master cannot be reached (says where and what to start).
        RobotError: no joint state on ``config.joint_states`` within ``config.state_timeout_s``.
    """
    from uniros_async.adapters.ros1 import msgs, open_ros1_node

    spec = config.spec
    base_name = f"/uniros_{config.node_name}_{spec.name}_{os.getpid()}_{next(_instances)}"
    assert config.command_type is not None  # filled in by Ros1BridgeConfig
    cmd_cls = msgs.MESSAGE_TYPES[config.command_type]
    ns = namespace or f"/{spec.name}"
    async with contextlib.AsyncExitStack() as stack:
        ros = await stack.enter_async_context(
            # a name of its own (as rospy's anonymous=True): a second node of the same name would make the master
            # shut this one down, e.g. a training and an evaluation env on one arm
            open_ros1_node(
                base_name,
                master_uri=config.master_uri,
                host=str(config.ros_host),
                insecure=config.insecure,
            )
        )
        node = await stack.enter_async_context(
            open_node(config.node_name, domain=domain, namespace=ns, transport=transport, options=options)
        )
        pub = await node.create_publisher(JointState, "joint_states", qos=latest())
        bridge = Ros1Bridge(config, pub.publish, node.now_ns)

        @contextlib.asynccontextmanager
        async def open_publisher(generation: int) -> AsyncIterator[Ros1Publisher[Any]]:
            async with open_ros1_node(
                f"{base_name}_cmd{generation}",
                master_uri=ros.master_uri,
                host=str(config.ros_host),
                insecure=config.insecure,
            ) as cmd_node:
                yield await cmd_node.advertise(config.command, cmd_cls)

        tasks = await stack.enter_async_context(asyncio.TaskGroup())
        ready: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        commands = tasks.create_task(bridge.run_commands(open_publisher, ready), name=f"ros1 {config.command}")
        stack.callback(commands.cancel)  # runs before the TaskGroup's exit waits for it
        await ready  # RobotError: the master refused or did not answer
        ros_pub = bridge.ros_pub
        assert ros_pub is not None
        await bridge.serve_on(node)
        await ros.subscribe(config.joint_states, msgs.JointState, bridge.on_ros_state)
        t0 = time.monotonic()
        try:
            await asyncio.wait_for(bridge.first_state.wait(), config.state_timeout_s)
        except TimeoutError:
            raise RobotError(
                f"{spec.name}: no sensor_msgs/JointState on {config.joint_states} from the ROS master "
                f"{ros.master_uri} within {config.state_timeout_s} s (is the arm's driver running? `rostopic list` "
                f"on that master shows its topics; Ros1BridgeConfig.joint_states / --joint-states picks another)"
            ) from None
        try:  # the driver connects to our command topic once the master told it we publish: not before now
            await ros_pub.wait_for_subscribers(1, timeout_s=max(config.state_timeout_s - (time.monotonic() - t0), 0.5))
        except TimeoutError:
            raise RobotError(
                f"{spec.name}: nothing on the ROS master {ros.master_uri} subscribes to {config.command} "
                f"({config.command_type}), so commands would go nowhere (is that the driver's command topic? "
                f"`rostopic info {config.command}` shows its subscribers; Ros1BridgeConfig.command / --command "
                f"picks another)"
            ) from None
        bridge.log_bridged(ns, t0)
        yield bridge


async def serve_ros1_bridge(
    config: Ros1BridgeConfig,
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    namespace: str | None = None,
    on_ready: Callable[[str], Any] | None = None,
    options: TransportOptions | None = None,
    tls: bool = False,
) -> None:
    """Run the bridge in an own domain on ``tcp://host:port`` (``tls``: ``tls://host:port``) until cancelled
    (``uniros robot bridge``).

    Args:
        on_ready: called with the domain URI once the arm's joint states flow (the CLI prints it).
        options: the domain's and the bridge node's transport options (``auth_key``; ``insecure`` for a non-loopback
            host without one; ``tls_*`` files, else ``$UNIROS_TLS_*``).
        tls: serve the domain on ``tls://`` (mutual TLS; the certificate must name ``host``).
    """
    await serve_bridge(
        open_ros1_bridge, config, host=host, port=port, namespace=namespace, on_ready=on_ready, options=options, tls=tls
    )


# ------------------------------------------------------------------------------------------------ the placement


def check_ros1_placement(robot: str, config: EnvConfig) -> None:
    """The ``ros1://`` placement's check of an env config: the master's URI and the ``ros1`` settings' names.

    Raises:
        ConfigError: a malformed URI or an unknown setting.
    """
    parse_ros1_uri(robot)
    unknown = sorted(set(config.ros1 or {}) - set(ROS1_SETTINGS))
    if unknown:
        raise ConfigError(f"ros1: unknown setting(s) {unknown}; expected some of {list(ROS1_SETTINGS)}")


@contextlib.asynccontextmanager
async def open_ros1_placement(request: PlacementRequest[EnvConfig]) -> AsyncIterator[ArmLink]:
    """``robot="ros1://HOST:PORT"``: the bridge in the env's process, on a memory domain the env joins as it joins
    an in-process sim; the bridge's settings are the env's ``ros1`` dict over the driver's defaults."""
    from uniros_async.placements import ArmLink

    cfg = request.config
    settings = {"max_command_age_s": cfg.robot_timeout_s, **(cfg.ros1 or {})}
    bridge_cfg = Ros1BridgeConfig(robot=request.robot.name, master_uri=parse_ros1_uri(cfg.robot), **settings)
    async with open_domain("memory://") as domain, open_ros1_bridge(bridge_cfg, domain=domain):
        yield ArmLink(domain=domain)
