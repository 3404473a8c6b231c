"""Loaned messages (``Publisher.loan``): a frame written once in a subscriber's shm ring and read there in another
process; the copying fallbacks (tcp, in-process); bad loans; a reader that dies and a publisher that restarts."""

from __future__ import annotations

import asyncio
from typing import Any

import numpy as np
import pytest
from rig.bus_peers import BusPeer

from uniros_async.bus import latest, open_domain, open_node, reliable
from uniros_async.bus.messages import Data, Header, Image
from uniros_async.bus.node import Node
from uniros_async.bus.pubsub import Publisher, Subscription
from uniros_async.errors import CodecError

TOPIC = "/cam/color/image_raw"
SHAPE = (480, 640, 3)


async def _loan_frame(pub: Publisher[Image], seq: int, *, in_place: bool) -> None:
    async with pub.loan(SHAPE) as loan:
        assert loan.in_place is in_place
        loan.array[...] = seq % 251  # the producer's one write (a renderer draws here)
        loan.message = Image(header=Header(stamp_ns=seq, seq=seq, frame_id="cam"), data=loan.array)


async def _seen(sub: Subscription[Data], seq: int) -> list[Any]:
    async with asyncio.timeout(10):
        while True:
            got = (await sub.receive()).value
            if got[0] == seq:
                return list(got)


async def _peer_and_topics(node: Node) -> tuple[Publisher[Image], Subscription[Data]]:
    pub = await node.create_publisher(Image, TOPIC, qos=latest())
    seen = await node.create_subscription(Data, "/frames_seen", qos=reliable(1000))
    return pub, seen


def _expect(seq: int) -> list[Any]:
    return [seq, (seq % 251) * int(np.prod(SHAPE)), True, list(SHAPE), "rgb8", "cam"]


@pytest.mark.slow
async def test_a_loaned_frame_is_written_once_and_read_in_place_in_another_process() -> None:
    async with open_domain() as domain, open_node("cam", domain=domain, transport="shm") as node:
        pub, seen = await _peer_and_topics(node)
        async with BusPeer(domain.uri, "frames", "shm"):
            await pub.wait_for_subscribers(1, timeout_s=20)
            await seen.wait_for_publishers(1, timeout_s=20)
            conn: Any = pub._sinks[0].conn
            sent0, loaned0 = conn.stats.frames_sent, conn.frames_loaned
            for seq in range(1, 21):
                await _loan_frame(pub, seq, in_place=True)
                # read-only views in the subscriber, the pixels as written, the Image's fields end to end
                assert await _seen(seen, seq) == _expect(seq)
            # the transport's own counters: 20 frames went out, all 20 in place, none copied into the ring
            assert conn.frames_loaned - loaned0 == 20
            assert conn.stats.frames_sent - sent0 == 20
            assert pub.loaned_in_place == 20 and pub.published == 20


@pytest.mark.slow
async def test_a_reader_that_dies_holding_a_frame_and_a_publisher_that_restarts() -> None:
    async with open_domain() as domain, open_node("cam", domain=domain, transport="shm") as node:
        pub, seen = await _peer_and_topics(node)
        peer = BusPeer(domain.uri, "frames", "shm")
        async with peer:
            await pub.wait_for_subscribers(1, timeout_s=20)
            await seen.wait_for_publishers(1, timeout_s=20)
            await _loan_frame(pub, 1, in_place=True)
            await _seen(seen, 1)
            peer.kill()  # a reader gone in the middle of the stream: its ring goes with its connection
            async with asyncio.timeout(10):
                while pub.subscription_count:  # noqa: ASYNC110 - the sink leaves when its connection breaks
                    await asyncio.sleep(0.02)
            async with pub.loan(SHAPE) as loan:  # nobody listens: a buffer of our own, published to no one
                assert not loan.in_place
                loan.message = Image(header=Header(seq=2), data=loan.array)
        async with BusPeer(domain.uri, "frames", "shm"):
            await pub.wait_for_subscribers(1, timeout_s=20)
            await seen.wait_for_publishers(1, timeout_s=20)
            await _loan_frame(pub, 3, in_place=True)
            assert await _seen(seen, 3) == _expect(3)
            await pub.aclose()  # the publisher restarts: a new one on the same topic
            pub2 = await node.create_publisher(Image, TOPIC, qos=latest())
            await pub2.wait_for_subscribers(1, timeout_s=20)
            await _loan_frame(pub2, 4, in_place=True)
            assert await _seen(seen, 4) == _expect(4)
            assert pub2._sinks[0].conn.frames_loaned == 1  # type: ignore[attr-defined]


@pytest.mark.slow
async def test_over_tcp_a_loan_is_a_buffer_of_our_own_sent_with_one_copy() -> None:
    async with open_domain() as domain, open_node("cam", domain=domain, transport="tcp") as node:
        pub, seen = await _peer_and_topics(node)
        async with BusPeer(domain.uri, "frames", "tcp"):
            await pub.wait_for_subscribers(1, timeout_s=20)
            await seen.wait_for_publishers(1, timeout_s=20)
            for seq in (1, 2):
                await _loan_frame(pub, seq, in_place=False)
                got = await _seen(seen, seq)
                assert got[:2] == _expect(seq)[:2] and got[3:] == _expect(seq)[3:]
            assert pub.loaned_in_place == 0 and pub.published == 2


async def test_in_process_subscribers_get_the_loaned_object_and_bad_loans_publish_nothing() -> None:
    async with open_domain() as domain, open_node("cam", domain=domain) as node:
        pub = await node.create_publisher(Image, TOPIC, qos=latest())
        sub = await node.create_subscription(Image, TOPIC, qos=latest())
        await _loan_frame(pub, 1, in_place=False)
        got = sub.latest()
        assert got is not None and got.header.seq == 1 and int(got.data[0, 0, 0]) == 1
        with pytest.raises(CodecError, match="message was not set"):
            async with pub.loan(SHAPE):
                pass
        with pytest.raises(CodecError, match="exactly one array, the loan's own"):
            async with pub.loan(SHAPE) as loan:
                loan.message = Image(header=Header(seq=9), data=np.zeros(SHAPE, np.uint8))
        with pytest.raises(CodecError, match="expected Image, got Data"):
            async with pub.loan(SHAPE) as bad:
                bad.message = Data(value=1)  # type: ignore[assignment]
        with pytest.raises(RuntimeError, match="the renderer failed"):
            async with pub.loan(SHAPE):
                raise RuntimeError("the renderer failed")
        assert pub.published == 1 and sub.received == 1 and sub.latest() is got
