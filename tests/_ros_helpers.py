"""Checks the ROS 1 tests (tests/adapters) and the ROS 2 tests (tests/ros2) share: one bridge or mirror is driven
the same way whichever ROS carries it, so the same steps and assertions serve both.

Imported as ``_ros_helpers``: tests/ is on ``sys.path`` (pytest's default import mode puts the folder of
tests/conftest.py there), in a network namespace's pytest too.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import signal
import subprocess
import sys
from collections.abc import Callable
from contextlib import AbstractAsyncContextManager
from pathlib import Path
from typing import Any

import numpy as np

from uniros_async.bench.ros1_peers import kill_process, wait_for_line
from uniros_async.bus import open_domain, open_node
from uniros_async.bus.messages import Header, JointCommand, JointState
from uniros_async.errors import RobotError
from uniros_async.robots import get_robot_spec
from uniros_async.testing.tls import TlsFiles

CHECKPOINT = Path(__file__).resolve().parents[1] / "docs/results/checkpoints/rx200_reach_dense_td3_uniros"
"""The dense reach policy of docs/results.md, trained in accelerated sim (its weights: training/weights.py)."""


def joint_command(q: list[float], duration_s: float = 0.0) -> JointCommand:
    """A command to the arm joints ``q`` (rad), reached in ``duration_s`` (0: as soon as the servos can)."""
    return JointCommand(header=Header(), position=np.asarray(q, dtype=np.float64), duration_s=duration_s)


async def command_line(proc: subprocess.Popen[str], timeout_s: float = 10.0) -> dict[str, Any]:
    """The next command a stand-in arm printed (one JSON line)."""
    line = await asyncio.to_thread(wait_for_line, proc, "{", timeout_s=timeout_s)
    return dict(json.loads(line))


def moved_commands(proc: subprocess.Popen[str], *, gap_s: float, most: int = 1000) -> tuple[int, list[dict[str, Any]]]:
    """The commands a stand-in arm printed until it printed none for ``gap_s`` (at most ``most``): how many of them
    command a position away from zero, and all of them."""
    lines: list[dict[str, Any]] = []
    with contextlib.suppress(TimeoutError):
        while len(lines) < most:
            lines.append(json.loads(wait_for_line(proc, "{", timeout_s=gap_s)))
    return sum(any(abs(v) > 1e-4 for v in ln["positions"]) for ln in lines), lines


def plain_fields(msg: Any) -> Any:
    """A rosbags message as plain values (what tests/ros2/rclpy_peer.py prints for rclpy's)."""
    if dataclasses.is_dataclass(msg):
        return {f.name: plain_fields(getattr(msg, f.name)) for f in dataclasses.fields(msg) if f.name != "__msgtype__"}
    if isinstance(msg, np.ndarray):
        return msg.tolist()
    if isinstance(msg, list | tuple):
        return [plain_fields(v) for v in msg]
    return msg


def robot_error(exc: BaseException) -> str:
    """The message of the RobotError inside a task group's wrapping."""
    while isinstance(exc, BaseExceptionGroup):
        exc = exc.exceptions[0]
    assert isinstance(exc, RobotError), repr(exc)
    return str(exc)


async def settled_at(js: Any, target: np.ndarray, n: int, timeout_s: float) -> np.ndarray:
    """Receive joint states until the first ``n`` positions are within 0.02 rad of ``target`` (or time runs out)."""
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout_s
    state = await asyncio.wait_for(js.receive(), 5.0)
    while loop.time() < end and not np.allclose(state.position[:n], target, atol=0.02):
        state = await asyncio.wait_for(js.receive(), 5.0)
    return np.asarray(state.position[:n])


async def check_bridge_drives_the_mirror(
    cfg: Any,
    open_driver: Callable[[Any], AbstractAsyncContextManager[Any]],
    open_bridge: Callable[..., AbstractAsyncContextManager[Any]],
) -> None:
    """bus -> bridge -> ROS -> driver mirror -> servo sim -> ROS -> bridge -> bus: one target reached, each message
    counted once, nothing dropped. ``cfg`` is the bridge config both ends read."""
    robot = cfg.spec.name
    async with (
        open_driver(cfg) as driver,
        open_domain("memory://") as dom,
        open_bridge(cfg, domain=dom) as bridge,
        open_node("env", domain=dom, namespace=f"/{robot}") as env,
    ):
        js = await env.create_subscription(JointState, "joint_states")
        cmd = await env.create_publisher(JointCommand, "command")
        await cmd.wait_for_subscribers(1, timeout_s=5.0)
        n = len(cfg.spec.arm_joint_names)
        target = np.linspace(-0.3, 0.3, n)
        cmd.publish(JointCommand(header=Header(), position=target, duration_s=1.0))
        reached = await settled_at(js, target, n, timeout_s=6.0)  # the servo profile: well within 6 s
        np.testing.assert_allclose(reached, target, atol=0.02)
        assert driver.commands_in == 1 and driver.dropped == 0 and driver.states_out >= 3
        assert bridge.stats.commands_out == 1 and bridge.stats.states_dropped == 0


def check_cli_bridge(*args: str, host: str = "127.0.0.1", tls: TlsFiles | None = None) -> None:
    """``uniros robot bridge rx200 ARGS --host HOST``: its domain's URI printed, the arm's joint states served there
    over tcp (``tls``: with ``--tls`` and these files by flag, over tls), the bridge's node offering only that
    scheme, at ``host``, and a clean exit on SIGINT."""
    scheme = "tcp" if tls is None else "tls"
    args = (*args, "--host", host)
    if tls is not None:
        args = (*args, "--tls", "--tls-cert", tls.cert_file, "--tls-key", tls.key_file, "--tls-ca", tls.ca_file)
    proc = subprocess.Popen(
        [sys.executable, "-m", "uniros_async.cli", "robot", "bridge", "rx200", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        line = wait_for_line(proc, f"export UNIROS_DOMAIN={scheme}://{host}:", timeout_s=60.0)
        uri = line.removeprefix("export UNIROS_DOMAIN=")
        options = None if tls is None else tls.options()

        async def one_state() -> tuple[JointState, dict[str, str]]:
            async with open_node("probe", domain=uri, namespace="/rx200", transport=scheme, options=options) as node:
                sub = await node.create_subscription(JointState, "joint_states")
                state = await asyncio.wait_for(sub.receive(), 10.0)
                info = await node._registry.request("lookup_service", name="/rx200/stats")
                return state, dict(info["endpoints"])

        state, endpoints = asyncio.run(one_state())
        assert state.name[:5] == get_robot_spec("rx200").arm_joint_names
        assert set(endpoints) == {scheme} and endpoints[scheme].startswith(f"{scheme}://{host}:"), endpoints
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=15.0) == 0
    finally:
        kill_process(proc)


def check_mixed_vec(robot: str) -> None:
    """One vector env, two worker processes: the rx200 at ``robot`` (its bridge in its worker) and a sim rx200,
    both driven toward the same target for two steps."""
    from uniros_async.runtime import make_vec

    venv = make_vec([("uniros/Rx200Reach-v0", {"robot": robot}), "uniros/Rx200Reach-v0"], reward_type="dense")
    try:
        obs, _ = venv.reset(seed=0)
        assert obs.shape[0] == 2 and np.all(np.isfinite(obs))
        action = np.array([[0.2, 0.1, 0.1, 0.1, 0.0]] * 2, dtype=np.float32)
        for _ in range(2):
            obs, reward, terminated, truncated, infos = venv.step(action)
        assert np.all(np.isfinite(obs)) and np.all(np.isfinite(reward))
        # both arms were driven toward the same target (the stand-in at 1 rad/s, the sim servos on their 2 s
        # profile): the arm joints (entries 7-11, after EE, direction and distance) and EE (0-2) agree closely
        assert np.abs(obs[0, 7:12] - obs[1, 7:12]).max() < 0.1, obs[:, 7:12]
        assert np.abs(obs[0, :3] - obs[1, :3]).max() < 0.03, obs[:, :3]
        assert np.abs(obs[0, 7:12]).max() > 0.1  # and the ROS arm did move
    finally:
        venv.close()


def policy_successes(serve: list[str], ready: str, robot: str, *, episodes: int = 3) -> int:
    """Zero-shot, in real time: the policy of ``CHECKPOINT`` on the emulated real arm that ``uniros robot serve
    rx200 --emulate-real SERVE`` serves (once it printed ``ready``), reached by ``robot``; its successes in
    ``episodes`` episodes of at most 30 steps."""
    import gymnasium as gym

    import uniros_async  # noqa: F401
    from uniros_async.training.weights import load_policy

    proc = subprocess.Popen(
        [sys.executable, "-m", "uniros_async.cli", "robot", "serve", "rx200", "--emulate-real", *serve],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert wait_for_line(proc, ready.split("=")[0] + "=", timeout_s=60.0) == ready
        policy = load_policy(CHECKPOINT)
        env = gym.make("uniros/Rx200Reach-v0", robot=robot, reward_type="dense", action_mode="delta")
        successes = 0
        try:
            for episode in range(episodes):
                obs, _ = env.reset(seed=episode)
                for _ in range(30):
                    action = policy(obs)
                    obs, _, terminated, truncated, info = env.step(action)
                    if terminated or truncated:
                        break
                successes += bool(info.get("is_success"))
        finally:
            env.close()
        return successes
    finally:
        kill_process(proc)
