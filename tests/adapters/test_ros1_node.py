"""The asyncio ROS 1 node against a real rosmaster and real rospy peers (tests/adapters/ros1_peer.py)."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
import os
import signal
import socket
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from uniros_async.adapters.ros1 import (
    Float64MultiArray,
    JointGroupCommand,
    JointState,
    JointTrajectory,
    JointTrajectoryPoint,
    Ros1Message,
    Ros1Publisher,
    Ros1Subscriber,
    RosHeader,
    _tcpros,
    open_ros1_node,
)
from uniros_async.adapters.ros1._xmlrpc import XmlRpcCallError, call
from uniros_async.bench.ros1_peers import (
    kill_process,
    open_rosmaster_process,
    requires_ros1,
    rospy_process,
    wait_for_line,
)
from uniros_async.errors import RobotError

PEER = Path(__file__).with_name("ros1_peer.py")
PeerFactory = Callable[..., subprocess.Popen[str]]
T_S = 20.0  # bound on waits for rospy processes (they start slowly on a loaded machine)


def as_plain(value: Any) -> Any:
    if isinstance(value, Ros1Message):
        return (type(value).__name__, *(as_plain(getattr(value, f)) for f in value.__dataclass_fields__))
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, list | tuple):
        return [as_plain(v) for v in value]
    return value


async def ready(proc: subprocess.Popen[str]) -> None:
    await asyncio.to_thread(wait_for_line, proc, "ready", timeout_s=T_S)


async def got(proc: subprocess.Popen[str]) -> Any:
    line = await asyncio.to_thread(wait_for_line, proc, "got ", timeout_s=T_S)
    return json.loads(line[4:])


async def eventually(check: Callable[[], bool], what: str, timeout_s: float = T_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout_s} s: {what}")
        await asyncio.sleep(0.02)


async def publish_until_received(pub: Ros1Publisher[Any], msg: Ros1Message, sub: Ros1Subscriber[Any]) -> Any:
    # A rospy publisher adds our connection just after sending its header, so the first message relayed through
    # it can miss us (ROS 1 itself has this race); resend until one comes back.
    async with asyncio.timeout(T_S):
        while True:
            pub.publish(msg)
            try:
                return await sub.receive(timeout_s=0.5)
            except TimeoutError:
                continue


async def system_state(master_uri: str) -> list[Any]:
    code, _, state = await call(master_uri, "getSystemState", "/test", timeout_s=5.0)
    assert code == 1
    return list(state)


def names_in(state: list[Any]) -> set[str]:
    return {node for kind in state[:2] for _, nodes in kind for node in nodes}


def joint_state(seq: int, position: list[float]) -> JointState:
    n = len(position)
    header = RosHeader(seq, 1_700_000_000_000_000_000 + seq, "base")
    return JointState(header, [f"j{i}" for i in range(n)], np.array(position), np.zeros(n), np.zeros(0))


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


# ---------------------------------------------------------------------------------------------- no ROS needed


async def test_unreachable_master_is_a_clear_robot_error_at_once() -> None:
    uri = f"http://127.0.0.1:{closed_port()}/"
    t0 = time.monotonic()
    with pytest.raises(RobotError, match=rf"{uri}.*start roscore .*set ROS_MASTER_URI"):
        async with open_ros1_node("/uniros_test", master_uri=uri, timeout_s=5.0):
            pass
    assert time.monotonic() - t0 < 1.0


async def test_silent_master_fails_within_timeout_s() -> None:
    accepted: list[asyncio.StreamWriter] = []
    server = await asyncio.start_server(lambda r, w: accepted.append(w), "127.0.0.1", 0)
    uri = f"http://127.0.0.1:{server.sockets[0].getsockname()[1]}/"
    try:
        t0 = time.monotonic()
        with pytest.raises(RobotError, match=rf"cannot reach the ROS master at {uri} \(TimeoutError"):
            async with open_ros1_node("/uniros_test", master_uri=uri, timeout_s=0.3):
                pass
        assert 0.25 < time.monotonic() - t0 < 1.5
        assert accepted  # it did connect: the timeout, not a refusal, ended the wait
    finally:
        for w in accepted:
            w.close()
        server.close()


# ---------------------------------------------------------------------------------------------- with ROS 1
# (the ros_master fixture skips, naming what to install, when ROS 1 is missing)


@pytest.mark.slow
async def test_rospy_talker_at_50hz_reaches_our_subscriber_in_order(
    ros_master: str, rospy_peer: PeerFactory, caplog: pytest.LogCaptureFixture
) -> None:
    async with open_ros1_node("/uniros_test", master_uri=ros_master) as node:
        seen: list[JointState] = []
        sub = await node.subscribe("/chatter", JointState, callback=seen.append)

        def explode(msg: JointState) -> None:
            raise ValueError("callback bug")

        boom = await node.subscribe("chatter", JointState, callback=explode)  # relative name, same topic
        assert boom.topic == "/chatter"
        assert sub.latest() is None and sub.latest_recv_ns is None and sub.publisher_count == 0

        talker = rospy_peer("talk", "sensor_msgs/JointState", "/chatter", "50")  # starts after we subscribed
        await sub.wait_for_publishers(1, timeout_s=T_S)
        assert sub.publisher_count == 1
        t0 = time.monotonic()
        msgs = [await sub.receive(timeout_s=5.0) for _ in range(10)]
        elapsed = time.monotonic() - t0
        seqs = [m.header.seq for m in msgs]
        assert all(b > a for a, b in zip(seqs, seqs[1:], strict=False)), seqs
        assert all(m.name == ["j1", "j2"] and m.position[0] == -m.position[1] > 0 for m in msgs)
        assert 0.1 < elapsed < 2.0  # ~50 Hz: 10 messages take about 0.2 s
        latest = sub.latest()
        assert latest is not None and latest.header.seq >= seqs[-1]
        assert sub.latest_recv_ns is not None and sub.latest_recv_ns <= time.monotonic_ns()
        assert len(seen) >= 10 and [m.header.seq for m in seen] == sorted({m.header.seq for m in seen})
        assert "the subscriber callback raised" in caplog.text  # logged, and delivery went on

        # rospy unregisters on SIGINT; the master's publisherUpdate makes us drop the connection
        await asyncio.to_thread(kill_process, talker)
        await eventually(lambda: sub.publisher_count == 0, "publisher_count back to 0")
        with pytest.raises(TimeoutError, match=r"/chatter: 0 of 1 publishers connected after 0.2 s"):
            await sub.wait_for_publishers(1, timeout_s=0.2)
        with pytest.raises(TimeoutError, match=r"no message on /chatter \(sensor_msgs/JointState\) after 0.2 s"):
            await sub.receive(timeout_s=0.2)


def _trajectory() -> JointTrajectory:
    def point(p: list[float], t_ns: int) -> JointTrajectoryPoint:
        return JointTrajectoryPoint(np.array(p), np.array([0.1, 0.2]), np.array([]), np.array([]), t_ns)

    points = [point([1, 2], 500_000_000), point([3, 4], 2_250_000_000)]
    return JointTrajectory(RosHeader(3, 42, "base"), ["waist", "elbow"], points)


ECHO_CASES = {
    "sensor_msgs/JointState": joint_state(9, [0.25, -1.5, 3.0]),
    "std_msgs/Float64MultiArray": Float64MultiArray(np.array([0.1, 0.2, -0.3, 0.4, 0.5]), [("joints", 5, 5)]),
    "trajectory_msgs/JointTrajectory": _trajectory(),
}


@pytest.mark.slow
@pytest.mark.parametrize("type_name", list(ECHO_CASES))
async def test_our_publisher_to_rospy_echo_to_our_subscriber(
    ros_master: str, rospy_peer: PeerFactory, type_name: str
) -> None:
    msg = ECHO_CASES[type_name]
    cls = type(msg)
    async with open_ros1_node("/uniros_test", master_uri=ros_master) as node:
        pub = await node.advertise("/in", cls)
        out = await node.subscribe("/out", cls)
        await ready(rospy_peer("echo", type_name, "/in", "/out"))
        await pub.wait_for_subscribers(1, timeout_s=T_S)
        await out.wait_for_publishers(1, timeout_s=T_S)
        back = await publish_until_received(pub, msg, out)
        if isinstance(msg, JointState | JointTrajectory):  # rospy numbers the header itself
            back = dataclasses.replace(back, header=dataclasses.replace(back.header, seq=msg.header.seq))
        assert as_plain(back) == as_plain(msg)
        assert pub.subscriber_count == 1 and out.publisher_count == 1


@pytest.mark.slow
async def test_joint_group_command_bytes_reach_rospy(ros_master: str, rospy_peer: PeerFactory) -> None:
    # rospy has no interbotix_xs_msgs here: an AnyMsg subscriber (md5 "*") shows the raw bytes and the header.
    msg = JointGroupCommand("arm", np.array([0.0, -0.5, 1.25, 0.0, 3.5], np.float32))
    async with open_ros1_node("/uniros_test", master_uri=ros_master) as node:
        pub = await node.advertise("/rx200/commands/joint_group", JointGroupCommand)
        listener = rospy_peer("anylisten", "/rx200/commands/joint_group")
        await pub.wait_for_subscribers(1, timeout_s=T_S)
        pub.publish(msg)  # once: our side queues frames after its header, so nothing can be missed
        seen = await got(listener)
    assert seen == {"type": JointGroupCommand._type, "md5sum": JointGroupCommand._md5sum, "hex": msg.serialize().hex()}


@pytest.mark.slow
async def test_latching_both_ways(ros_master: str, rospy_peer: PeerFactory) -> None:
    async with open_ros1_node("/uniros_test", master_uri=ros_master) as node:
        pub = await node.advertise("/latched_ours", JointState, latch=True)
        pub.publish(joint_state(1, [1.0]))
        pub.publish(joint_state(2, [2.0]))  # only the last one is latched
        late = rospy_peer("listen", "sensor_msgs/JointState", "/latched_ours")  # subscribes after publish
        assert (await got(late))["position"] == [2.0]

        await ready(rospy_peer("latch", "sensor_msgs/JointState", "/latched_rospy"))
        sub = await node.subscribe("/latched_rospy", JointState)
        latched = await sub.receive(timeout_s=T_S)
        assert latched.name == ["latched"] and latched.position.tolist() == [42.0]


@pytest.mark.slow
async def test_several_subscribers_get_every_message(ros_master: str, rospy_peer: PeerFactory) -> None:
    async with (
        open_ros1_node("/uniros_pub", master_uri=ros_master) as node,
        open_ros1_node("/uniros_sub", master_uri=ros_master) as other,
    ):
        pub = await node.advertise("/fanout", JointState)
        listeners = [rospy_peer("listen", "sensor_msgs/JointState", "/fanout") for _ in range(2)]
        ours = [await other.subscribe("/fanout", JointState) for _ in range(2)]  # two handles, one connection
        await pub.wait_for_subscribers(3, timeout_s=T_S)
        assert pub.subscriber_count == 3 and ours[0].publisher_count == 1
        receives = [asyncio.ensure_future(s.receive(timeout_s=T_S)) for s in ours]
        await asyncio.sleep(0)  # both receives are waiting before the message goes out
        pub.publish(joint_state(5, [0.5, 0.25]))
        for listener in listeners:
            assert (await got(listener))["position"] == [0.5, 0.25]
        for r in receives:
            assert (await r).position.tolist() == [0.5, 0.25]

        await asyncio.to_thread(kill_process, listeners[0])
        await eventually(lambda: pub.subscriber_count == 2, "subscriber_count down to 2 after a listener died")


@pytest.mark.slow
async def test_leaving_or_cancelling_the_node_unregisters_it(ros_master: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROS_MASTER_URI", ros_master)
    async with open_ros1_node("uniros_test") as node:  # no master_uri: $ROS_MASTER_URI; "/" is added
        assert node.name == "/uniros_test" and node.master_uri == ros_master
        await node.advertise("/a", JointState)
        await node.subscribe("/b", Float64MultiArray)
        state = await system_state(ros_master)
        assert ["/a", ["/uniros_test"]] in state[0] and ["/b", ["/uniros_test"]] in state[1]
    assert "/uniros_test" not in names_in(await system_state(ros_master))
    with pytest.raises(OSError):
        await call(node.uri, "getPid", "/test", timeout_s=1.0)  # its slave API is gone

    opened = asyncio.Event()

    async def run_forever() -> None:
        async with open_ros1_node("/uniros_cancelled", master_uri=ros_master) as n:
            await n.advertise("/c", JointState)
            opened.set()
            await asyncio.Event().wait()

    async with asyncio.TaskGroup() as tg:
        task = tg.create_task(run_forever())
        async with asyncio.timeout(10):
            await opened.wait()
        assert "/uniros_cancelled" in names_in(await system_state(ros_master))
        task.cancel()
    assert task.cancelled()
    assert "/uniros_cancelled" not in names_in(await system_state(ros_master))


@requires_ros1
@pytest.mark.slow
async def test_close_with_a_hung_master_is_bounded_by_timeout_s(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with open_rosmaster_process(tmp_path) as (master, uri):
        try:
            async with open_ros1_node("/uniros_test", master_uri=uri, timeout_s=0.5) as node:
                await node.advertise("/a", JointState)
                os.kill(master.pid, signal.SIGSTOP)  # alive, accepting connections, never answering
                t0 = time.monotonic()
            assert time.monotonic() - t0 < 1.5
            assert "did not confirm unregistering /uniros_test" in caplog.text
        finally:
            os.kill(master.pid, signal.SIGCONT)


@pytest.mark.slow
async def test_type_mismatch_is_refused_both_ways_and_the_node_keeps_working(
    ros_master: str, rospy_peer: PeerFactory, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="uniros_async.adapters.ros1")
    async with open_ros1_node("/uniros_test", master_uri=ros_master) as node:
        wrong_sub = await node.subscribe("/x", JointState)
        talker = rospy_peer("talk", "std_msgs/Float64MultiArray", "/x", "20")
        wrong_pub = await node.advertise("/y", JointState)
        listener = rospy_peer("listen", "std_msgs/Float64MultiArray", "/y")

        def warned(topic: str) -> bool:
            return any(
                r.levelno == logging.WARNING
                and topic in r.getMessage()
                and "3066dcd76a6cfaef579bd0f34173e9fd" in r.getMessage()
                and "4b7d974086d4060e7db4613a7e6c3ba4" in r.getMessage()
                and "sensor_msgs/JointState" in r.getMessage()
                and "std_msgs/Float64MultiArray" in r.getMessage()
                for r in caplog.records
            )

        await eventually(lambda: warned("/x"), "a warning naming /x, both types and md5s (rospy refused us)")
        await eventually(lambda: warned("/y"), "a warning naming /y, both types and md5s (we refused rospy)")
        assert wrong_sub.publisher_count == 0 and wrong_pub.subscriber_count == 0
        assert wrong_sub.latest() is None
        assert talker.poll() is None and listener.poll() is None

        # the node still works: a loop-back topic through its own TCPROS server
        pub = await node.advertise("/ok", JointState)
        sub = await node.subscribe("/ok", JointState)
        await sub.wait_for_publishers(1, timeout_s=T_S)
        assert (await publish_until_received(pub, joint_state(1, [7.0]), sub)).position.tolist() == [7.0]


@pytest.mark.slow
async def test_slow_subscriber_drops_old_frames_without_blocking_others(ros_master: str) -> None:
    async with open_ros1_node("/uniros_test", master_uri=ros_master) as node:
        pub = await node.advertise("/big", JointState, queue_size=4)
        fast = await node.subscribe("/big", JointState)
        # A subscriber that sends its header and then never reads.
        reader, writer = await asyncio.open_connection("127.0.0.1", node.tcpros_port)
        try:
            writer.write(_tcpros.encode_header({"callerid": "/stuck", "topic": "/big", "md5sum": "*", "type": "*"}))
            header = await asyncio.wait_for(_tcpros.read_header(reader), 5.0)
            assert header["type"] == "sensor_msgs/JointState" and header["latching"] == "0"
            await pub.wait_for_subscribers(2, timeout_s=T_S)
            big = np.arange(50_000, dtype=np.float64)  # 400 kB a message
            for seq in range(1, 121):
                pub.publish(joint_state(seq, big + seq))
                await asyncio.sleep(0.002)
            await eventually(lambda: (m := fast.latest()) is not None and m.header.seq == 120, "fast one got all")
            assert pub.dropped_frames > 0
            assert all(len(link.queue) <= 4 for link in pub._pub.links)  # bounded memory for the stuck one
        finally:
            writer.close()


@pytest.mark.slow
async def test_slave_api_answers_like_a_ros_node(ros_master: str) -> None:
    async with open_ros1_node("/uniros_test", master_uri=ros_master) as node:
        pub = await node.advertise("/a", JointState)
        sub = await node.subscribe("/a", JointState)
        await sub.wait_for_publishers(1, timeout_s=T_S)
        await pub.wait_for_subscribers(1, timeout_s=T_S)

        async def slave(method: str, *args: Any) -> Any:
            return await call(node.uri, method, "/test", *args, timeout_s=5.0)

        assert await slave("getPid") == [1, "", os.getpid()]
        assert await slave("getMasterUri") == [1, "", ros_master]
        assert await slave("getPublications") == [1, "", [["/a", "sensor_msgs/JointState"]]]
        assert await slave("getSubscriptions") == [1, "", [["/a", "sensor_msgs/JointState"]]]
        _, _, info = await slave("getBusInfo")
        assert {(i[2], i[3], i[4]) for i in info} == {("i", "TCPROS", "/a"), ("o", "TCPROS", "/a")}
        _, _, (pub_stats, sub_stats, _) = await slave("getBusStats")
        assert pub_stats[0][0] == "/a" and sub_stats[0][0] == "/a"
        assert await slave("requestTopic", "/nope", [["TCPROS"]]) == [-1, "Not a publisher of [/nope]", []]
        assert (await slave("requestTopic", "/a", [["UDPROS"]]))[0] == 0
        assert await slave("requestTopic", "/a", [["TCPROS"]]) == [
            1,
            f"ready on 127.0.0.1:{node.tcpros_port}",
            ["TCPROS", "127.0.0.1", node.tcpros_port],
        ]
        with pytest.raises(XmlRpcCallError, match=r"fault -32601: unknown method 'noSuchMethod'"):
            await slave("noSuchMethod")
        assert await slave("shutdown", "a test asked") == [1, "", 0]  # logged, not obeyed
        assert (await publish_until_received(pub, joint_state(3, [3.0]), sub)).position.tolist() == [3.0]


@requires_ros1
@pytest.mark.slow
async def test_helpers_leave_no_process_or_port_behind(tmp_path: Path) -> None:
    with open_rosmaster_process(tmp_path) as (master, uri):
        with rospy_process(PEER, "listen", "sensor_msgs/JointState", "/z", master_uri=uri, tmp_path=tmp_path) as p:
            await ready(p)
            assert p.poll() is None
    for proc in (master, p):
        assert proc.returncode is not None  # reaped
        with pytest.raises(ProcessLookupError):
            os.kill(proc.pid, 0)
    with pytest.raises(OSError):
        await call(uri, "getPid", "/test", timeout_s=1.0)
