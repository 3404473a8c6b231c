"""An arm of ours as a ROS 2 driver: our servo sim, nominal or emulated real, or a Dynamixel bus arm.

    uniros robot serve rx200 --emulate-real --ros2 0          # the sim; serves until SIGINT/SIGTERM
    uniros robot serve rx200 --dxl /dev/ttyDXL --ros2 0       # the arm on its Dynamixel bus
    env = gym.make("uniros/Rx200Reach-v0", robot="ros2://0")  # drives either through the bridge

The mirror of ``ros2_bridge``, sharing the ROS 1 mirror's checks and sim end (``_driver_mirror``). The arm's node
(``joint_states`` and ``command`` in the namespace ``/ROBOT`` of an in-process domain: the servo sim's, or
``DxlArmNode``'s) is mapped to the real driver's topics, messages and QoS (``ROS2_DRIVERS``) by ``mirror_arm``:

- it publishes ``sensor_msgs/msg/JointState`` at the hardware rate, reliable with keep last 10 as xs_sdk and
  ros2_control's joint_state_broadcaster do, stamped with the wall clock;
- it takes the driver's command type (reliable, keep last 10): an Interbotix ``JointGroupCommand`` for the group
  ``group``, a ``JointTrajectory`` (its last point, reached at ``time_from_start``), or a ``Float64MultiArray``.

A ROS 2 stack (rclpy nodes, rviz, ros2 topic), or our bridge, can then be tried against real physics and the
emulated arm's noise and delays with no arm attached, and a bus arm needs no Interbotix install to be a ROS 2
driver. A command the arm cannot take (another group, joints missing or of the wrong count) is logged and counted
(``dropped``), never applied. The bus arm serves no uniros domain beside ROS 2 (its commands come from one side),
moves to each goal with its servos' profile (a trajectory's ``time_from_start`` does not apply), and holds where it
is when the block ends (or, with ``shutdown="rest"``, goes to rest before its torque goes off).
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import AsyncIterator, Callable
from typing import TYPE_CHECKING, Any

from uniros_async.adapters._driver_mirror import DriverMirror, follow_sim_states, open_sim_end, serve_until_cancelled
from uniros_async.adapters.ros2_bridge import Ros2BridgeConfig
from uniros_async.bus import open_domain, open_node
from uniros_async.bus.messages import JointCommand
from uniros_async.bus.qos import latest

if TYPE_CHECKING:
    from uniros_async.bus.node import Node
    from uniros_async.bus.pubsub import Publisher
    from uniros_async.hardware.dxl.servo_map import ServoMap

__all__ = [
    "Ros2Driver",
    "mirror_arm",
    "open_ros2_driver",
    "open_ros2_dxl_driver",
    "serve_ros2_driver",
    "serve_ros2_dxl_driver",
]

logger = logging.getLogger(__name__)


class Ros2Driver(DriverMirror):
    """The translation both ways for one arm (built by ``mirror_arm``), in ROS 2 messages."""

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


async def mirror_arm(
    stack: contextlib.AsyncExitStack,
    config: Ros2BridgeConfig,
    node: Node,
    command: Publisher[JointCommand],
    ros_name: str,
) -> Ros2Driver:
    """Serve the arm ``node`` sees (its ``joint_states``; ``command`` publishes its ``command``, both in the arm's
    namespace) as a ROS 2 driver in ``config.domain_id``, on the topics of ``config``, until ``stack`` closes; the
    ROS 2 participant is the node ``ros_name``.

    Raises:
        ConfigError: cyclonedds / rosbags missing, or a bad domain id.
    """
    from uniros_async.adapters.ros2 import COMMANDS, open_ros2_node

    assert config.command_type is not None and config.joint_states is not None and config.command is not None
    ros = await stack.enter_async_context(
        open_ros2_node(ros_name, domain_id=config.domain_id, localhost_only=config.localhost_only)
    )
    ros_js = ros.create_publisher(config.joint_states, "sensor_msgs/msg/JointState", qos=COMMANDS)
    driver = Ros2Driver(config, ros_js.publish, command.publish, node.now_ns)
    driver.domain_id = ros.domain_id
    ros.create_subscription(config.command, config.command_type, driver.on_ros_command, qos=COMMANDS)
    await follow_sim_states(node, driver)
    return driver


@contextlib.asynccontextmanager
async def open_ros2_driver(
    config: Ros2BridgeConfig, *, emulation: Any = None, servo: Any = None
) -> AsyncIterator[Ros2Driver]:
    """Run ``config.robot``'s servo sim (``emulation``: an ``EmulationConfig`` for the emulated real arm) as a ROS 2
    driver in ``config.domain_id``, on the topics of ``config``, until the block ends.

    Raises:
        ConfigError: cyclonedds / rosbags missing, or a bad domain id.
    """
    async with contextlib.AsyncExitStack() as stack:
        node, cmd = await open_sim_end(stack, config.spec, "ros2_driver", emulation=emulation, servo=servo)
        driver = await mirror_arm(stack, config, node, cmd, f"uniros_sim_{config.spec.name}")
        driver.log_serving(f"a ROS 2 driver in domain {driver.domain_id}", emulated=bool(emulation))
        yield driver


@contextlib.asynccontextmanager
async def open_ros2_dxl_driver(
    config: Ros2BridgeConfig,
    path: str,
    servos: ServoMap,
    *,
    baud: int | None = None,
    margin_s: float | None = None,
    shutdown: str = "hold",
) -> AsyncIterator[Ros2Driver]:
    """Start the arm of ``servos`` on the Dynamixel bus at ``path`` (``placement.open_dxl_arm``, in an in-process
    domain) and serve it as a ROS 2 driver in ``config.domain_id``, on the topics of ``config``, until the block
    ends; then the ROS 2 side closes first, and the arm shuts down by ``shutdown`` (``hold`` or ``rest``).

    Raises:
        ConfigError: cyclonedds / rosbags missing, a bad domain id, or a map of another robot.
        DxlPortError: the port cannot be opened.
        RobotError: the arm's start-up failed, or, at the block's end, the arm failed while it was served.
    """
    from uniros_async.hardware.dxl.placement import open_dxl_arm

    spec = config.spec
    async with contextlib.AsyncExitStack() as stack:
        domain = await stack.enter_async_context(open_domain("memory://"))
        arm = await stack.enter_async_context(
            open_dxl_arm(path, spec, servos, domain=domain, baud=baud, margin_s=margin_s, shutdown=shutdown)
        )
        node = await stack.enter_async_context(open_node("ros2_driver", domain=domain, namespace=f"/{spec.name}"))
        cmd = await node.create_publisher(JointCommand, "command", qos=latest())
        driver = await mirror_arm(stack, config, node, cmd, f"uniros_dxl_{spec.name}")
        logger.info(
            "%s on its bus at %s (%.0f Hz) as a ROS 2 driver in domain %d: %s, %s (%s)",
            spec.name,
            path,
            arm.rate_hz,
            driver.domain_id,
            config.joint_states,
            config.command,
            config.command_type,
        )
        yield driver


def _address(config: Ros2BridgeConfig) -> Callable[[Ros2Driver], str]:
    """The ``ros2://DOMAIN_ID/NAMESPACE`` a served driver of ``config`` is driven by."""
    namespace = config.namespace if config.namespace != "/" else ""
    return lambda driver: f"ros2://{driver.domain_id}{namespace}"


async def serve_ros2_driver(
    config: Ros2BridgeConfig,
    *,
    emulation: Any = None,
    servo: Any = None,
    on_ready: Callable[[str], Any] | None = None,
) -> None:
    """``open_ros2_driver`` until cancelled (``uniros robot serve ROBOT --ros2 [DOMAIN_ID]``); ``on_ready`` gets
    the driver's ``ros2://DOMAIN_ID/NAMESPACE`` once the topics are up."""
    opened = open_ros2_driver(config, emulation=emulation, servo=servo)
    await serve_until_cancelled(opened, on_ready, _address(config))


async def serve_ros2_dxl_driver(
    config: Ros2BridgeConfig,
    path: str,
    servos: ServoMap,
    *,
    baud: int | None = None,
    margin_s: float | None = None,
    shutdown: str = "hold",
    on_ready: Callable[[str], Any] | None = None,
) -> None:
    """``open_ros2_dxl_driver`` until cancelled (``uniros robot serve ROBOT --dxl PATH --ros2 [DOMAIN_ID]``);
    ``on_ready`` gets the driver's ``ros2://DOMAIN_ID/NAMESPACE`` once the arm is up and the topics are."""
    opened = open_ros2_dxl_driver(config, path, servos, baud=baud, margin_s=margin_s, shutdown=shutdown)
    await serve_until_cancelled(opened, on_ready, _address(config))
