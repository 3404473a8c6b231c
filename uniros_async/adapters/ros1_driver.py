"""A simulated arm as a ROS 1 driver: our servo sim, nominal or emulated real, on a ROS master.

    uniros robot serve rx200 --emulate-real --ros1-master http://127.0.0.1:11311/   # serves until SIGINT/SIGTERM
    env = gym.make("uniros/Rx200Reach-v0", robot="ros1://127.0.0.1:11311")          # drives it through the bridge

The mirror of ``ros1_bridge``. The sim speaks the real driver's topics and messages on the ROS graph
(the robot's ROS 1 driver in ``adapters.drivers``):

- it publishes ``sensor_msgs/JointState`` at the hardware rate, stamped with the wall clock as a driver's are;
- it takes the driver's command type: an Interbotix ``JointGroupCommand`` for the group ``group``, a
  ``JointTrajectory`` (its last point, reached at ``time_from_start``), or a ``Float64MultiArray``.

A ROS 1 pipeline, or our bridge, can then be tried against real physics and the emulated arm's noise and delays
through a real rosmaster, with no arm attached. A command the sim cannot take (another group, joints missing or of
the wrong count) is logged and counted (``dropped``), never applied.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator, Callable
from typing import Any

import numpy as np

from uniros_async.adapters.ros1_bridge import Ros1BridgeConfig
from uniros_async.bus import open_domain, open_node
from uniros_async.bus.messages import Header, JointCommand, JointState
from uniros_async.bus.qos import latest

__all__ = ["Ros1Driver", "open_ros1_driver", "serve_ros1_driver"]

logger = logging.getLogger(__name__)


class Ros1Driver:
    """The translation both ways for one simulated arm (built by ``open_ros1_driver``)."""

    def __init__(
        self,
        config: Ros1BridgeConfig,
        ros_publish: Callable[[Any], None],
        command: Callable[[Any], None],
        now_ns: Callable[[], int],
    ) -> None:
        from uniros_async.adapters.ros1 import msgs

        self.config = config
        self.spec = config.spec
        self._msgs = msgs
        self._ros_publish = ros_publish
        self._command = command
        self._now_ns = now_ns
        self._seq = 0
        self.master_uri = config.master_uri or ""  # the master actually used, once open
        self.states_out = 0
        self.commands_in = 0
        self.dropped = 0

    def on_sim_state(self, js: JointState) -> None:
        """Our sim's joint state -> the driver's ``sensor_msgs/JointState``."""
        self._seq += 1
        m = self._msgs
        self._ros_publish(
            m.JointState(
                header=m.RosHeader(seq=self._seq, stamp_ns=time.time_ns(), frame_id=""),
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
        if kind == "interbotix_xs_msgs/JointGroupCommand":
            if msg.name != self.config.group:
                self._drop(f"group {msg.name!r}, not {self.config.group!r}")
                return
            q = np.asarray(msg.cmd, dtype=np.float64)
        elif kind == "trajectory_msgs/JointTrajectory":
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
            duration_s = max(point.time_from_start_ns / 1e9, 0.0)
        else:
            q = np.asarray(msg.data, dtype=np.float64)
        if q.shape != (len(arm),):
            self._drop(f"{q.size} positions for the {len(arm)} arm joints {arm}")
            return
        self.commands_in += 1
        self._command(JointCommand(header=Header(stamp_ns=self._now_ns()), position=q, duration_s=duration_s))

    def _drop(self, why: str) -> None:
        self.dropped += 1
        logger.warning("%s: ignored a command on %s: %s", self.spec.name, self.config.command, why)


@contextlib.asynccontextmanager
async def open_ros1_driver(
    config: Ros1BridgeConfig,
    *,
    emulation: Any = None,
    servo: Any = None,
    on_event: Callable[[dict[str, Any]], None] | None = None,
) -> AsyncIterator[Ros1Driver]:
    """Run ``config.robot``'s servo sim (``emulation``: an ``EmulationConfig`` for the emulated real arm) as a ROS 1
    driver on ``config.master_uri``, on the topics of ``config``, until the block ends. ``on_event`` gets the sim's
    command and watchdog events (``ServoSimNode.on_event``; a command's age counts from its arrival here, as the
    driver's command messages carry no stamp).

    Raises:
        RobotError: the master cannot be reached (the message names it).
    """
    from uniros_async.adapters.ros1 import msgs, open_ros1_node
    from uniros_async.sim.node import open_servo_sim

    spec = config.spec
    assert config.command_type is not None  # filled in by Ros1BridgeConfig
    async with contextlib.AsyncExitStack() as stack:
        dom = await stack.enter_async_context(open_domain("memory://"))
        await stack.enter_async_context(
            open_servo_sim(spec, domain=dom, config=servo, emulation=emulation, on_event=on_event)
        )
        node = await stack.enter_async_context(open_node("ros1_driver", domain=dom, namespace=f"/{spec.name}"))
        cmd = await node.create_publisher(JointCommand, "command", qos=latest())
        ros = await stack.enter_async_context(
            open_ros1_node(
                f"/uniros_sim_{spec.name}",
                master_uri=config.master_uri,
                host=str(config.ros_host),
                insecure=config.insecure,
            )
        )
        ros_js = await ros.advertise(config.joint_states, msgs.JointState)
        driver = Ros1Driver(config, ros_js.publish, cmd.publish, node.now_ns)
        driver.master_uri = ros.master_uri
        await ros.subscribe(config.command, msgs.MESSAGE_TYPES[config.command_type], driver.on_ros_command)
        await node.create_subscription(JointState, "joint_states", driver.on_sim_state, qos=latest())
        logger.info(
            "%s sim%s as a ROS 1 driver on %s: %s, %s (%s)",
            spec.name,
            " (emulated real)" if emulation else "",
            ros.master_uri,
            config.joint_states,
            config.command,
            config.command_type,
        )
        yield driver


async def serve_ros1_driver(
    config: Ros1BridgeConfig,
    *,
    emulation: Any = None,
    servo: Any = None,
    on_ready: Callable[[str], Any] | None = None,
    on_event: Callable[[dict[str, Any]], None] | None = None,
) -> None:
    """``open_ros1_driver`` until cancelled (``uniros robot serve ROBOT --ros1-master URI``); ``on_ready`` gets the
    master's URI once the topics are up."""
    async with open_ros1_driver(config, emulation=emulation, servo=servo, on_event=on_event) as driver:
        if on_ready is not None:
            on_ready(driver.master_uri)
        await asyncio.Event().wait()  # until cancelled
