"""The ROS 2 tests: our participant, bridge and mirror against real rclpy nodes, in a network namespace.

DDS discovers peers by multicast, so these tests run only inside a network namespace of their own, where nothing
else can hear them: ``tests/adapters/test_ros2_in_netns.py`` runs each file of this folder there
(``ros2_peers.netns_command``: ``unshare --net --mount``, loopback up with multicast on, a /dev/shm of its own)
and fails with its output when anything here fails. Run directly, outside such a namespace, nothing here is
collected. To run them by hand (as root): ``python -m pytest tests/adapters/test_ros2_in_netns.py``.

The rclpy peers (Jazzy wheels from PyPI) live in their own venv (``uniros_async.bench.ros2_peers``); without it every
test here skips saying how to make it, or fails under ``UNIROS_REQUIRE_ROS=1``.
"""

from __future__ import annotations

import contextlib
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from uniros_async.bench.ros2_peers import in_netns, rclpy_process, ros2_missing, skip_or_fail, wait_for_line

HERE = Path(__file__).parent
PEER = HERE / "rclpy_peer.py"
FAKE_ARM = HERE / "rclpy_fake_arm.py"

if not in_netns():
    collect_ignore_glob = ["test_*.py"]  # run by tests/adapters/test_ros2_in_netns.py, in a network namespace


@pytest.fixture(autouse=True)
def _rclpy_peers() -> None:
    reason = ros2_missing()
    if reason is not None:
        skip_or_fail(reason)


@pytest.fixture
def rclpy_peer(tmp_path: Path) -> Iterator[Callable[..., subprocess.Popen[str]]]:
    """Starts ``rclpy_peer.py *args`` (stdin a pipe) and waits for its ``ready``; killed at teardown."""
    with contextlib.ExitStack() as stack:

        def start(*args: str, domain_id: int = 0) -> subprocess.Popen[str]:
            proc = stack.enter_context(rclpy_process(PEER, *args, domain_id=domain_id, tmp_path=tmp_path, stdin=True))
            wait_for_line(proc, "ready", timeout_s=60.0)
            return proc

        yield start


@pytest.fixture
def fake_arm(tmp_path: Path) -> Iterator[Callable[..., subprocess.Popen[str]]]:
    """Starts the rclpy stand-in of a ros2_control arm with the topics of the robot's registered ROS 2 ``driver``
    (``adapters.drivers``), or others given."""
    from uniros_async.adapters.drivers import ros_driver_defaults
    from uniros_async.robots import get_robot_spec

    with contextlib.ExitStack() as stack:

        def start(robot: str, driver: str, *, domain_id: int = 0, **topics: str) -> subprocess.Popen[str]:
            spec = get_robot_spec(robot)
            defaults = ros_driver_defaults("ros2", robot, driver)
            assert defaults is not None
            t = {**defaults.as_settings(), **topics}
            args = ["--joints", ",".join(spec.joint_state_names), "--arm", str(len(spec.arm_joint_names))]
            args += ["--joint-states", t["joint_states"], "--command", t["command"]]
            args += ["--command-type", t["command_type"], "--rate", str(spec.hardware_rate_hz)]
            proc = stack.enter_context(rclpy_process(FAKE_ARM, *args, domain_id=domain_id, tmp_path=tmp_path))
            wait_for_line(proc, "ready", timeout_s=60.0)
            return proc

        yield start
