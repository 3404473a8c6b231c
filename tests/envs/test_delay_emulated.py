"""A constant delay past the robot timeout, from the start, on the emulated arm's latency model: no network namespace.

The arm is ``serve_servo_sim`` in a process of its own (a tcp domain on loopback, the wall clock), the emulated real
arm with its state and command latency set to a constant 1.5 robot timeouts each way and its watchdog at the robot
timeout; it writes its command and hold events (``trace``) on stdout. The env (wall clock, this process) joins it.
Every state then arrives equally late, so the quickest-state estimate alone would see none of the delay; the arm's
echo of our commands shows the round trip (``envs.transit``): the reset raises RobotError naming the delay, the env
sends nothing after it, and the arm holds by its watchdog within the robot timeout and a control period of the last
command it took. tests/faults/test_tcp_arm_delay.py does the same through a delaying relay in the netns rig.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from typing import Any

import gymnasium as gym
import pytest

from uniros_async.errors import RobotError

pytestmark = pytest.mark.slow

ROBOT_TIMEOUT_S = 0.5
DELAY_S = 1.5 * ROBOT_TIMEOUT_S
PERIOD_S = 0.1  # the rx200's 10 Hz
SLACK_S = 0.05
"""The code path of the hosts' loops and a loaded machine's scheduling."""

ARM = f"""
import asyncio, dataclasses, sys
from uniros_async.sim.emulated import EmulationConfig, LatencyModel
from uniros_async.sim.serve import ServeConfig, serve_servo_sim
from uniros_async.sim.servo import ServoSimConfig
line = LatencyModel(base_s={DELAY_S}, jitter_s=0.0, distribution="constant")
emu = dataclasses.replace(EmulationConfig.nominal(), state_latency=line, command_latency=line)
servo = ServoSimConfig(command_timeout_s={ROBOT_TIMEOUT_S})
config = ServeConfig(robot="rx200", servo=servo, emulation=emu, trace=True)
asyncio.run(serve_servo_sim(config, on_ready=lambda uri: print("ready", uri, flush=True)))
"""


class Arm:
    """The arm's process; its event lines read on a thread."""

    def __init__(self) -> None:
        self.proc = subprocess.Popen([sys.executable, "-c", ARM], stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None
        first = self.proc.stdout.readline().split()
        assert first[:1] == ["ready"], first
        self.uri = first[1]
        self.events: list[dict[str, Any]] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.startswith("{"):
                self.events.append(json.loads(line))

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)
        self._reader.join(10)
        assert self.proc.stdout is not None
        self.proc.stdout.close()


def test_a_constant_delay_past_the_robot_timeout_raises_and_the_arm_holds() -> None:
    arm = Arm()
    try:
        env = gym.make(
            "uniros/Rx200Reach-v0",
            robot=arm.uri,
            clock="wall",
            robot_timeout_s=ROBOT_TIMEOUT_S,
            action_cycle_s=0.2,
            goal_pool=8,
        )
        try:
            with pytest.raises(RobotError, match="round trip|echoed none of our commands") as info:
                env.reset(seed=0)
            raised_ns = time.monotonic_ns()
            sent = list(env.unwrapped.timing.command_ns)
            assert sent, "the reset sent no command"
            time.sleep(DELAY_S + ROBOT_TIMEOUT_S + 3 * PERIOD_S)  # what was in flight lands; the watchdog holds
            # the env sent nothing after the error: its first reset's commands only, all before it raised
            assert list(env.unwrapped.timing.command_ns) == sent and max(sent) <= raised_ns
        finally:
            env.close()
        message = str(info.value)
        assert "s old" in message, message
        commands = [e for e in arm.events if e["ev"] == "cmd"]
        holds = [e for e in arm.events if e["ev"] == "hold"]
        assert commands, arm.events
        last_cmd_ns = max(e["t_ns"] for e in commands)
        # every command the arm took came the constant delay late; the last one came after the env stopped sending
        assert min(e["age_ns"] for e in commands) >= (DELAY_S - SLACK_S) * 1e9, commands
        after = [e["t_ns"] for e in holds if e["t_ns"] > last_cmd_ns]
        assert after, arm.events
        held_s = (min(after) - last_cmd_ns) / 1e9
        print(f"raised: {message}\nthe arm held {held_s:.3f} s after the last command it took")
        assert held_s <= ROBOT_TIMEOUT_S + PERIOD_S + SLACK_S, held_s
    finally:
        arm.stop()
