"""Hostile peers against the ROS 1 adapter's ports: a served arm as a ROS 1 driver (`uniros robot serve rx200
--ros1-master URI`, a real process on a real rosmaster) has an XML-RPC slave API and a TCPROS publisher port; every
attack of ``_attacks`` goes to each, while a legitimate ROS 1 subscriber (our adapter) reads every joint state and
a legitimate XML-RPC client keeps calling ``getPid``.

Asserted: the driver survives, no joint state is lost (their header seq stays contiguous), every ``getPid`` is
answered, RSS grows by less than 64 MiB while 1,000 connections are held, and the log stays rate-limited.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.hostile import _attacks, _served
from uniros_async.adapters.ros1 import msgs, open_ros1_node
from uniros_async.adapters.ros1._xmlrpc import call_ros
from uniros_async.bench.ros1_peers import open_rosmaster, ros1_missing

pytestmark = pytest.mark.slow

TOPIC = "/rx200/joint_states"


@pytest.fixture
def ros_master(tmp_path: Path) -> Iterator[str]:
    reason = ros1_missing()
    if reason is not None:
        pytest.fail(f"ROS 1 is needed for the hostile ROS 1 tests and is missing: {reason}")
    with open_rosmaster(tmp_path, timeout_s=10.0) as uri:
        yield uri


async def test_ros1_driver_ports_keep_serving_under_attack(ros_master: str, tmp_path: Path) -> None:
    _attacks.raise_fd_limit()
    log = tmp_path / "driver.log"
    proc, _ = _served.start_serve(["--ros1-master", ros_master], log, unset=("ROS_IP", "ROS_HOSTNAME"))
    try:
        async with asyncio.timeout(300), open_ros1_node("/hostile_legit", master_uri=ros_master) as ros:
            seqs: list[int] = []
            got_one = asyncio.Event()

            def on_state(msg: msgs.JointState) -> None:
                seqs.append(msg.header.seq)
                got_one.set()

            await ros.subscribe(TOPIC, msgs.JointState, on_state)
            await got_one.wait()
            code, _, slave_uri = await call_ros(ros_master, "lookupNode", "/hostile", "/uniros_sim_rx200", timeout_s=5)
            assert code == 1, slave_uri
            code, _, proto = await call_ros(slave_uri, "requestTopic", "/hostile", TOPIC, [["TCPROS"]], timeout_s=5)
            assert code == 1 and proto[0] == "TCPROS", proto
            tcpros_host, tcpros_port = str(proto[1]), int(proto[2])

            answers = 0
            stop = asyncio.Event()

            async def ask_slave() -> None:
                nonlocal answers
                while not stop.is_set():
                    code, _, pid = await call_ros(slave_uri, "getPid", "/hostile_legit", timeout_s=5)
                    assert code == 1 and pid == proc.pid
                    answers += 1
                    await asyncio.sleep(0.05)

            t0 = time.monotonic()
            reports = {}
            async with asyncio.TaskGroup() as tg:
                asker = tg.create_task(ask_slave())
                host, port = _served.host_port(slave_uri)
                reports["xml-rpc"] = await _attacks.run_attacks(host, port, _attacks.xmlrpc(), server_pid=proc.pid)
                reports["tcpros"] = await _attacks.run_attacks(
                    tcpros_host, tcpros_port, _attacks.tcpros(TOPIC), server_pid=proc.pid
                )
                n_before = len(seqs)
                await asyncio.sleep(1.0)
                stop.set()
                await asker
            elapsed = time.monotonic() - t0

            assert proc.poll() is None, f"the ROS 1 driver died; its log:\n{log.read_text()[-3000:]}"
            _served.check_stream_whole(seqs, n_before)
            assert answers >= 10, f"only {answers} getPid calls answered in {elapsed:.1f} s"
            _served.check_rss_bounded(reports, "driver")
    finally:
        _served.stop_serve(proc)
    _served.check_log_rate_limited(log, elapsed, reports)
