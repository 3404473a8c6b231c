"""The bus across real processes: pub/sub over shm and tcp, services, and a crashed node's cleanup."""

from __future__ import annotations

import asyncio
import os

import numpy as np
import pytest
from rig.bus_peers import BusPeer, check_talker

from uniros_async.bus import open_domain, open_node, reliable
from uniros_async.bus.messages import Blob, Header, JointState

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("transport", ["shm", "tcp"])
async def test_subscriber_in_another_process(transport: str) -> None:
    async with open_domain() as domain, open_node("listener", domain=domain, transport=transport) as node:
        async with BusPeer(domain.uri, "talker", transport):
            await check_talker(node)  # pub/sub and a service across processes


@pytest.mark.parametrize("transport", ["shm", "tcp"])
async def test_round_trip_through_a_remote_echo_node(transport: str) -> None:
    async with open_domain() as domain, open_node("pinger", domain=domain, transport=transport) as node:
        async with BusPeer(domain.uri, "echo", transport):
            ping = await node.create_publisher(Blob, "/ping", qos=reliable(1000))
            pong = await node.create_subscription(Blob, "/pong", qos=reliable(1000))
            async with asyncio.timeout(20):
                await ping.wait_for_subscribers(1, timeout_s=10)
                await pong.wait_for_publishers(1, timeout_s=10)
                for size in (277, 64 * 1024, 640 * 480 * 3):
                    data = np.frombuffer(os.urandom(size), np.uint8)
                    ping.publish(Blob(header=Header(seq=size), data=data))
                    got = await pong.receive()
                    assert got.header.seq == size and np.array_equal(got.data, data)


async def test_a_killed_node_is_removed_from_the_domain() -> None:
    async with open_domain() as domain, open_node("observer", domain=domain) as node:
        peer = BusPeer(domain.uri, "talker", "tcp")
        async with peer:
            assert "/talker" in await node.list_nodes()
            sub = await node.create_subscription(JointState, "/chatter")
            await sub.wait_for_publishers(1, timeout_s=10)
            peer.kill()
            async with asyncio.timeout(10):
                while "/talker" in await node.list_nodes():  # noqa: ASYNC110 - the registry's state, polled
                    await asyncio.sleep(0.05)
            topics = {t["topic"]: t for t in await node.list_topics()}
            assert topics["/chatter"]["publishers"] == []
            services = await node.list_services()
            assert all(s["service"] != "/add" for s in services), "the dead node's service is gone"
            async with asyncio.timeout(5):
                while sub.publisher_count:  # noqa: ASYNC110 - no event says it changed; polled under a timeout
                    await asyncio.sleep(0.05)
