"""What the fault tests share about their processes: the served arms, the ROS master and the agent, each started in
its namespace of a pair (``rig.netfault``) and stopped together, and their figures reported.

Every ``start_*`` puts the process it starts into ``peers`` (from ``stopping()``) before it waits for anything, so
a start that fails still leaves nothing running.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import signal
import subprocess
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest
from rig.netfault import EventPeer, NetnsPair

from uniros_async.bench.ros1_peers import ros1_missing, ros1_python, ros_env, rosmaster_bin

ROBOT_TIMEOUT_S = 0.5
COMMAND_TIMEOUT_S = 0.5
PERIOD_S = 0.1  # rx200: 10 Hz
ACTION_CYCLE_S = 0.2
TCP_ARM_PORT = 7000
REGISTRY_PORT = 7001
MASTER_PORT = 11311
START_S = 60.0
"""A bound against a hang: the agent's first step (or error), its env built and the arm reached."""


@contextlib.contextmanager
def stopping(sig: int = signal.SIGTERM) -> Iterator[list[EventPeer]]:
    """A list to put started processes in; on leaving, each is stopped with ``sig`` (``EventPeer.stop``), the last
    started first."""
    peers: list[EventPeer] = []
    try:
        yield peers
    finally:
        for peer in reversed(peers):
            peer.stop(sig)


def auth_env() -> dict[str, str]:
    """This environment with a fresh random ``UNIROS_AUTH_KEY``: a listener beyond loopback needs the domain's key,
    and the served arm's domain and the env's node both read it from there."""
    return {**os.environ, "UNIROS_AUTH_KEY": secrets.token_hex(16)}


def _start_served(pair: NetnsPair, peers: list[EventPeer], argv: list[str], ready: str, **popen: Any) -> EventPeer:
    """Start ``argv`` in the arm's namespace, check that its first line is ``ready``, and read its events."""
    proc = pair.popen("arm", argv, **popen)
    peer = EventPeer(proc)
    peers.append(peer)
    assert proc.stdout is not None
    line = proc.stdout.readline().strip()
    assert line == ready, line
    peer.start_reader()
    return peer


def skip_or_fail(reason: str | None, require_var: str) -> None:
    """Skip the test saying ``reason`` (what is missing), or fail instead when ``$require_var`` is 1 (``.ci/run``
    sets it: there the thing must be present); nothing when ``reason`` is None."""
    if reason is None:
        return
    if os.environ.get(require_var) == "1":
        pytest.fail(f"{require_var}=1 but {reason}")
    pytest.skip(reason)


def start_tcp_arm(
    pair: NetnsPair,
    peers: list[EventPeer],
    env: dict[str, str],
    *,
    port: int = TCP_ARM_PORT,
    max_command_age_s: float = ROBOT_TIMEOUT_S,
) -> tuple[EventPeer, str]:
    """``uniros robot serve rx200`` over tcp in the arm's namespace (watchdog ``COMMAND_TIMEOUT_S``, commands older
    than ``max_command_age_s`` dropped, every command and hold traced); returns it and its domain's URI."""
    uri = f"tcp://{pair.arm_ip}:{port}"
    argv = [sys.executable, "-m", "uniros_async.cli", "robot", "serve", "rx200", "--host", pair.arm_ip, "--port",
            str(port), "--command-timeout", str(COMMAND_TIMEOUT_S), "--max-command-age", str(max_command_age_s),
            "--trace"]  # fmt: skip
    return _start_served(pair, peers, argv, f"export UNIROS_DOMAIN={uri}", env=env), uri


def start_registry(pair: NetnsPair, peers: list[EventPeer], env: dict[str, str], uri: str) -> EventPeer:
    """A domain registry alone in a process of the arm's namespace (``rig.domain_peer registry``), at ``uri``."""
    argv = [sys.executable, "-m", "rig.domain_peer", "registry", "--uri", uri]
    return _start_served(pair, peers, argv, "ready", env=env)


def start_arm_in_domain(pair: NetnsPair, peers: list[EventPeer], env: dict[str, str], uri: str) -> EventPeer:
    """The rx200's servo sim joined to the domain at ``uri`` (``rig.domain_peer arm``: watchdog ``COMMAND_TIMEOUT_S``,
    commands older than ``ROBOT_TIMEOUT_S`` dropped, traced as ``start_tcp_arm``'s)."""
    argv = [sys.executable, "-m", "rig.domain_peer", "arm", "--domain", uri, "--host", pair.arm_ip,
            "--command-timeout", str(COMMAND_TIMEOUT_S), "--max-command-age", str(ROBOT_TIMEOUT_S)]  # fmt: skip
    return _start_served(pair, peers, argv, f"export UNIROS_DOMAIN={uri}", env=env)


def probe_domain(pair: NetnsPair, env: dict[str, str], uri: str, topic: str, service: str) -> dict[str, Any]:
    """What a new process in the env's namespace sees of the domain at ``uri`` (``rig.domain_peer probe``): the
    topics and their publishers, the services, and the first message of ``topic`` (seconds, or None)."""
    argv = [sys.executable, "-m", "rig.domain_peer", "probe", "--domain", uri, "--topic", topic, "--service", service]
    proc = pair.popen("env", argv, env=env)
    try:
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, f"the probe failed ({proc.returncode}): {out}"
    return dict(json.loads(out.strip().splitlines()[-1]))


def start_agent(
    pair: NetnsPair,
    peers: list[EventPeer],
    robot: str,
    *,
    env: dict[str, str] | None = None,
    ros_host: str | None = None,
) -> EventPeer:
    """The agent in the env's namespace (``netfault drive``: the rx200 reach env on ``robot``, ``ROBOT_TIMEOUT_S``,
    ``ACTION_CYCLE_S``), its events being read."""
    argv = [sys.executable, "-m", "rig.netfault", "drive", "--robot", robot,
            "--robot-timeout", str(ROBOT_TIMEOUT_S), "--action-cycle", str(ACTION_CYCLE_S)]  # fmt: skip
    if ros_host is not None:
        argv += ["--ros-host", ros_host]
    agent = EventPeer(pair.popen("env", argv, env=env))
    peers.append(agent)
    agent.start_reader()
    return agent


def require_ros1() -> None:
    """Skip the test when ROS 1 is not installed, saying what is missing; fail instead under
    ``UNIROS_REQUIRE_ROS=1``."""
    skip_or_fail(ros1_missing(), "UNIROS_REQUIRE_ROS")


def start_rosmaster(pair: NetnsPair, peers: list[EventPeer], home: Path) -> tuple[str, dict[str, str]]:
    """A real ``rosmaster`` in the arm's namespace; returns its URI and the environment ROS 1 processes there need
    (``ROS_HOSTNAME`` the arm's address)."""
    master_uri = f"http://{pair.arm_ip}:{MASTER_PORT}/"
    env = {**ros_env(master_uri, home=home), "ROS_HOSTNAME": pair.arm_ip}
    peers.append(EventPeer(pair.popen("arm", [rosmaster_bin(), "--core", "-p", str(MASTER_PORT)], env=env)))
    return master_uri, env


_ROS1_PROBE = """
import json, sys, time
import rospy
from sensor_msgs.msg import JointState
t0 = time.monotonic()
rospy.init_node("fault_probe", anonymous=True, disable_signals=True)
topics = sorted(name for name, _ in rospy.get_published_topics())
first = None
try:
    rospy.wait_for_message(sys.argv[1], JointState, timeout=20.0)
    first = time.monotonic() - t0
except rospy.ROSException:
    pass
print(json.dumps({"topics": topics, "first_message_s": first}))
rospy.signal_shutdown("probed")
"""


def probe_ros1(pair: NetnsPair, master_uri: str, home: Path, topic: str) -> dict[str, Any]:
    """What a new rospy process in the env's namespace sees of the ROS 1 graph at ``master_uri``: the published
    topics (the master's list) and how long the first ``sensor_msgs/JointState`` on ``topic`` took (None: none came
    within 20 s)."""
    env = {**ros_env(master_uri, home=home), "ROS_HOSTNAME": pair.env_ip}
    proc = pair.popen("env", [ros1_python(), "-c", _ROS1_PROBE, topic], env=env, stderr=subprocess.STDOUT)
    try:
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, f"the rospy probe failed ({proc.returncode}): {out}"
    return dict(json.loads(out.strip().splitlines()[-1]))


def start_ros1_driver(pair: NetnsPair, peers: list[EventPeer], master_uri: str, extra: Sequence[str] = ()) -> EventPeer:
    """Our sim as the rx200's ROS 1 driver (``uniros robot serve --ros1-master``) in the arm's namespace, allowed
    beyond loopback (ROS 1 cannot authenticate: only the test's two namespaces reach it), with ``extra`` arguments."""
    argv = [sys.executable, "-m", "uniros_async.cli", "robot", "serve", "rx200", "--ros1-master", master_uri,
            "--ros-host", pair.arm_ip, "--insecure", *extra]  # fmt: skip
    return _start_served(pair, peers, argv, f"export ROS_MASTER_URI={master_uri}")


def shm_names() -> set[str]:
    """The names in /dev/shm now (the bus's shared memory is anonymous, memfd: none of ours should ever appear)."""
    return set(os.listdir("/dev/shm"))


def assert_nothing_left(pair: NetnsPair, peers: list[EventPeer], shm_before: set[str]) -> None:
    """After a rig is taken down: every process it started has ended, both namespaces are gone, and /dev/shm holds
    no new name of ours (``uniros`` in it; other tests of the machine may add their own meanwhile)."""
    assert all(p.proc.poll() is not None for p in peers), [p.proc.args for p in peers if p.proc.poll() is None]
    listed = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, timeout=10).stdout
    assert pair.arm_ns not in listed and pair.env_ns not in listed, listed
    left = {n for n in shm_names() - shm_before if "uniros" in n}
    assert not left, left


def uncaught(agent: EventPeer) -> list[dict[str, Any]]:
    """The agent's ``error`` events: exceptions other than ``RobotError``, each with its traceback."""
    return [e for e in list(agent.events) if e["ev"] == "error"]


def report(row: dict[str, Any]) -> None:
    """Print one run's figures as a JSON line, and append it to ``$UNIROS_FAULT_REPORT`` when set
    (docs/reliability.md's tables)."""
    line = json.dumps(row)
    print(line)
    path = os.environ.get("UNIROS_FAULT_REPORT")
    if path:
        with open(path, "a") as f:
            f.write(line + "\n")
