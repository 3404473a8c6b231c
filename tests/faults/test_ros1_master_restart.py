"""A restarted rosmaster gets the graph back from our ROS 1 nodes (``adapters/ros1/node.py``: they watch the
master's pid and register again), and data flows to a subscriber that joined after the restart.

A real ``rosmaster --core`` on loopback, killed with SIGKILL and started again on the same port; two of our ROS 1
nodes (a publisher at 50 Hz and a subscriber) in this process. No namespaces: the fault is the master's death.
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from uniros_async.adapters.ros1 import msgs
from uniros_async.adapters.ros1._xmlrpc import call_ros
from uniros_async.adapters.ros1.node import MASTER_WATCH_S, open_ros1_node
from uniros_async.bench.ros1_peers import kill_process, ros_env, rosmaster_bin

from ._arm import require_ros1

pytestmark = pytest.mark.slow

TOPIC = "/rx200/joint_states"


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _spawn_master(port: int, home: Path) -> subprocess.Popen[bytes]:
    uri = f"http://127.0.0.1:{port}/"
    return subprocess.Popen(
        [rosmaster_bin(), "--core", "-p", str(port)],
        env=ros_env(uri, home=home),
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )


async def _start_master(port: int, home: Path) -> subprocess.Popen[bytes]:
    """``rosmaster --core`` on ``port``, once it answers."""
    uri = f"http://127.0.0.1:{port}/"
    proc = _spawn_master(port, home)
    deadline = time.monotonic() + 20
    while True:
        try:
            await call_ros(uri, "getPid", "/probe", timeout_s=1.0)
            return proc
        except (OSError, TimeoutError):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise AssertionError(f"rosmaster did not start on {port} (exit {proc.poll()})") from None
            await asyncio.sleep(0.05)


async def _state(uri: str) -> tuple[dict[str, list[str]], dict[str, list[str]]]:
    """The master's publishers and subscribers per topic (``getSystemState``)."""
    code, _, (pubs, subs, _) = await call_ros(uri, "getSystemState", "/probe", timeout_s=2.0)
    assert code == 1
    return {t: list(n) for t, n in pubs}, {t: list(n) for t, n in subs}


async def test_a_restarted_rosmaster_gets_our_publishers_and_subscribers_back(tmp_path: Path) -> None:
    require_ros1()
    port = _free_port()
    uri = f"http://127.0.0.1:{port}/"
    master = await _start_master(port, tmp_path)
    try:
        async with (
            open_ros1_node("/driver", master_uri=uri) as driver,
            open_ros1_node("/bridge", master_uri=uri) as bridge,
        ):
            pub = await driver.advertise(TOPIC, msgs.JointState)
            sub = await bridge.subscribe(TOPIC, msgs.JointState)
            zeros = np.zeros(1)

            async def publish() -> None:
                seq = 0
                while True:
                    seq += 1
                    pub.publish(
                        msgs.JointState(
                            header=msgs.RosHeader(seq=seq), name=["a"], position=zeros, velocity=zeros, effort=zeros
                        )
                    )
                    await asyncio.sleep(0.02)

            async with asyncio.TaskGroup() as tg:
                publisher = tg.create_task(publish())
                await sub.wait_for_publishers(1, timeout_s=10)
                os.kill(master.pid, signal.SIGKILL)
                master.wait(10)
                await asyncio.sleep(2 * MASTER_WATCH_S)  # the nodes notice the master gone
                master = await _start_master(port, tmp_path)
                assert (await _state(uri))[0].get(TOPIC) is None, "a new master knows nothing"
                t0 = time.monotonic()
                async with asyncio.timeout(3 * MASTER_WATCH_S + 5):
                    while True:
                        pubs, subs = await _state(uri)
                        if pubs.get(TOPIC) == ["/driver"] and subs.get(TOPIC) == ["/bridge"]:
                            break
                        await asyncio.sleep(0.05)
                assert time.monotonic() - t0 <= 2 * MASTER_WATCH_S + 1.0
                await sub.receive(timeout_s=5)  # the bridge's link to the driver carried on throughout
                async with open_ros1_node("/late", master_uri=uri) as late:  # joins after the restart
                    late_sub = await late.subscribe(TOPIC, msgs.JointState)
                    got = await late_sub.receive(timeout_s=10)
                    assert got.name == ["a"]
                publisher.cancel()
    finally:
        kill_process(master)  # type: ignore[arg-type]
