"""The ROS 2 bridge against real rclpy nodes in the driver's place.

No physical arm is attached here, so ``rclpy_fake_arm.py`` (real rclpy, Jazzy, Fast DDS) stands in for a
ros2_control arm's driver: it publishes sensor_msgs/msg/JointState at the hardware rate, moves toward the commands
it gets on the controller's topic and prints each as a JSON line, which these tests check. Everything on our side
is the real code: the bridge, our DDS participant, the bus, a real-time env, ``make_vec`` workers and the CLI. The
Interbotix xs_sdk's JointGroupCommand is not on PyPI, so that driver is tested against our mirror
(test_ros2_driver.py).
"""

from __future__ import annotations

import asyncio
import logging
import math
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from _ros_helpers import check_cli_bridge, check_mixed_vec, command_line, joint_command, moved_commands, robot_error

from uniros_async.bench.ros2_peers import kill_process
from uniros_async.bus import open_domain, open_node
from uniros_async.bus.messages import Data, Empty, JointCommand, JointState, Trigger
from uniros_async.errors import RobotError
from uniros_async.robots import get_robot_spec
from uniros_async.testing.tls import write_test_certs

FPC = "forward_position_controller"
JTC = "joint_trajectory_controller"


async def test_states_in_our_order_and_forward_commands_checked(fake_arm: Any) -> None:
    from uniros_async.adapters.ros2_bridge import Ros2BridgeConfig, open_ros2_bridge

    arm = fake_arm("rx200", FPC)
    spec = get_robot_spec("rx200")
    cfg = Ros2BridgeConfig(robot="rx200", driver=FPC)
    async with (
        open_domain("memory://") as dom,
        open_ros2_bridge(cfg, domain=dom) as bridge,
        open_node("env", domain=dom, namespace="/rx200") as env,
    ):
        js = await env.create_subscription(JointState, "joint_states")
        cmd = await env.create_publisher(JointCommand, "command")
        stats = env.create_client(Empty, Data, "stats")
        hold = env.create_client(Empty, Trigger, "hold")
        await cmd.wait_for_subscribers(1, timeout_s=5.0)
        first = await asyncio.wait_for(js.receive(), 5.0)
        assert first.name == spec.joint_state_names
        np.testing.assert_allclose(first.position, 0.0)
        for bad in ([0.0, 2.5, 0.0, 0.0, 0.0], [0.1, 0.2], [0.0, 0.1, 0.0, 0.0, math.nan]):
            cmd.publish(joint_command(bad))  # shoulder beyond +113 deg; two values for five joints; NaN: all refused
            await asyncio.sleep(0.05)  # the command topic keeps the latest only: let each be taken
        target = [0.3, -0.2, 0.25, 0.1, -0.15]
        cmd.publish(joint_command(target))
        got = await command_line(arm)  # the first command the driver sees is the valid one
        assert got["type"] == "std_msgs/msg/Float64MultiArray"
        np.testing.assert_allclose(got["positions"], target)
        elbow_max = spec.joint_upper_rad[2]
        cmd.publish(joint_command([0.3, -0.2, elbow_max + 0.01, 0.1, -0.15]))  # a hair past: clamped, as the servos do
        got = await command_line(arm)
        np.testing.assert_allclose(got["positions"], [0.3, -0.2, elbow_max, 0.1, -0.15])
        counts = (await stats.call(Empty(), timeout_s=5.0)).value
        assert counts["commands_rejected"] == 3 and counts["commands_out"] == 2 and counts["commands_clamped"] == 1
        for _ in range(60):  # the stand-in moves at 1 rad/s at 10 Hz: there within 2 s, seen in our order
            state = await asyncio.wait_for(js.receive(), 5.0)
            if state.position[2] > 1.5:
                break
        assert state.position[2] > 1.5 and state.header.seq > first.header.seq
        reply = await hold.call(Empty(), timeout_s=5.0)
        assert reply.success, reply.message
        held = await command_line(arm)  # hold: the newest measured position
        assert len(held["positions"]) == 5 and held["positions"][2] > 1.5
        assert bridge.stats.states_in >= 5


async def test_ned2_joint_trajectory_commands(fake_arm: Any) -> None:
    from uniros_async.adapters.ros2_bridge import Ros2BridgeConfig, open_ros2_bridge

    arm = fake_arm("ned2", JTC)
    cfg = Ros2BridgeConfig.from_uri("ned2", "ros2://0")  # the Ned2's default driver: a joint_trajectory_controller
    async with (
        open_domain("memory://") as dom,
        open_ros2_bridge(cfg, domain=dom),
        open_node("env", domain=dom, namespace="/ned2") as env,
    ):
        cmd = await env.create_publisher(JointCommand, "command")
        await cmd.wait_for_subscribers(1, timeout_s=5.0)
        cmd.publish(joint_command([0.1, 0.2, -0.3, 0.0, 0.1, 0.0]))
        got = await command_line(arm)
        assert got["type"] == "trajectory_msgs/msg/JointTrajectory"
        assert got["joint_names"] == ["joint_1", "joint_2", "joint_3", "joint_4", "joint_5", "joint_6"]
        np.testing.assert_allclose(got["positions"], [0.1, 0.2, -0.3, 0.0, 0.1, 0.0])
        assert got["time_from_start_s"] == pytest.approx(0.04)  # one 25 Hz period: as soon as the servos can
        cmd.publish(joint_command([0.0] * 6, duration_s=1.5))
        assert (await command_line(arm))["time_from_start_s"] == pytest.approx(1.5)


async def test_silent_driver_or_a_driver_of_another_type_is_a_clear_error(fake_arm: Any) -> None:
    from uniros_async.adapters.ros2_bridge import Ros2BridgeConfig, open_ros2_bridge

    async with open_domain("memory://") as dom:
        cfg = Ros2BridgeConfig.from_uri("rx200", "ros2://4", state_timeout_s=1.0)
        t0 = time.monotonic()
        with pytest.raises((RobotError, BaseExceptionGroup)) as err:
            async with open_ros2_bridge(cfg, domain=dom):
                pass
        text = robot_error(err.value)
        assert "/rx200/joint_states" in text and "domain 4" in text and "within 1.0 s" in text
        assert time.monotonic() - t0 < 5.0
        # a trajectory controller where the bridge was told to expect a position forwarder: refused, naming both
        arm = fake_arm("rx200", JTC, command="/forward_position_controller/commands")
        cfg = Ros2BridgeConfig(robot="rx200", driver=FPC, state_timeout_s=10.0)
        with pytest.raises((RobotError, BaseExceptionGroup)) as err:
            async with open_ros2_bridge(cfg, domain=dom):
                pass
        text = robot_error(err.value)
        assert "/forward_position_controller/commands" in text
        assert "trajectory_msgs/msg/JointTrajectory" in text and "std_msgs/msg/Float64MultiArray" in text
        with pytest.raises(TimeoutError):  # and nothing was sent
            await command_line(arm, timeout_s=1.0)


@pytest.mark.slow
def test_real_time_env_on_a_ros2_arm_and_the_driver_vanishing(fake_arm: Any, caplog: pytest.LogCaptureFixture) -> None:
    """The same TaskEnv as on the sim, on the rclpy arm through ``robot="ros2://..."``: one step's env loop re-sends
    the action at the hardware rate, every command reaching the driver; when the driver dies mid-episode the env's
    robot timeout fires, the arm is told to hold, and the error names the robot and the topic (the bridge's log
    names the driver's topic and domain)."""
    import gymnasium as gym

    import uniros_async  # noqa: F401

    arm = fake_arm("rx200", FPC)
    env = gym.make("uniros/Rx200Reach-v0", robot=f"ros2://0?driver={FPC}", reward_type="dense")
    caplog.set_level(logging.WARNING, logger="uniros_async.adapters.ros2_bridge")
    try:
        obs, info = env.reset(seed=0)
        assert np.all(np.isfinite(obs))
        action = np.array([0.2, 0.1, 0.1, 0.1, 0.0], dtype=np.float32)
        env.step(action)
        t0 = time.monotonic()
        obs, reward, terminated, truncated, info = env.step(action)
        assert 0.7 < time.monotonic() - t0 < 0.9  # one 0.8 s action cycle, in real time
        assert np.all(np.isfinite(obs)) and math.isfinite(reward) and "unsafe_reason" not in info, info
        n, lines = moved_commands(arm, gap_s=0.2, most=40)  # the env loop goes on sending: what came in the two steps
        assert n >= 9, lines  # the action re-sent tick after tick: 10 Hz over two steps (>= 0.9 s)
        kill_process(arm)  # the driver vanishes mid-episode
        with pytest.raises(RobotError) as err:
            for _ in range(10):
                env.step(action)
        assert "rx200" in str(err.value) and "joint_states" in str(err.value) and "hold" in str(err.value)
        warned = [r.getMessage() for r in caplog.records if "no sensor_msgs/msg/JointState" in r.getMessage()]
        assert warned and "/joint_states" in warned[0] and "domain 0" in warned[0], caplog.text
    finally:
        env.close()


@pytest.mark.slow
def test_make_vec_mixes_a_ros2_arm_with_a_sim_arm(fake_arm: Any) -> None:
    """One vector env, two worker processes: the rx200 behind ROS 2 (the bridge in its worker) and a sim rx200."""
    arm = fake_arm("rx200", FPC)
    check_mixed_vec(f"ros2://0?driver={FPC}")
    n, lines = moved_commands(arm, gap_s=0.5, most=100)
    assert n >= 9, lines


@pytest.mark.slow
def test_cli_bridge_serves_a_domain_until_sigint(fake_arm: Any) -> None:
    fake_arm("rx200", FPC)
    check_cli_bridge("--ros2", f"ros2://0?driver={FPC}")


@pytest.mark.slow
def test_cli_bridge_serves_a_domain_on_tls(fake_arm: Any, tmp_path: Path) -> None:
    fake_arm("rx200", FPC)
    check_cli_bridge("--ros2", f"ros2://0?driver={FPC}", tls=write_test_certs(tmp_path / "tls"))


def test_cli_bridge_reports_a_silent_driver() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "uniros_async.cli", "robot", "bridge", "rx200", "--ros2", "9", "--state-timeout", "1"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2, proc.stderr
    assert "/rx200/joint_states" in proc.stderr and "domain 9" in proc.stderr and "Traceback" not in proc.stderr
