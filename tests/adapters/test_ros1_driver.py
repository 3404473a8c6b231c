"""Our servo sim as a ROS 1 driver (adapters/ros1_driver.py), on a real rosmaster, driven through the bridge.

Both ends are our code here, but everything between them is ROS 1 as a real arm would meet it: a real rosmaster,
registration over XML-RPC, the driver's topics and message types over TCPROS. The last test puts the policy of
docs/results.md (trained in accelerated sim) on the emulated real arm served this way, in real time.
"""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from _ros_helpers import check_bridge_drives_the_mirror, policy_successes


@pytest.mark.parametrize("robot", ["rx200", "ned2"])
async def test_bridge_drives_the_sim_through_ros1(ros_master: str, robot: str) -> None:
    """bus -> bridge -> TCPROS -> driver -> servo sim -> TCPROS -> bridge -> bus, each robot with its own command
    type (Interbotix JointGroupCommand, a JointTrajectory)."""
    from uniros_async.adapters.ros1_bridge import Ros1BridgeConfig, open_ros1_bridge
    from uniros_async.adapters.ros1_driver import open_ros1_driver

    cfg = Ros1BridgeConfig(robot=robot, master_uri=ros_master)
    await check_bridge_drives_the_mirror(cfg, open_ros1_driver, open_ros1_bridge)


async def test_commands_the_sim_cannot_take_are_dropped(ros_master: str) -> None:
    from uniros_async.adapters.ros1 import msgs, open_ros1_node
    from uniros_async.adapters.ros1_bridge import Ros1BridgeConfig
    from uniros_async.adapters.ros1_driver import open_ros1_driver

    cfg = Ros1BridgeConfig(robot="rx200", master_uri=ros_master)
    async with open_ros1_driver(cfg) as driver, open_ros1_node("/probe", master_uri=ros_master) as probe:
        pub = await probe.advertise("/rx200/commands/joint_group", msgs.JointGroupCommand)
        await pub.wait_for_subscribers(1, timeout_s=5.0)
        pub.publish(msgs.JointGroupCommand(name="gripper", cmd=np.zeros(1, np.float32)))  # another group
        pub.publish(msgs.JointGroupCommand(name="arm", cmd=np.zeros(3, np.float32)))  # 3 of 5 joints
        pub.publish(msgs.JointGroupCommand(name="arm", cmd=np.full(5, 0.1, np.float32)))
        for _ in range(100):
            if driver.commands_in + driver.dropped >= 3:
                break
            await asyncio.sleep(0.02)
        assert driver.dropped == 2 and driver.commands_in == 1


@pytest.mark.slow
def test_sim_trained_policy_on_the_emulated_arm_over_ros1(ros_master: str) -> None:
    """Zero-shot, in real time: the dense reach policy of docs/results.md on the emulated real arm, which
    ``uniros robot serve --emulate-real --ros1-master`` serves as a ROS 1 driver, reached by ``robot="ros1://..."``."""
    port = ros_master.rstrip("/").rsplit(":", 1)[1]
    ready = f"export ROS_MASTER_URI={ros_master}"
    successes = policy_successes(["--ros1-master", ros_master], ready, f"ros1://127.0.0.1:{port}")
    assert successes >= 2  # 100 % over 200 episodes accelerated; a wrong joint order or sign gives 0
