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
the wrong count) is logged and counted (``dropped``), never applied. The checks and the sim end are shared with
the ROS 2 mirror (``_driver_mirror``); this module holds what ROS 1 spells its own way.
"""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator, Callable
from typing import Any

from uniros_async.adapters._driver_mirror import DriverMirror, follow_sim_states, open_sim_end, serve_until_cancelled
from uniros_async.adapters.ros1_bridge import Ros1BridgeConfig

__all__ = ["Ros1Driver", "open_ros1_driver", "serve_ros1_driver"]


class Ros1Driver(DriverMirror):
    """The translation both ways for one simulated arm (built by ``open_ros1_driver``), in ROS 1 messages."""

    GROUP_COMMAND = "interbotix_xs_msgs/JointGroupCommand"
    TRAJECTORY = "trajectory_msgs/JointTrajectory"
    config: Ros1BridgeConfig

    def __init__(
        self,
        config: Ros1BridgeConfig,
        ros_publish: Callable[[Any], None],
        command: Callable[[Any], None],
        now_ns: Callable[[], int],
    ) -> None:
        from uniros_async.adapters.ros1 import msgs

        super().__init__(config, ros_publish, command, now_ns)
        self._msgs = msgs
        self._seq = 0
        self.master_uri = config.master_uri or ""  # the master actually used, once open

    def _ros_joint_state(self, stamp_ns: int, **fields: Any) -> Any:
        self._seq += 1
        m = self._msgs
        return m.JointState(header=m.RosHeader(seq=self._seq, stamp_ns=stamp_ns, frame_id=""), **fields)

    def _time_from_start_s(self, point: Any) -> float:
        return float(point.time_from_start_ns) / 1e9


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

    spec = config.spec
    assert config.command_type is not None and config.joint_states is not None and config.command is not None
    async with contextlib.AsyncExitStack() as stack:
        node, cmd = await open_sim_end(stack, spec, "ros1_driver", emulation=emulation, servo=servo, on_event=on_event)
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
        await follow_sim_states(node, driver)
        driver.log_serving(f"a ROS 1 driver on {ros.master_uri}", emulated=bool(emulation))
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
    opened = open_ros1_driver(config, emulation=emulation, servo=servo, on_event=on_event)
    await serve_until_cancelled(opened, on_ready, lambda driver: driver.master_uri)
