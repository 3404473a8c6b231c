"""``robot="dxl://..."``: a real-time env on an arm on its (virtual) bus, in the env's process and in make_vec
workers, and the servos' watchdog after the env's process is SIGKILLed."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time

import gymnasium as gym
import numpy as np
import pytest

import uniros_async
from uniros_async.errors import RobotError, UnirosError

from ._vbus import MARGIN_MS, read, running_vbus, sdk_port

pytestmark = pytest.mark.slow

Q = slice(7, 12)
"""The rx200 reach observation's arm joint positions (after the EE position, the goal direction and distance)."""


def test_real_time_env_on_a_bus_arm_and_a_silent_servo_is_a_robot_error() -> None:
    with running_vbus() as vbus:
        env = gym.make(
            "uniros/Rx200Reach-v0",
            robot=f"dxl://{vbus.path}?map=rx200&margin_ms={MARGIN_MS}",
            robot_timeout_s=1.0,
            action_cycle_s=0.2,
        )
        try:
            obs, _ = env.reset(seed=0)
            q0 = obs[Q].copy()  # the joint positions
            action = np.zeros(env.action_space.shape, dtype=np.float32)
            action[0] = env.action_space.high[0]  # the waist, one way
            times = []
            for _ in range(8):
                t = time.monotonic()
                obs, *_ = env.step(action)
                times.append(time.monotonic() - t)
            assert obs[Q][0] - q0[0] > 0.02, f"the waist did not move on the bus: {q0[0]} -> {obs[Q][0]}"
            # real time: a step takes its action cycle on the wall clock
            assert 0.17 < float(np.median(times)) < 0.23, times
            assert vbus.send("silent 4") == "ok silent 4"
            t = time.monotonic()
            errors: list[UnirosError] = []
            for _ in range(20):
                try:
                    env.step(action)
                except UnirosError as exc:
                    # steps while the env's loop is being torn down (the arm's shutdown) meet its closed
                    # publishers; once it ended, a step reports what ended it
                    errors.append(exc)
                    if isinstance(exc, RobotError):
                        break
                    time.sleep(0.05)
            assert errors and isinstance(errors[-1], RobotError), errors
            assert "joint 'elbow' (servo ID 4) does not answer" in str(errors[-1])
            assert time.monotonic() - t < 1.0 + 0.5, "no RobotError within the robot timeout"
        finally:
            env.close()


def test_make_vec_mixes_a_bus_arm_with_a_sim_arm() -> None:
    with running_vbus() as vbus:
        envs = uniros_async.make_vec(
            [
                ("uniros/Rx200Reach-v0", {"robot": f"dxl://{vbus.path}?map=rx200&margin_ms={MARGIN_MS}"}),
                ("uniros/Rx200Reach-v0", {"robot": "sim"}),
            ]
        )
        try:
            obs, _ = envs.reset(seed=1)
            start = obs[:, Q].copy()
            actions = np.zeros(envs.action_space.shape, dtype=np.float32)
            actions[:, 0] = envs.single_action_space.high[0]
            for _ in range(5):
                obs, *_ = envs.step(actions)
            assert (obs[:, Q][:, 0] - start[:, 0] > 0.02).all(), (start[:, 0], obs[:, Q][:, 0])
        finally:
            envs.close()
        with sdk_port(vbus.path) as (port, ph):
            # the worker's shutdown held the arm: torque on, goal where it was (a moving arm stops a hair past it)
            assert read(ph, port, 1, 64, 1) == 1
            assert abs(read(ph, port, 1, 116, 4) - read(ph, port, 1, 132, 4)) <= 10


_ENV_PROCESS = textwrap.dedent(
    """
    import sys
    import gymnasium as gym
    import numpy as np
    import uniros_async
    env = gym.make("uniros/Rx200Reach-v0", robot=f"dxl://{sys.argv[1]}?map=rx200&margin_ms={sys.argv[2]}")
    env.reset(seed=0)
    action = np.zeros(env.action_space.shape, dtype=np.float32)
    action[0] = env.action_space.high[0]
    print("stepping", flush=True)
    while True:
        env.step(action)
    """
)


def test_servos_stop_and_hold_within_the_watchdog_time_after_the_env_process_is_killed() -> None:
    with running_vbus() as vbus:
        env_process = subprocess.Popen(
            [sys.executable, "-c", _ENV_PROCESS, vbus.path, str(MARGIN_MS)], stdout=subprocess.PIPE, text=True
        )
        try:
            assert env_process.stdout is not None
            assert env_process.stdout.readline().strip() == "stepping"
            time.sleep(0.5)
            env_process.send_signal(signal.SIGKILL)
            killed = time.monotonic()
            env_process.wait(10)
        finally:
            if env_process.poll() is None:
                env_process.kill()
                env_process.wait()
            assert env_process.stdout is not None
            env_process.stdout.close()
        tripped: dict[int, float] = {}
        while len(tripped) < 7:
            line = vbus.expect(("watchdog id=",), 2.0)
            servo_id = int(line.split()[1].removeprefix("id="))
            tripped[servo_id] = float(line.rsplit("t=", 1)[1])
        assert sorted(tripped) == [1, 2, 3, 4, 5, 6, 7]
        worst = max(tripped.values()) - killed
        assert worst <= 0.100 + 0.015, f"the last servo stopped {worst * 1e3:.0f} ms after the kill"
        time.sleep(0.4)
        with sdk_port(vbus.path) as (port, ph):
            first = [read(ph, port, i, 132, 4) for i in range(1, 7)]
            time.sleep(0.3)
            second = [read(ph, port, i, 132, 4) for i in range(1, 7)]
            assert max(abs(a - b) for a, b in zip(first, second, strict=True)) <= 2, (first, second)
            assert all(read(ph, port, i, 64, 1) == 1 for i in range(1, 7))  # held, torque on
