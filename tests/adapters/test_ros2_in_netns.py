"""Runs the ROS 2 tests (tests/ros2/) in a network namespace of their own, against real rclpy peers.

DDS discovers peers by multicast: the tests must neither reach nor hear anything but themselves. Each file of
tests/ros2 runs in its own pytest inside a fresh ``unshare --net`` (loopback up, multicast on); its test here fails
with that output when any test there fails, or skips there. Without root (``unshare``) or the rclpy venv it skips
saying what is needed, and fails instead under ``UNIROS_REQUIRE_ROS=1`` (``.ci/run``).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from uniros_async.bench.ros2_peers import netns_command, netns_missing, ros2_missing, skip_or_fail

SUITE = Path(__file__).resolve().parents[1] / "ros2"


@pytest.mark.slow
@pytest.mark.parametrize("inner", sorted(p.name for p in SUITE.glob("test_*.py")))
def test_ros2_suite_in_a_network_namespace(inner: str) -> None:
    reason = ros2_missing() or netns_missing()
    if reason is not None:
        skip_or_fail(reason)
    env = dict(os.environ, UNIROS_REQUIRE_ROS="1")  # the peers are there: nothing inside may skip for lack of them
    argv = [sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", str(SUITE / inner)]
    proc = subprocess.run(
        netns_command(argv), env=env, capture_output=True, text=True, timeout=1500, cwd=SUITE.parents[1]
    )
    out = proc.stdout[-20000:] + proc.stderr[-5000:]
    assert proc.returncode == 0, f"tests/ros2/{inner} failed in its network namespace:\n{out}"
    summary = proc.stdout.strip().splitlines()[-1]
    assert re.search(r"\d+ passed", summary) and "skipped" not in summary and "error" not in summary, out
