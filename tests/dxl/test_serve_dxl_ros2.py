"""``uniros robot serve rx200 --dxl PATH --ros2 N``: the arm on its (virtual) bus as a ROS 2 driver, driven by rclpy.

Real peers only: ``uniros robot vbus rx200`` on a pty, the serving process on it, and a real rclpy node (Jazzy, the
rclpy venv: ``uniros_async.bench.ros2_peers``) that reads the arm's joint states and commands it through ros2_control's
``forward_position_controller`` topics (rclpy cannot speak xs_sdk's ``JointGroupCommand``, which is not on PyPI).
DDS discovers peers by multicast, so the rclpy test runs in a network namespace of its own: run outside one, this
file's ``test_serve_dxl_ros2_in_a_network_namespace`` runs it there (``netns_command``), as
``tests/adapters/test_ros2_in_netns.py`` runs tests/ros2. Without root or the venv it skips saying what is needed,
or fails under ``UNIROS_REQUIRE_ROS=1``.
"""

from __future__ import annotations

import json
import math
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from uniros_async.bench.ros2_peers import (
    in_netns,
    kill_process,
    netns_command,
    netns_missing,
    rclpy_process,
    ros2_missing,
    skip_or_fail,
    wait_for_line,
)

from ._vbus import MARGIN_MS, pty_gone, read, running_vbus, sdk_port

pytestmark = pytest.mark.slow

CLIENT = Path(__file__).with_name("rclpy_driver_client.py")
DOMAIN_ID = 7
TARGET = [0.4, -0.3, 0.25, 0.35, -0.3]  # the arm joints' goal (rad), well inside the rx200's limits


def _serve_argv(*extra: str) -> list[str]:
    return [sys.executable, "-m", "uniros_async.cli", "robot", "serve", "rx200", *extra]


def test_options_that_do_not_apply_to_a_bus_arm_on_ros2_are_refused() -> None:
    """No bus is opened and no DDS joined: the flags are checked first, and each error names what was wrong."""
    cases = {
        ("--ros2", "0", "--port", "7000"): "--port",
        ("--ros2", "0", "--namespace", "/arm1"): "--namespace (give it in the ros2:// URI)",
        ("--ros2", "0", "--tls"): "--ros2 serves no uniros domain",
        ("--ros2", "0", "--emulate-real"): "--emulate-real apply to the servo sim only",
        ("--ros1-master", "http://127.0.0.1:11311/"): "not on ROS 1",
        ("--ros2", "ros2://0?bogus=1"): "unknown parameter(s) ['bogus']",
    }
    for flags, message in cases.items():
        proc = subprocess.run(
            _serve_argv("--dxl", "/dev/null/none", *flags), capture_output=True, text=True, timeout=60
        )
        assert proc.returncode == 2, (flags, proc.stderr)
        assert message in proc.stderr, (flags, proc.stderr)


def _states(client: subprocess.Popen[str], timeout_s: float) -> dict[str, Any]:
    return dict(json.loads(wait_for_line(client, "{", timeout_s=timeout_s)))


def _stamp_s(state: dict[str, Any]) -> float:
    return float(state["stamp"][0] + state["stamp"][1] / 1e9)


def _state_when(client: subprocess.Popen[str], reached: Any, timeout_s: float) -> dict[str, Any]:
    """The first joint state the client prints for which ``reached(state)`` holds; fails after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    last: dict[str, Any] = {}
    while time.monotonic() < deadline:
        last = _states(client, max(0.1, deadline - time.monotonic()))
        if reached(last):
            return last
    raise AssertionError(f"no joint state within {timeout_s} s met the condition; the last: {last}")


if in_netns():

    def test_rclpy_drives_the_bus_arm_through_serve_dxl_ros2(tmp_path: Path) -> None:
        reason = ros2_missing()
        if reason is not None:
            skip_or_fail(reason)
        from uniros_async.robots import get_robot_spec

        spec = get_robot_spec("rx200")
        with running_vbus() as vbus:
            with sdk_port(vbus.path) as (port, ph):  # where the arm is before anything is served
                waist0 = (read(ph, port, 1, 132, 4) - 2048) * 2 * math.pi / 4096
            uri = f"ros2://{DOMAIN_ID}?driver=forward_position_controller"
            argv = _serve_argv("--dxl", vbus.path, "--ros2", uri, "--dxl-margin-ms", str(MARGIN_MS))
            argv += ["--dxl-profile-ms", "0"]
            server = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            try:
                assert wait_for_line(server, "export ", timeout_s=60.0) == f"export ROS_DOMAIN_ID={DOMAIN_ID}"
                assert wait_for_line(server, "#", timeout_s=5.0).endswith(f"robot=ros2://{DOMAIN_ID}")
                with rclpy_process(
                    CLIENT,
                    "/joint_states",
                    "/forward_position_controller/commands",
                    domain_id=DOMAIN_ID,
                    tmp_path=tmp_path,
                    stdin=True,
                ) as client:
                    wait_for_line(client, "ready", timeout_s=60.0)
                    first = _states(client, 30.0)
                    # the bus arm's state as the driver's: every joint, in the robot's order, stamped by the wall
                    # clock; start-up left the arm where it was, far from the goal sent below
                    assert first["name"] == list(spec.joint_state_names)
                    assert len(first["position"]) == len(first["velocity"]) == len(spec.joint_state_names)
                    assert abs(_stamp_s(first) - time.time()) < 10.0
                    assert abs(first["position"][0] - waist0) < 0.01, (first["position"][0], waist0)
                    assert np.max(np.abs(np.asarray(first["position"][:5]) - TARGET)) > 0.2, first["position"]
                    assert client.stdin is not None
                    client.stdin.write(json.dumps({"data": TARGET}) + "\n")
                    client.stdin.flush()
                    reached = _state_when(
                        client, lambda s: np.allclose(s["position"][:5], TARGET, atol=0.02), timeout_s=20.0
                    )
                    assert np.allclose(reached["position"][:5], TARGET, atol=0.02)
                    # a command of 3 positions for 5 joints is dropped: the arm stays at its goal
                    client.stdin.write(json.dumps({"data": [0.0, 0.0, 0.0]}) + "\n")
                    client.stdin.flush()
                    sent_s = time.time()
                    later = _state_when(client, lambda s: _stamp_s(s) > sent_s + 1.0, timeout_s=10.0)
                    assert np.allclose(later["position"][:5], TARGET, atol=0.02), later["position"]
                server.send_signal(signal.SIGINT)
                assert server.wait(20) == 0
                _, err = server.communicate(timeout=5)
                assert "Traceback" not in err, err
            finally:
                kill_process(server)
            with sdk_port(vbus.path) as (port, ph):
                # SIGINT left the arm holding where rclpy sent it: torque on, the waist's goal and present
                # position at TARGET's waist in ticks (2048 at zero, 4096 a turn)
                ticks = 2048 + round(TARGET[0] * 4096 / (2 * math.pi))
                assert read(ph, port, 1, 64, 1) == 1
                assert abs(read(ph, port, 1, 116, 4) - ticks) <= 15
                assert abs(read(ph, port, 1, 132, 4) - ticks) <= 15
        assert pty_gone(vbus.path)

else:

    def test_serve_dxl_ros2_in_a_network_namespace() -> None:
        reason = ros2_missing() or netns_missing()
        if reason is not None:
            skip_or_fail(reason)
        env = dict(os.environ, UNIROS_REQUIRE_ROS="1")  # the peers are there: nothing inside may skip for lack of them
        inner = Path(__file__).resolve()
        argv = [sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", str(inner), "-k", "rclpy"]
        proc = subprocess.run(
            netns_command(argv), env=env, capture_output=True, text=True, timeout=600, cwd=inner.parents[2]
        )
        out = proc.stdout[-20000:] + proc.stderr[-5000:]
        assert proc.returncode == 0, f"{inner.name} failed in its network namespace:\n{out}"
        summary = proc.stdout.strip().splitlines()[-1]
        assert re.search(r"1 passed", summary) and "skipped" not in summary and "error" not in summary, out
