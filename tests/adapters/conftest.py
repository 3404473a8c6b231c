"""Fixtures for the ROS 1 adapter tests: a real rosmaster per test and rospy peers run by the system Python.

Helpers live in ``uniros_async.bench.ros1_peers`` (``requires_ros1``, ``ros_env``, ``start_rospy``, ``rospy_process``,
``wait_for_line``); tests import them from there. A fixture here skips, naming what to install, when ROS 1 is missing.
"""

from __future__ import annotations

import subprocess
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path

import pytest

from uniros_async.bench.ros1_peers import open_rosmaster, ros1_missing, rospy_process
from uniros_async.bench.ros2_peers import skip_or_fail

PEER_SCRIPT = Path(__file__).with_name("ros1_peer.py")


@pytest.fixture
def ros_master(tmp_path: Path) -> Iterator[str]:
    """A real ``rosmaster --core`` on a free loopback port; yields its URI ("http://127.0.0.1:PORT/")."""
    reason = ros1_missing()
    if reason is not None:
        skip_or_fail(reason)
    with open_rosmaster(tmp_path, timeout_s=10.0) as uri:
        yield uri


@pytest.fixture
def rospy_peer(ros_master: str, tmp_path: Path) -> Iterator[Callable[..., subprocess.Popen[str]]]:
    """Starts ``tests/adapters/ros1_peer.py *args`` against ``ros_master``; every peer is killed at teardown."""
    with ExitStack() as stack:

        def start(*args: str) -> subprocess.Popen[str]:
            return stack.enter_context(rospy_process(PEER_SCRIPT, *args, master_uri=ros_master, tmp_path=tmp_path))

        yield start
