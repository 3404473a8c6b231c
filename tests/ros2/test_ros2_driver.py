"""Our servo sim as a ROS 2 driver (adapters/ros2_driver.py), driven through the bridge, and seen by rclpy.

The rx200's xs_sdk speaks ``interbotix_xs_msgs/msg/JointGroupCommand``, which is not on PyPI, so no rclpy node can
play that driver here: the mirror plays it (the real driver's topics, message and QoS), driven by the bridge over
DDS, and an rclpy node checks that the mirror's joint states are what a ROS 2 stack would read. The last test puts
the policy of docs/results.md (trained in accelerated sim) on the emulated real arm served this way, in real time.
"""

from __future__ import annotations

import asyncio
import json
import signal
import subprocess
import sys
from typing import Any

import numpy as np
import pytest
from _ros_helpers import check_bridge_drives_the_mirror, policy_successes

from uniros_async.bench.ros2_peers import kill_process, wait_for_line


@pytest.mark.parametrize(
    ("robot", "uri"),
    [("rx200", "ros2://0"), ("ned2", "ros2://0"), ("rx200", "ros2://0/lab?driver=forward_position_controller")],
)
async def test_bridge_drives_the_sim_through_ros2(robot: str, uri: str) -> None:
    """bus -> bridge -> DDS -> driver -> servo sim -> DDS -> bridge -> bus, with each driver's command type
    (JointGroupCommand for the rx200's xs_sdk, JointTrajectory for the Ned2, Float64MultiArray)."""
    from uniros_async.adapters.ros2_bridge import Ros2BridgeConfig, open_ros2_bridge
    from uniros_async.adapters.ros2_driver import open_ros2_driver

    cfg = Ros2BridgeConfig.from_uri(robot, uri)
    await check_bridge_drives_the_mirror(cfg, open_ros2_driver, open_ros2_bridge)


async def test_rclpy_reads_the_mirror_and_bad_commands_are_dropped(rclpy_peer: Any) -> None:
    from uniros_async.adapters.ros2 import open_ros2_node
    from uniros_async.adapters.ros2.msgs import message_class
    from uniros_async.adapters.ros2_bridge import Ros2BridgeConfig
    from uniros_async.adapters.ros2_driver import open_ros2_driver

    cfg = Ros2BridgeConfig(robot="rx200")
    watch = rclpy_peer("relay", "sensor_msgs/msg/JointState")  # reads /uniros_out: the mirror's, moved there
    moved = Ros2BridgeConfig(robot="rx200", joint_states="/uniros_out")
    async with open_ros2_driver(moved) as driver, open_ros2_node("probe") as probe:
        got = json.loads(await asyncio.to_thread(wait_for_line, watch, "{", timeout_s=20.0))["msg"]
        assert got["name"] == list(cfg.spec.joint_state_names) and len(got["position"]) == 8
        assert got["header"]["stamp"]["sec"] > 1_700_000_000  # wall-clock stamps, as a driver's
        kind = "interbotix_xs_msgs/msg/JointGroupCommand"
        pub = probe.create_publisher("/rx200/commands/joint_group", kind)
        await pub.wait_for_subscribers(1, timeout_s=20.0)
        jgc = message_class(kind)
        pub.publish(jgc(name="gripper", cmd=np.zeros(1, np.float32)))  # another group
        pub.publish(jgc(name="arm", cmd=np.zeros(3, np.float32)))  # 3 of 5 joints
        pub.publish(jgc(name="arm", cmd=np.full(5, 0.1, np.float32)))
        for _ in range(200):
            if driver.commands_in + driver.dropped >= 3:
                break
            await asyncio.sleep(0.02)
        assert driver.dropped == 2 and driver.commands_in == 1


@pytest.mark.slow
def test_cli_serves_the_mirror_until_sigint() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "uniros_async.cli", "robot", "serve", "rx200", "--ros2", "3"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert wait_for_line(proc, "export ROS_DOMAIN_ID=", timeout_s=60.0) == "export ROS_DOMAIN_ID=3"
        assert wait_for_line(proc, "#", timeout_s=5.0).endswith("robot=ros2://3/rx200")

        async def one_state() -> Any:
            from uniros_async.adapters.ros2 import open_ros2_node

            async with open_ros2_node("probe", domain_id=3) as node:
                got: asyncio.Queue[Any] = asyncio.Queue()
                node.create_subscription("/rx200/joint_states", "sensor_msgs/msg/JointState", got.put_nowait)
                return await asyncio.wait_for(got.get(), 20.0)

        state = asyncio.run(one_state())
        assert list(state.name[:5]) == ["waist", "shoulder", "elbow", "wrist_angle", "wrist_rotate"]
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=15.0) == 0
    finally:
        kill_process(proc)


@pytest.mark.slow
def test_sim_trained_policy_on_the_emulated_arm_over_ros2() -> None:
    """Zero-shot, in real time: the dense reach policy of docs/results.md on the emulated real arm, which
    ``uniros robot serve --emulate-real --ros2`` serves as the rx200's ROS 2 driver, reached by ``robot="ros2://0"``
    (the bridge in the env's process). docs/results.md has the 200-episode run of the same."""
    successes = policy_successes(["--ros2", "0"], "export ROS_DOMAIN_ID=0", "ros2://0")
    assert successes >= 2  # 99.5 % over 200 episodes; a wrong joint order or sign gives 0
