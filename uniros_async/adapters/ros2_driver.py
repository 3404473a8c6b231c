"""A simulated arm as a ROS 2 driver: our servo sim, nominal or emulated real, on a ROS 2 domain.

    uniros robot serve rx200 --emulate-real --ros2 0          # serves until SIGINT/SIGTERM
    env = gym.make("uniros/Rx200Reach-v0", robot="ros2://0")  # drives it through the bridge

The mirror of ``ros2_bridge`` (and the ROS 2 twin of ``ros1_driver``). The sim speaks the real driver's topics,
messages and QoS (``ROS2_DRIVERS``):

- it publishes ``sensor_msgs/msg/JointState`` at the hardware rate, reliable with keep last 10 as xs_sdk and
  ros2_control's joint_state_broadcaster do, stamped with the wall clock;
- it takes the driver's command type (reliable, keep last 10): an Interbotix ``JointGroupCommand`` for the group
  ``group``, a ``JointTrajectory`` (its last point, reached at ``time_from_start``), or a ``Float64MultiArray``.

A ROS 2 stack (rclpy nodes, rviz, ros2 topic), or our bridge, can then be tried against real physics and the
emulated arm's noise and delays with no arm attached. A command the sim cannot take (another group, joints missing
or of the wrong count) is logged and counted (``dropped``), never applied.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator, Callable
from typing import Any

import numpy as np

from uniros_async.adapters.ros2_bridge import Ros2BridgeConfig
from uniros_async.bus import open_domain, open_node
from uniros_async.bus.messages import Header, JointCommand, JointState
from uniros_async.bus.qos import latest

__all__ = ["Ros2Driver", "open_ros2_driver", "serve_ros2_driver"]

logger = logging.getLogger(__name__)


class Ros2Driver:
    """The translation both ways for one simulated arm (built by ``open_ros2_driver``)."""

    def __init__(
        self,
        config: Ros2BridgeConfig,
        ros_publish: Callable[[Any], None],
        command: Callable[[Any], None],
        now_ns: Callable[[], int],
    ) -> None:
        from uniros_async.adapters.ros2 import msgs

        self.config = config
        self.spec = config.spec
        self._cls = msgs.message_class
        self._ros_publish = ros_publish
        self._command = command
        self._now_ns = now_ns
        self.domain_id = config.domain_id or 0  # the domain actually used, once open
        self.states_out = 0
        self.commands_in = 0
        self.dropped = 0

    def on_sim_state(self, js: JointState) -> None:
        """Our sim's joint state -> the driver's ``sensor_msgs/msg/JointState``."""
        cls = self._cls
        sec, nsec = divmod(time.time_ns(), 1_000_000_000)
        self._ros_publish(
            cls("sensor_msgs/msg/JointState")(
                header=cls("std_msgs/msg/Header")(
                    stamp=cls("builtin_interfaces/msg/Time")(sec=sec, nanosec=nsec), frame_id=""
                ),
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
        if kind == "interbotix_xs_msgs/msg/JointGroupCommand":
            if msg.name != self.config.group:
                self._drop(f"group {msg.name!r}, not {self.config.group!r}")
                return
            q = np.asarray(msg.cmd, dtype=np.float64)
        elif kind == "trajectory_msgs/msg/JointTrajectory":
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
            duration_s = max(point.time_from_start.sec + point.time_from_start.nanosec / 1e9, 0.0)
        else:
            q = np.asarray(msg.data, dtype=np.float64)
        if q.shape != (len(arm),) or not np.all(np.isfinite(q)):
            self._drop(f"{q.tolist()}: expected {len(arm)} finite positions for the arm joints {arm}")
            return
        self.commands_in += 1
        self._command(JointCommand(header=Header(stamp_ns=self._now_ns()), position=q, duration_s=duration_s))

    def _drop(self, why: str) -> None:
        self.dropped += 1
        logger.warning("%s: ignored a command on %s: %s", self.spec.name, self.config.command, why)


@contextlib.asynccontextmanager
async def open_ros2_driver(
    config: Ros2BridgeConfig, *, emulation: Any = None, servo: Any = None
) -> AsyncIterator[Ros2Driver]:
    """Run ``config.robot``'s servo sim (``emulation``: an ``EmulationConfig`` for the emulated real arm) as a ROS 2
    driver in ``config.domain_id``, on the topics of ``config``, until the block ends.

    Raises:
        ConfigError: cyclonedds / rosbags missing, or a bad domain id.
    """
    from uniros_async.adapters.ros2 import COMMANDS, open_ros2_node
    from uniros_async.sim.node import open_servo_sim

    spec = config.spec
    assert config.command_type is not None and config.joint_states is not None and config.command is not None
    async with contextlib.AsyncExitStack() as stack:
        dom = await stack.enter_async_context(open_domain("memory://"))
        await stack.enter_async_context(open_servo_sim(spec, domain=dom, config=servo, emulation=emulation))
        node = await stack.enter_async_context(open_node("ros2_driver", domain=dom, namespace=f"/{spec.name}"))
        cmd = await node.create_publisher(JointCommand, "command", qos=latest())
        ros = await stack.enter_async_context(
            open_ros2_node(f"uniros_sim_{spec.name}", domain_id=config.domain_id, localhost_only=config.localhost_only)
        )
        ros_js = ros.create_publisher(config.joint_states, "sensor_msgs/msg/JointState", qos=COMMANDS)
        driver = Ros2Driver(config, ros_js.publish, cmd.publish, node.now_ns)
        driver.domain_id = ros.domain_id
        ros.create_subscription(config.command, config.command_type, driver.on_ros_command, qos=COMMANDS)
        await node.create_subscription(JointState, "joint_states", driver.on_sim_state, qos=latest())
        logger.info(
            "%s sim%s as a ROS 2 driver in domain %d: %s, %s (%s)",
            spec.name,
            " (emulated real)" if emulation else "",
            ros.domain_id,
            config.joint_states,
            config.command,
            config.command_type,
        )
        yield driver


async def serve_ros2_driver(
    config: Ros2BridgeConfig,
    *,
    emulation: Any = None,
    servo: Any = None,
    on_ready: Callable[[str], Any] | None = None,
) -> None:
    """``open_ros2_driver`` until cancelled (``uniros robot serve ROBOT --ros2 [DOMAIN_ID]``); ``on_ready`` gets
    the driver's ``ros2://DOMAIN_ID/NAMESPACE`` once the topics are up."""
    async with open_ros2_driver(config, emulation=emulation, servo=servo) as driver:
        if on_ready is not None:
            on_ready(f"ros2://{driver.domain_id}{config.namespace if config.namespace != '/' else ''}")
        await asyncio.Event().wait()  # until cancelled
