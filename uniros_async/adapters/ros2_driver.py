"""A simulated arm as a ROS 2 driver: our servo sim, nominal or emulated real, on a ROS 2 domain.

    uniros robot serve rx200 --emulate-real --ros2 0          # serves until SIGINT/SIGTERM
    env = gym.make("uniros/Rx200Reach-v0", robot="ros2://0")  # drives it through the bridge

The mirror of ``ros2_bridge``, sharing the ROS 1 mirror's checks and sim end (``_driver_mirror``). The sim
speaks the real driver's topics, messages and QoS (``ROS2_DRIVERS``):

- it publishes ``sensor_msgs/msg/JointState`` at the hardware rate, reliable with keep last 10 as xs_sdk and
  ros2_control's joint_state_broadcaster do, stamped with the wall clock;
- it takes the driver's command type (reliable, keep last 10): an Interbotix ``JointGroupCommand`` for the group
  ``group``, a ``JointTrajectory`` (its last point, reached at ``time_from_start``), or a ``Float64MultiArray``.

A ROS 2 stack (rclpy nodes, rviz, ros2 topic), or our bridge, can then be tried against real physics and the
emulated arm's noise and delays with no arm attached. A command the sim cannot take (another group, joints missing
or of the wrong count) is logged and counted (``dropped``), never applied.
"""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator, Callable
from typing import Any

from uniros_async.adapters._driver_mirror import DriverMirror, follow_sim_states, open_sim_end, serve_until_cancelled
from uniros_async.adapters.ros2_bridge import Ros2BridgeConfig

__all__ = ["Ros2Driver", "open_ros2_driver", "serve_ros2_driver"]


class Ros2Driver(DriverMirror):
    """The translation both ways for one simulated arm (built by ``open_ros2_driver``), in ROS 2 messages."""

    GROUP_COMMAND = "interbotix_xs_msgs/msg/JointGroupCommand"
    TRAJECTORY = "trajectory_msgs/msg/JointTrajectory"
    config: Ros2BridgeConfig

    def __init__(
        self,
        config: Ros2BridgeConfig,
        ros_publish: Callable[[Any], None],
        command: Callable[[Any], None],
        now_ns: Callable[[], int],
    ) -> None:
        from uniros_async.adapters.ros2 import msgs

        super().__init__(config, ros_publish, command, now_ns)
        self._cls = msgs.message_class
        self.domain_id = config.domain_id or 0  # the domain actually used, once open

    def _ros_joint_state(self, stamp_ns: int, **fields: Any) -> Any:
        cls = self._cls
        sec, nsec = divmod(stamp_ns, 1_000_000_000)
        stamp = cls("builtin_interfaces/msg/Time")(sec=sec, nanosec=nsec)
        return cls("sensor_msgs/msg/JointState")(header=cls("std_msgs/msg/Header")(stamp=stamp, frame_id=""), **fields)

    def _time_from_start_s(self, point: Any) -> float:
        return float(point.time_from_start.sec + point.time_from_start.nanosec / 1e9)


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

    spec = config.spec
    assert config.command_type is not None and config.joint_states is not None and config.command is not None
    async with contextlib.AsyncExitStack() as stack:
        node, cmd = await open_sim_end(stack, spec, "ros2_driver", emulation=emulation, servo=servo)
        ros = await stack.enter_async_context(
            open_ros2_node(f"uniros_sim_{spec.name}", domain_id=config.domain_id, localhost_only=config.localhost_only)
        )
        ros_js = ros.create_publisher(config.joint_states, "sensor_msgs/msg/JointState", qos=COMMANDS)
        driver = Ros2Driver(config, ros_js.publish, cmd.publish, node.now_ns)
        driver.domain_id = ros.domain_id
        ros.create_subscription(config.command, config.command_type, driver.on_ros_command, qos=COMMANDS)
        await follow_sim_states(node, driver)
        driver.log_serving(f"a ROS 2 driver in domain {ros.domain_id}", emulated=bool(emulation))
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
    namespace = config.namespace if config.namespace != "/" else ""
    opened = open_ros2_driver(config, emulation=emulation, servo=servo)
    await serve_until_cancelled(opened, on_ready, lambda driver: f"ros2://{driver.domain_id}{namespace}")
