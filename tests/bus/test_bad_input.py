"""Bad input at the bus level: each is a logged, counted rejection; the connection and the process keep working
and nothing already accepted is lost."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from uniros_async.bus import codec, open_domain, open_node, reliable
from uniros_async.bus.messages import Header, JointState, Pose, Text
from uniros_async.transports.base import TransportOptions, connect


def js(seq: int) -> JointState:
    return JointState(header=Header(seq=seq), name=("a",), position=[seq], velocity=[0.0], effort=[0.0])


@pytest.mark.parametrize("transport", ["tcp", "shm"])
async def test_malformed_frames_from_a_publisher_are_rejected_and_counted(transport: str) -> None:
    async with (
        open_domain() as domain,
        open_node("pub", domain=domain) as p,
        open_node("sub", domain=domain, transport=transport) as s,
    ):
        pub = await p.create_publisher(JointState, "/js", qos=reliable(100))
        sub = await s.create_subscription(JointState, "/js", qos=reliable(100))
        async with asyncio.timeout(10):
            await pub.wait_for_subscribers(1)
            pub.publish(js(1))
            assert (await sub.receive()).header.seq == 1
            sink = pub._sinks[0]  # inject straight into the real connection, as a faulty peer would
            sink.push([b"\x01"])  # shorter than a header
            sink.push([b"\xff\xff\xff\x00garbage"])  # announces more than it holds
            sink.push(codec.encode(Text(data="wrong type")))
            sink.push(codec.encode(Pose(header=Header(), position=[1, 2, 3])))
            pub.publish(js(2))
            assert (await sub.receive()).header.seq == 2, "the connection survives and delivers what follows"
        assert sub.rejected == 4
        assert sub.received == 2


async def test_registry_survives_malformed_requests() -> None:
    async with open_domain() as domain, open_node("n", domain=domain) as node:
        raw = await connect(domain.uri, TransportOptions())
        try:
            async with asyncio.timeout(5):
                await raw.send(b"\xc1 not msgpack")
                await raw.send(codec.encode_plain(["not", "a", "map"]))
                await raw.send(codec.encode_plain({"op": "no_such_op", "id": 7}))
                reply = codec.decode_plain(await raw.receive())
                assert reply["id"] == 7 and not reply["ok"] and "unknown registry operation" in reply["error"]
                await raw.send(codec.encode_plain({"op": "advertise", "id": 8}))  # missing fields
                reply = codec.decode_plain(await raw.receive())
                assert reply["id"] == 8 and not reply["ok"] and "topic" in reply["error"]
        finally:
            await raw.aclose()
        assert domain.rejected_requests == 4
        assert await node.list_nodes() == ["/n"], "the registry keeps serving everyone else"


async def test_a_garbage_hello_to_a_node_is_rejected_and_the_node_keeps_serving() -> None:
    async with (
        open_domain() as domain,
        open_node("pub", domain=domain) as p,
        open_node("sub", domain=domain, transport="tcp") as s,
    ):
        pub = await p.create_publisher(JointState, "/js", qos=reliable(10))
        raw = await connect(p._listeners["tcp"].uri, TransportOptions())
        await raw.send(b"\x00\x01 not a hello")
        await raw.send(codec.encode_plain({"op": "subscribe", "topic": "/js", "type": "Pose"}))
        await raw.aclose()
        sub = await s.create_subscription(JointState, "/js", qos=reliable(10))
        async with asyncio.timeout(10):
            await pub.wait_for_subscribers(1)
            pub.publish(js(5))
            assert (await sub.receive()).header.seq == 5
        assert p.rejected_connections >= 1
        assert np.array_equal(sub.latest().position, [5.0])
