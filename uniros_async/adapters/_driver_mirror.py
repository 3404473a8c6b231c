"""What the ROS 1 and ROS 2 driver mirrors share: the command checks, the sim end and serving until cancelled.

A driver mirror (``ros1_driver``, ``ros2_driver``) serves our servo sim on a ROS graph with a real driver's topics
and messages. Both take the same three command types and check them the same way; they differ only in how a
message is spelled (type names, header, durations) and in the ROS node that carries it. ``DriverMirror`` holds the
shared translation, and each subclass names its message types and builds its ``sensor_msgs`` joint state.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from contextlib import AbstractAsyncContextManager
from typing import Any, ClassVar, Protocol, TypeVar

import numpy as np

from uniros_async.bus import open_domain, open_node
from uniros_async.bus.messages import Header, JointCommand, JointState
from uniros_async.bus.node import Node
from uniros_async.bus.pubsub import Publisher
from uniros_async.bus.qos import latest
from uniros_async.robots.spec import RobotSpec

__all__ = ["DriverMirror", "MirrorConfig", "follow_sim_states", "open_sim_end", "serve_until_cancelled"]

D = TypeVar("D")


class MirrorConfig(Protocol):
    """The part of a bridge config (``Ros1BridgeConfig``, ``Ros2BridgeConfig``) a driver mirror reads."""

    @property
    def spec(self) -> RobotSpec: ...  # noqa: D102

    @property
    def joint_states(self) -> str | None: ...  # noqa: D102

    @property
    def command(self) -> str | None: ...  # noqa: D102

    @property
    def command_type(self) -> str | None: ...  # noqa: D102

    @property
    def group(self) -> str | None: ...  # noqa: D102


class DriverMirror:
    """The translation both ways for one simulated arm, whatever ROS carries it.

    Subclasses set ``GROUP_COMMAND`` and ``TRAJECTORY`` (their spelling of the Interbotix and trajectory command
    types; any other command type is read as a ``Float64MultiArray``) and build the ROS messages.

    Attributes:
        states_out: joint states published to ROS.
        commands_in: commands passed on to the sim.
        dropped: commands the sim cannot take (logged, never applied).
    """

    GROUP_COMMAND: ClassVar[str]
    TRAJECTORY: ClassVar[str]

    def __init__(
        self,
        config: MirrorConfig,
        ros_publish: Callable[[Any], None],
        command: Callable[[Any], None],
        now_ns: Callable[[], int],
    ) -> None:
        self.config = config
        self.spec = config.spec
        self._ros_publish = ros_publish
        self._command = command
        self._now_ns = now_ns
        self._logger = logging.getLogger(type(self).__module__)
        self.states_out = 0
        self.commands_in = 0
        self.dropped = 0

    def _ros_joint_state(self, stamp_ns: int, **fields: Any) -> Any:
        """Build the driver's ``sensor_msgs`` joint state stamped ``stamp_ns`` (wall clock) with ``fields``."""
        raise NotImplementedError

    def _time_from_start_s(self, point: Any) -> float:
        """A trajectory point's ``time_from_start``, in seconds."""
        raise NotImplementedError

    def on_sim_state(self, js: JointState) -> None:
        """Our sim's joint state -> the driver's ``sensor_msgs`` joint state, stamped with the wall clock."""
        self._ros_publish(
            self._ros_joint_state(
                time.time_ns(),
                name=list(js.name),
                position=np.asarray(js.position, dtype=np.float64),
                velocity=np.asarray(js.velocity, dtype=np.float64),
                effort=np.asarray(js.effort, dtype=np.float64),
            )
        )
        self.states_out += 1

    def on_ros_command(self, msg: Any) -> None:
        """The driver's command message -> our ``JointCommand`` for the sim."""
        arm = self.spec.arm_joint_names
        duration_s = 0.0
        kind = self.config.command_type
        if kind == self.GROUP_COMMAND:
            if msg.name != self.config.group:
                self._drop(f"group {msg.name!r}, not {self.config.group!r}")
                return
            q = np.asarray(msg.cmd, dtype=np.float64)
        elif kind == self.TRAJECTORY:
            if not msg.points:
                self._drop("a trajectory without points")
                return
            where = {n: i for i, n in enumerate(msg.joint_names)}
            missing = [j for j in arm if j not in where]
            if missing:
                self._drop(f"joints {missing} missing from {list(msg.joint_names)}")
                return
            point = msg.points[-1]
            pos = np.asarray(point.positions, dtype=np.float64)
            if pos.shape != (len(msg.joint_names),):
                self._drop(f"{pos.size} positions for {len(msg.joint_names)} joint names")
                return
            q = pos[[where[j] for j in arm]]
            duration_s = max(self._time_from_start_s(point), 0.0)
        else:
            q = np.asarray(msg.data, dtype=np.float64)
        if q.shape != (len(arm),) or not np.all(np.isfinite(q)):
            self._drop(f"{q.tolist()}: expected {len(arm)} finite positions for the arm joints {arm}")
            return
        self.commands_in += 1
        self._command(JointCommand(header=Header(stamp_ns=self._now_ns()), position=q, duration_s=duration_s))

    def log_serving(self, where: str, *, emulated: bool) -> None:
        """Log that the mirror serves, ``where`` naming its ROS graph (``a ROS 1 driver on URI``)."""
        self._logger.info(
            "%s sim%s as %s: %s, %s (%s)",
            self.spec.name,
            " (emulated real)" if emulated else "",
            where,
            self.config.joint_states,
            self.config.command,
            self.config.command_type,
        )

    def _drop(self, why: str) -> None:
        self.dropped += 1
        self._logger.warning("%s: ignored a command on %s: %s", self.spec.name, self.config.command, why)


async def open_sim_end(
    stack: contextlib.AsyncExitStack,
    spec: RobotSpec,
    node_name: str,
    *,
    emulation: Any = None,
    servo: Any = None,
    on_event: Callable[[dict[str, Any]], None] | None = None,
) -> tuple[Node, Publisher[JointCommand]]:
    """Open ``spec``'s servo sim in an in-process domain, and node ``node_name`` beside it, on ``stack``.

    Args:
        stack: closes the domain, the sim and the node when it closes.
        spec: the robot the sim plays.
        node_name: the mirror's node on the sim's domain, in the namespace ``/ROBOT``.
        emulation: an ``EmulationConfig`` for the emulated real arm; None: the nominal sim.
        servo: the sim's ``ServoSimConfig``; None: the robot's default.
        on_event: gets the sim's command and watchdog events (``ServoSimNode.on_event``).

    Returns:
        The node, and its publisher of the sim's ``command`` topic. Subscribe the mirror to its ``joint_states``.
    """
    from uniros_async.sim.node import open_servo_sim

    dom = await stack.enter_async_context(open_domain("memory://"))
    await stack.enter_async_context(
        open_servo_sim(spec, domain=dom, config=servo, emulation=emulation, on_event=on_event)
    )
    node = await stack.enter_async_context(open_node(node_name, domain=dom, namespace=f"/{spec.name}"))
    cmd = await node.create_publisher(JointCommand, "command", qos=latest())
    return node, cmd


async def follow_sim_states(node: Node, mirror: DriverMirror) -> None:
    """Pass the sim's joint states (``joint_states`` of ``node``) to ``mirror`` from now on."""
    await node.create_subscription(JointState, "joint_states", mirror.on_sim_state, qos=latest())


async def serve_until_cancelled(
    opened: AbstractAsyncContextManager[D],
    on_ready: Callable[[str], Any] | None,
    address: Callable[[D], str],
) -> None:
    """Enter ``opened`` (an ``open_ros*_driver`` block), give ``on_ready`` its ``address``, and wait for cancellation.

    Cancelling leaves ``opened`` closed: its nodes, sim and domain are gone.
    """
    async with opened as driver:
        if on_ready is not None:
            on_ready(address(driver))
        await asyncio.Event().wait()  # until cancelled
