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
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from uniros_async.bus import open_domain, open_node
from uniros_async.bus.messages import Header, JointCommand, JointState
from uniros_async.testing.ros2 import kill_process, wait_for_line

CHECKPOINT = Path(__file__).resolve().parents[2] / "docs/results/checkpoints/rx200_reach_dense_td3_uniros"


async def _settled_at(js: Any, target: np.ndarray, n: int, timeout_s: float) -> np.ndarray:
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout_s
    state = await asyncio.wait_for(js.receive(), 5.0)
    while loop.time() < end and not np.allclose(state.position[:n], target, atol=0.02):
        state = await asyncio.wait_for(js.receive(), 5.0)
    return np.asarray(state.position[:n])


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
    async with (
        open_ros2_driver(cfg) as driver,
        open_domain("memory://") as dom,
        open_ros2_bridge(cfg, domain=dom) as bridge,
        open_node("env", domain=dom, namespace=f"/{robot}") as env,
    ):
        js = await env.create_subscription(JointState, "joint_states")
        cmd = await env.create_publisher(JointCommand, "command")
        await cmd.wait_for_subscribers(1, timeout_s=5.0)
        n = len(cfg.spec.arm_joint_names)
        target = np.linspace(-0.3, 0.3, n)
        cmd.publish(JointCommand(header=Header(), position=target, duration_s=1.0))
        reached = await _settled_at(js, target, n, timeout_s=6.0)
        np.testing.assert_allclose(reached, target, atol=0.02)
        assert driver.commands_in == 1 and driver.dropped == 0 and driver.states_out >= 3
        assert bridge.stats.commands_out == 1 and bridge.stats.states_dropped == 0


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
    import gymnasium as gym
    from stable_baselines3 import TD3

    import uniros_async  # noqa: F401

    proc = subprocess.Popen(
        [sys.executable, "-m", "uniros_async.cli", "robot", "serve", "rx200", "--emulate-real", "--ros2", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert wait_for_line(proc, "export ROS_DOMAIN_ID=", timeout_s=60.0) == "export ROS_DOMAIN_ID=0"
        model = TD3.load(CHECKPOINT / "model.zip", device="cpu")
        env = gym.make("uniros/Rx200Reach-v0", robot="ros2://0", reward_type="dense", action_mode="delta")
        successes = 0
        try:
            for episode in range(3):
                obs, _ = env.reset(seed=episode)
                for _ in range(30):
                    action, _ = model.predict(obs, deterministic=True)
                    obs, _, terminated, truncated, info = env.step(action)
                    if terminated or truncated:
                        break
                successes += bool(info.get("is_success"))
        finally:
            env.close()
        assert successes >= 2  # 99.5 % over 200 episodes; a wrong joint order or sign gives 0
    finally:
        kill_process(proc)
