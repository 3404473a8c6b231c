"""Our servo sim as a ROS 1 driver (adapters/ros1_driver.py), on a real rosmaster, driven through the bridge.

Both ends are our code here, but everything between them is ROS 1 as a real arm would meet it: a real rosmaster,
registration over XML-RPC, the driver's topics and message types over TCPROS. The last test puts the policy of
docs/results.md (trained in accelerated sim) on the emulated real arm served this way, in real time.
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from uniros_async.bus import open_domain, open_node
from uniros_async.bus.messages import Header, JointCommand, JointState
from uniros_async.testing.ros1 import kill_process, wait_for_line

CHECKPOINT = Path(__file__).resolve().parents[2] / "docs/results/checkpoints/rx200_reach_dense_td3_uniros"


async def _settled_at(js: Any, target: np.ndarray, n: int, timeout_s: float) -> np.ndarray:
    """Receive joint states until the first ``n`` positions are within 0.02 rad of ``target`` (or time runs out)."""
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout_s
    state = await asyncio.wait_for(js.receive(), 5.0)
    while loop.time() < end and not np.allclose(state.position[:n], target, atol=0.02):
        state = await asyncio.wait_for(js.receive(), 5.0)
    return np.asarray(state.position[:n])


@pytest.mark.parametrize("robot", ["rx200", "ned2"])
async def test_bridge_drives_the_sim_through_ros1(ros_master: str, robot: str) -> None:
    """bus -> bridge -> TCPROS -> driver -> servo sim -> TCPROS -> bridge -> bus, each robot with its own command
    type (Interbotix JointGroupCommand, a JointTrajectory)."""
    from uniros_async.adapters.ros1_bridge import Ros1BridgeConfig, open_ros1_bridge
    from uniros_async.adapters.ros1_driver import open_ros1_driver

    cfg = Ros1BridgeConfig(robot=robot, master_uri=ros_master)
    async with (
        open_ros1_driver(cfg) as driver,
        open_domain("memory://") as dom,
        open_ros1_bridge(cfg, domain=dom) as bridge,
        open_node("env", domain=dom, namespace=f"/{robot}") as env,
    ):
        js = await env.create_subscription(JointState, "joint_states")
        cmd = await env.create_publisher(JointCommand, "command")
        await cmd.wait_for_subscribers(1, timeout_s=5.0)
        n = len(cfg.spec.arm_joint_names)
        target = np.linspace(-0.3, 0.3, n)
        cmd.publish(JointCommand(header=Header(), position=target, duration_s=1.0))
        reached = await _settled_at(js, target, n, timeout_s=6.0)  # the servo profile: well within 6 s
        np.testing.assert_allclose(reached, target, atol=0.02)
        assert driver.commands_in == 1 and driver.dropped == 0 and driver.states_out >= 3
        assert bridge.stats.commands_out == 1 and bridge.stats.states_dropped == 0


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
def test_sim_trained_policy_on_the_emulated_arm_over_ros1(ros_master: str, tmp_path: Path) -> None:
    """Zero-shot, in real time: the dense reach policy of docs/results.md on the emulated real arm, which
    ``uniros robot serve --emulate-real --ros1-master`` serves as a ROS 1 driver, reached by ``robot="ros1://..."``."""
    import gymnasium as gym
    from stable_baselines3 import TD3

    import uniros_async  # noqa: F401

    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "uniros_async.cli",
            "robot",
            "serve",
            "rx200",
            "--emulate-real",
            "--ros1-master",
            ros_master,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert wait_for_line(proc, "export ROS_MASTER_URI=", timeout_s=60.0) == f"export ROS_MASTER_URI={ros_master}"
        model = TD3.load(CHECKPOINT / "model.zip", device="cpu")
        port = ros_master.rstrip("/").rsplit(":", 1)[1]
        env = gym.make(
            "uniros/Rx200Reach-v0", robot=f"ros1://127.0.0.1:{port}", reward_type="dense", action_mode="delta"
        )
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
        assert successes >= 2  # 100 % over 200 episodes accelerated; a wrong joint order or sign gives 0
    finally:
        kill_process(proc)
