"""A frozen arm (its process stopped with SIGSTOP, then resumed with SIGCONT): no step or reset is built on its
last joint state, both report it within ``robot_timeout_s``, and the same env carries on once it runs again.

Needs no namespaces: the served arm is the env's own child process (``robot="sim-process"`` teleports home on
reset, ``robot="emulated-real"`` moves home and settles).
"""

from __future__ import annotations

import os
import signal
import time

import gymnasium as gym
import numpy as np
import pytest

import uniros_async  # noqa: F401  (registers the ids)
from uniros_async.errors import RobotError

pytestmark = pytest.mark.slow

TIMEOUT_S = 0.5
CYCLE_S = 0.2
SLACK_S = 1.0
"""Scheduling slack on a shared 2-core machine, beyond the robot timeout and one action cycle."""


@pytest.mark.parametrize("robot", ["sim-process", "emulated-real"])
def test_frozen_arm_fails_step_and_reset_then_recovers(robot: str) -> None:
    env = gym.make("uniros/Rx200Reach-v0", robot=robot, action_cycle_s=CYCLE_S, robot_timeout_s=TIMEOUT_S)
    u = env.unwrapped
    pid = u.robot_process.pid
    zero = np.zeros(env.action_space.shape, np.float32)
    try:
        env.reset(seed=0)
        env.step(zero)
        os.kill(pid, signal.SIGSTOP)
        t0 = time.monotonic()
        with pytest.raises(RobotError, match=r"rx200: step: the newest joint state .* s old"):
            for _ in range(20):
                env.step(zero)
        assert time.monotonic() - t0 < TIMEOUT_S + CYCLE_S + SLACK_S
        for _ in range(3):  # again and again: never a reset on the old state
            t1 = time.monotonic()
            with pytest.raises(RobotError, match=r"rx200: reset.* joint state .* s old") as err:
                env.reset()
            assert time.monotonic() - t1 < TIMEOUT_S + SLACK_S
            age = float(str(err.value).split(" s old")[0].rsplit(" ", 1)[1])
            assert age > TIMEOUT_S, err.value
        # while frozen, the loop builds nothing and sends nothing: three more ticks find the state stale
        sent = len(u.timing.command_ns)
        stale = u.timing.stale_ticks
        deadline = time.monotonic() + 3 * 0.1 + SLACK_S  # the rx200's ticks are 0.1 s apart
        while u.timing.stale_ticks < stale + 3:
            assert time.monotonic() < deadline, f"the env loop ticked {u.timing.stale_ticks - stale} times"
            time.sleep(0.01)
        assert len(u.timing.command_ns) == sent
        os.kill(pid, signal.SIGCONT)
        obs, _ = env.reset()  # the same env, no restart
        _, _, _, _, info = env.step(zero)
        assert u._state_age_s() < TIMEOUT_S
        assert np.all(np.isfinite(obs))
    finally:
        os.kill(pid, signal.SIGCONT)
        env.close()
