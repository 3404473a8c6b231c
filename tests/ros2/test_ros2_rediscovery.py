"""DDS needs no registry to come back: our ROS 2 participant finds a peer that was killed and started again, and
is found again by it, with nothing of ours doing so (SPDP announcements and SEDP, the participant's own
discovery). The ROS 2 counterpart of the bus's rejoin (tests/bus/test_rejoin.py) and of a restarted rosmaster
(tests/faults/test_ros1_master_restart.py).
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

from uniros_async.bench.ros2_peers import wait_for_line

JS = "sensor_msgs/msg/JointState"
REDISCOVER_S = 20.0
"""A bound against a hang (discovery on loopback takes well under a second)."""


async def _count_reaches(got: list[Any], n: int, timeout_s: float) -> None:
    async with asyncio.timeout(timeout_s):
        while len(got) < n:  # noqa: ASYNC110 - a callback's list, polled under a timeout
            await asyncio.sleep(0.02)


async def test_our_subscription_finds_a_restarted_rclpy_publisher(rclpy_peer: Any) -> None:
    from uniros_async.adapters.ros2 import open_ros2_node

    got: list[Any] = []
    async with open_ros2_node("rediscovery") as node:
        sub = node.create_subscription("/chatter", JS, got.append)
        first = rclpy_peer("publish", "/chatter", JS)
        await sub.wait_for_publishers(1, timeout_s=REDISCOVER_S)
        await _count_reaches(got, 3, REDISCOVER_S)
        first.kill()
        first.wait(10)
        await asyncio.sleep(1.0)
        before = len(got)
        t0 = time.monotonic()
        rclpy_peer("publish", "/chatter", JS)  # a new process: a new participant, new GUIDs
        await _count_reaches(got, before + 3, REDISCOVER_S)
        assert time.monotonic() - t0 < REDISCOVER_S


async def test_a_restarted_rclpy_node_sees_our_publisher_again(rclpy_peer: Any) -> None:
    from uniros_async.adapters.ros2 import open_ros2_node

    async with open_ros2_node("rediscovered") as node:
        node.create_publisher("/seen", JS)
        first = rclpy_peer("watch", "/seen")
        assert await asyncio.to_thread(wait_for_line, first, "publishers 1", timeout_s=REDISCOVER_S)
        first.kill()
        first.wait(10)
        again = rclpy_peer("watch", "/seen")
        assert await asyncio.to_thread(wait_for_line, again, "publishers 1", timeout_s=REDISCOVER_S)
