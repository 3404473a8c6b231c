"""Our ROS 2 participant (adapters/ros2) on the wire with real rclpy nodes (Jazzy, Fast DDS).

Messages go both ways through an rclpy relay (``rclpy_peer.py relay``), compared field by field (hypothesis
round trips); the QoS of both ends decide what matches; a type of another name or hash on a topic is refused before
anything is sent; domains keep apart; closing is bounded and tells the peers.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import subprocess
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from _ros_helpers import plain_fields
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from uniros_async.bench.ros2_peers import wait_for_line
from uniros_async.errors import RobotError

JS = "sensor_msgs/msg/JointState"


def _joint_state(stamp: tuple[int, int], frame: str, names: list[str], pos: list[float]) -> Any:
    from uniros_async.adapters.ros2.msgs import message_class as cls

    return cls(JS)(
        header=cls("std_msgs/msg/Header")(
            stamp=cls("builtin_interfaces/msg/Time")(sec=stamp[0], nanosec=stamp[1]), frame_id=frame
        ),
        name=names,
        position=np.array(pos, float),
        velocity=np.zeros(len(pos)),
        effort=np.array(pos[::-1], float),
    )


class _Loop:
    """One event loop and one open node for many hypothesis examples (discovery happens once)."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.stack = contextlib.AsyncExitStack()
        self.inbox: asyncio.Queue[Any] = asyncio.Queue()

    def run(self, coro: Any) -> Any:
        return self.loop.run_until_complete(coro)

    async def open(self) -> Any:
        from uniros_async.adapters.ros2 import COMMANDS, open_ros2_node

        self.node = await self.stack.enter_async_context(open_ros2_node("relay_test"))
        self.pub = self.node.create_publisher("/uniros_out", JS, qos=COMMANDS)
        self.sub = self.node.create_subscription("/uniros_in", JS, self.inbox.put_nowait, qos=COMMANDS)
        await self.pub.wait_for_subscribers(1, timeout_s=20.0)
        await self.sub.wait_for_publishers(1, timeout_s=20.0)

    def close(self) -> None:
        self.run(self.stack.aclose())
        self.loop.close()


@pytest.fixture
def relay(rclpy_peer: Any) -> Iterator[tuple[_Loop, subprocess.Popen[str]]]:
    peer = rclpy_peer("relay", JS)
    loop = _Loop()
    try:
        loop.run(loop.open())
        yield loop, peer
    finally:
        loop.close()


_text = st.text(st.characters(min_codepoint=1, max_codepoint=0x2FF, blacklist_categories=("Cs",)), max_size=10)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    stamp=st.tuples(st.integers(-(2**31), 2**31 - 1), st.integers(0, 999_999_999)),
    frame=_text,
    names=st.lists(_text, max_size=8),
    pos=st.lists(st.floats(allow_nan=False, width=64), max_size=8),
)
def test_joint_states_cross_with_rclpy_both_ways(
    relay: tuple[_Loop, subprocess.Popen[str]], stamp: Any, frame: str, names: list[str], pos: list[float]
) -> None:
    loop, peer = relay
    msg = _joint_state(stamp, frame, names, pos)
    loop.pub.publish(msg)  # ours -> rclpy's subscription: it prints the fields it got
    got = json.loads(wait_for_line(peer, "{", timeout_s=10.0))
    assert got["msg"] == plain_fields(msg)
    assert peer.stdin is not None  # rclpy's publisher -> our subscription
    peer.stdin.write(json.dumps({"msg": plain_fields(msg)}) + "\n")
    peer.stdin.flush()
    back = loop.run(asyncio.wait_for(loop.inbox.get(), 10.0))
    assert plain_fields(back) == plain_fields(msg)


async def _matched_within(endpoint: Any, n: int, timeout_s: float) -> bool:
    with contextlib.suppress(TimeoutError):
        await endpoint._wait_matched(n, timeout_s)
        return True
    return False


async def test_qos_profiles_match_as_ros2s_do(rclpy_peer: Any) -> None:
    """A best-effort reader takes a reliable writer's data; a reliable reader never matches a best-effort writer."""
    from uniros_async.adapters.ros2 import COMMANDS, SENSOR_DATA, open_ros2_node

    reliable_peer = rclpy_peer("relay", JS, "--qos", "reliable")
    async with open_ros2_node("qos_test") as node:
        inbox: asyncio.Queue[Any] = asyncio.Queue()
        sensor_sub = node.create_subscription("/uniros_in", JS, inbox.put_nowait, qos=SENSOR_DATA)
        assert await _matched_within(sensor_sub, 1, 20.0)  # best effort <- reliable: matched
        best_effort_pub = node.create_publisher("/uniros_out", JS, qos=SENSOR_DATA)
        assert not await _matched_within(best_effort_pub, 1, 2.0)  # reliable rclpy reader <- best effort: never
        best_effort_pub.publish(_joint_state((0, 0), "lost", [], []))
        reliable_pub = node.create_publisher("/uniros_out", JS, qos=COMMANDS)
        assert await _matched_within(reliable_pub, 1, 20.0)
        reliable_pub.publish(_joint_state((0, 0), "kept", [], []))
        got = json.loads(await asyncio.to_thread(wait_for_line, reliable_peer, "{", timeout_s=10.0))
        assert got["msg"]["header"]["frame_id"] == "kept"  # only the reliable writer's message arrived
        assert reliable_peer.stdin is not None
        reliable_peer.stdin.write(json.dumps({"msg": {"name": ["a"], "position": [1.5]}}) + "\n")
        reliable_peer.stdin.flush()
        got_back = await asyncio.wait_for(inbox.get(), 10.0)
        assert list(got_back.name) == ["a"] and got_back.position.tolist() == [1.5]
        rclpy_peer("relay", JS, "--qos", "best_effort")
        reliable_sub = node.create_subscription("/uniros_in", JS, inbox.put_nowait, qos=COMMANDS)
        await asyncio.sleep(2.0)  # time for the best-effort rclpy publisher to be discovered
        assert reliable_sub.matched() == 1  # the reliable rclpy publisher only, not the best-effort one
        assert sensor_sub.matched() == 2  # both


async def test_domains_keep_apart(rclpy_peer: Any) -> None:
    from uniros_async.adapters.ros2 import open_ros2_node

    rclpy_peer("publish", "/chatter", JS, domain_id=7)
    seen: dict[int, list[Any]] = {0: [], 7: []}
    async with open_ros2_node("d0", domain_id=0) as n0, open_ros2_node("d7", domain_id=7) as n7:
        s0 = n0.create_subscription("/chatter", JS, seen[0].append)
        s7 = n7.create_subscription("/chatter", JS, seen[7].append)
        await s7.wait_for_publishers(1, timeout_s=20.0)
        for _ in range(200):
            if len(seen[7]) >= 3:
                break
            await asyncio.sleep(0.05)
        assert len(seen[7]) >= 3 and s0.matched() == 0 and seen[0] == []


async def test_a_peer_type_of_another_name_is_refused_naming_both(rclpy_peer: Any) -> None:
    from uniros_async.adapters.ros2 import open_ros2_node

    rclpy_peer("publish", "/rx200/joint_states", "std_msgs/msg/Float64MultiArray")
    async with open_ros2_node("mismatch") as node:
        got: list[Any] = []
        sub = node.create_subscription("/rx200/joint_states", JS, got.append)
        with pytest.raises(RobotError) as err:
            await sub.wait_for_publishers(1, timeout_s=20.0)
        text = str(err.value)
        assert "/rx200/joint_states" in text and "domain 0" in text
        assert "std_msgs/msg/Float64MultiArray" in text and JS in text and "RIHS01_" in text
        assert got == [] and sub.matched() == 0


async def test_a_peer_type_of_another_hash_is_refused_and_nothing_is_sent() -> None:
    """The same type name with another definition (another RIHS01 hash in the peer's USER_DATA, as Jazzy's rmw
    announces it). rclpy can only announce the hashes of the messages it was built with, so the peer here is a
    plain cyclonedds participant of this process announcing another hash: a real DDS reader, matched by DDS."""
    from cyclonedds.core import Policy, Qos
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic

    from uniros_async.adapters.ros2 import open_ros2_node
    from uniros_async.adapters.ros2.msgs import idl_type, type_hash

    kind = "interbotix_xs_msgs/msg/JointGroupCommand"
    other = "RIHS01_" + "0" * 64
    async with open_ros2_node("hash_test") as node:
        raw = DomainParticipant(0)
        topic = Topic(raw, "rt/rx200/commands/joint_group", idl_type(kind))
        reader = DataReader(raw, topic, qos=Qos(Policy.Userdata(data=f"typehash={other};".encode())))
        pub = node.create_publisher("/rx200/commands/joint_group", kind)
        with pytest.raises(RobotError) as err:
            await pub.wait_for_subscribers(1, timeout_s=20.0)
        text = str(err.value)
        assert other in text and type_hash(kind) in text and kind in text and "/rx200/commands/joint_group" in text
        assert pub.sent == 0 and reader.take(10) == []
        del reader, topic, raw


async def test_closing_is_bounded_and_peers_see_us_go(rclpy_peer: Any) -> None:
    from uniros_async.adapters.ros2 import open_ros2_node

    watch = rclpy_peer("watch", "/going")
    assert await asyncio.to_thread(wait_for_line, watch, "publishers", timeout_s=10.0) == "publishers 0"
    async with open_ros2_node("leaver") as node:
        pub = node.create_publisher("/going", JS)
        assert await asyncio.to_thread(wait_for_line, watch, "publishers", timeout_s=20.0) == "publishers 1"
        t0 = time.monotonic()
    assert time.monotonic() - t0 < 2.5  # close_timeout_s bounds it; deleting a participant is quick
    # rclpy's graph drops our publisher once our participant's lease (3 s) runs out
    assert await asyncio.to_thread(wait_for_line, watch, "publishers", timeout_s=6.0) == "publishers 0"
    with pytest.raises(RobotError, match="closed"):
        pub.publish(_joint_state((0, 0), "", [], []))
