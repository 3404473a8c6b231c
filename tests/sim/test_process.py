"""The servo sim in its own process (same domain) and the emulated real arm served over tcp from another process."""

from __future__ import annotations

import asyncio
import os
import signal
import sys
from collections.abc import Callable

import numpy as np
import pytest

from uniros_async.bus import Subscription, open_domain, open_node
from uniros_async.bus.messages import Header, JointCommand, JointState
from uniros_async.errors import ConfigError
from uniros_async.sim.serve import open_servo_sim_process

pytestmark = pytest.mark.slow


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


async def state_where(
    states: Subscription[JointState], predicate: Callable[[JointState], bool], timeout_s: float = 5.0
) -> JointState:
    """The first joint state (newest first) that satisfies ``predicate``, within ``timeout_s``."""
    async with asyncio.timeout(timeout_s):
        msg = states.latest()
        while msg is None or not predicate(msg):
            msg = await states.receive()
    return msg


async def test_servo_sim_in_its_own_process_joins_the_domain() -> None:
    async with open_domain("tcp://127.0.0.1:0") as domain:
        async with open_servo_sim_process("ned2", domain=domain) as proc, open_node("env", domain=domain) as env:
            assert proc.is_alive() and proc.pid != os.getpid()
            states = await env.create_subscription(JointState, "/ned2/joint_states")
            pub = await env.create_publisher(JointCommand, "/ned2/command")
            await states.wait_for_publishers(1, timeout_s=5)
            await pub.wait_for_subscribers(1, timeout_s=5)
            await state_where(states, lambda m: True)
            pub.publish(JointCommand(header=Header(), position=np.array([0.6, 0, 0, 0, 0, 0])))
            await state_where(states, lambda m: abs(m.position[0] - 0.6) < 0.03)
            pid = proc.pid
        assert pid is not None and not _pid_alive(pid), "no servo sim process outlives the block"
    with pytest.raises(ConfigError, match="tcp"):
        async with open_servo_sim_process("ned2", domain="memory://x"):
            pass


async def test_emulated_real_arm_is_reached_over_tcp_from_another_process() -> None:
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "uniros_async.sim.cli",
        "serve",
        "rx200",
        "--port",
        "0",
        "--emulate-real",
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    assert proc.stdout is not None
    try:
        async with asyncio.timeout(30):
            line = (await proc.stdout.readline()).decode()
        assert line.startswith("export UNIROS_DOMAIN=tcp://127.0.0.1:"), f"expected the domain to join, got {line!r}"
        uri = line.strip().removeprefix("export UNIROS_DOMAIN=")
        async with open_node("trainer", domain=uri) as env:
            states = await env.create_subscription(JointState, "/rx200/joint_states")
            pub = await env.create_publisher(JointCommand, "/rx200/command")
            await states.wait_for_publishers(1, timeout_s=5)
            await pub.wait_for_subscribers(1, timeout_s=5)
            start = await state_where(states, lambda m: True)
            assert start.name[:5] == ("waist", "shoulder", "elbow", "wrist_angle", "wrist_rotate")
            goal = np.array([0.5, 0.2, -0.3, 0.4, 0.0])
            for _ in range(10):  # the env's action repeat; the emulated network delays each one
                pub.publish(JointCommand(header=Header(stamp_ns=env.now_ns()), position=goal))
                await asyncio.sleep(0.1)
            await state_where(states, lambda m: bool(np.abs(m.position[:5] - goal).max() < 0.05))
    finally:
        if proc.returncode is None:
            proc.send_signal(signal.SIGTERM)
        try:
            async with asyncio.timeout(10):
                _, err = await proc.communicate()
        except TimeoutError:
            proc.kill()
            _, err = await proc.communicate()
    assert proc.returncode == 0, f"serve exited with {proc.returncode}: {err.decode()}"
