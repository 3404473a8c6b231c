"""The tests' delaying relay (``rig.delayrelay``) on loopback: it delays, keeps the order, passes
the end on, and stops reading a sender while its buffer for a receiver that does not read is full."""

from __future__ import annotations

import asyncio
import time

import pytest
from rig.delayrelay import DelayRelay


async def _echo_sink(received: list[tuple[int, bytes]], started: asyncio.Event) -> tuple[asyncio.Server, int]:
    async def on_conn(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while chunk := await reader.read(65536):
            received.append((time.monotonic_ns(), chunk))
        writer.write(b"bye")
        await writer.drain()
        writer.close()

    server = await asyncio.start_server(on_conn, "127.0.0.1", 0)
    started.set()
    return server, int(server.sockets[0].getsockname()[1])


async def _relay_to(port: int, relay: DelayRelay, tg: asyncio.TaskGroup) -> tuple[int, asyncio.Task[None]]:
    # a free port for the relay: bind, read, release (the relay binds it again at once)
    probe = await asyncio.start_server(lambda r, w: None, "127.0.0.1", 0)
    relay_port = int(probe.sockets[0].getsockname()[1])
    probe.close()
    await probe.wait_closed()
    ready = asyncio.Event()
    task = tg.create_task(relay.serve("127.0.0.1", relay_port, ready))
    async with asyncio.timeout(5):
        await ready.wait()
    return relay_port, task


async def test_delays_each_chunk_keeps_the_order_and_passes_the_end_on() -> None:
    received: list[tuple[int, bytes]] = []
    server, port = await _echo_sink(received, asyncio.Event())
    relay = DelayRelay(0.1, 0.05, target=("127.0.0.1", port), seed=1)
    async with server, asyncio.TaskGroup() as tg:
        relay_port, serving = await _relay_to(port, relay, tg)
        reader, writer = await asyncio.open_connection("127.0.0.1", relay_port)
        sent: list[int] = []
        for i in range(20):
            sent.append(time.monotonic_ns())
            writer.write(b"%03d;" % i)
            await writer.drain()
            await asyncio.sleep(0.005)  # separate chunks, so each gets a delay of its own
        writer.write_eof()
        async with asyncio.timeout(10):
            assert await reader.read() == b"bye"  # the end went through, and the answer came back
        writer.close()
        serving.cancel()
    data = b"".join(c for _, c in received)
    assert data == b"".join(b"%03d;" % i for i in range(20))  # every byte, in order
    # no byte came before the least delay (0.1 - 0.05 s) after it was sent
    assert received[0][0] - sent[0] >= 0.05e9
    assert relay.stats.connections == 1 and relay.stats.max_delay_s >= 0.05


async def test_stops_reading_while_its_buffer_is_full_and_the_receiver_does_not_read() -> None:
    stalled = asyncio.Event()
    handled = asyncio.Event()

    async def on_conn(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            await stalled.wait()  # reads nothing until told
            while await reader.read(65536):
                pass
        except ConnectionError:  # the relay's end was reset when it was cancelled
            pass
        finally:
            writer.close()
            handled.set()

    server = await asyncio.start_server(on_conn, "127.0.0.1", 0)
    port = int(server.sockets[0].getsockname()[1])
    relay = DelayRelay(0.0, target=("127.0.0.1", port), max_buffer_bytes=64 * 1024)
    async with server, asyncio.TaskGroup() as tg:
        relay_port, serving = await _relay_to(port, relay, tg)
        _, writer = await asyncio.open_connection("127.0.0.1", relay_port)
        block = b"x" * 65536
        with pytest.raises(TimeoutError):  # the sender is held back: its writes stop draining
            async with asyncio.timeout(2):
                while True:
                    writer.write(block)
                    await writer.drain()
        assert relay.stats.backpressure_waits >= 1
        stalled.set()
        writer.close()
        serving.cancel()
        async with asyncio.timeout(5):  # the target's end is closed before the test ends, not left to the GC
            await handled.wait()
