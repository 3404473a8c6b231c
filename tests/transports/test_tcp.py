"""tcp:// specifics beyond the shared contract: hostile and broken peers, connect backoff, binding, buffers."""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import os
import socket
import struct
import time
from collections.abc import AsyncIterator

import pytest

from uniros_async.errors import AuthenticationError, FrameTooLargeError, TransportBrokenError, TransportClosedError
from uniros_async.testing import transport_contract as contract
from uniros_async.transports import tcp
from uniros_async.transports._spin import SPIN_CREDIT
from uniros_async.transports.base import TransportOptions, connect, listen

T_S = 5.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.asynccontextmanager
async def _listening(
    options: TransportOptions | None = None, uri: str = "tcp://127.0.0.1:0"
) -> AsyncIterator[tcp.TcpListener]:
    lst = await listen(uri, options or TransportOptions())
    assert isinstance(lst, tcp.TcpListener)
    try:
        yield lst
    finally:
        await lst.aclose()


async def _close(writer: asyncio.StreamWriter) -> None:
    writer.close()
    with contextlib.suppress(OSError):
        await writer.wait_closed()


async def _raw_peer(
    lst: tcp.TcpListener, *, version: int = tcp.PROTOCOL_VERSION, flags: int = 0, max_frame: int = 2**32 - 1
) -> tuple[asyncio.StreamReader, asyncio.StreamWriter, bytes]:
    """A socket that speaks the hello by hand; returns the listener's hello too."""
    reader, writer = await asyncio.open_connection(*lst.address)
    writer.write(tcp.HELLO.pack(tcp.MAGIC, version, flags, max_frame, b"n" * 32))
    theirs = await reader.readexactly(tcp.HELLO.size)
    return reader, writer, theirs


async def _exchange_works(lst: tcp.TcpListener, options: TransportOptions | None = None) -> None:
    acc = asyncio.ensure_future(lst.accept())
    c = await connect(lst.uri, options or TransportOptions())
    s = await acc
    try:
        await c.send(b"ping")
        assert bytes(await s.receive()) == b"ping"
        await s.send(b"pong")
        assert bytes(await c.receive()) == b"pong"
    finally:
        await c.aclose()
        await s.aclose()


# ------------------------------------------------------------------------------------------ hostile peers


async def test_oversize_header_rejected_and_counted_others_keep_working() -> None:
    async with asyncio.timeout(T_S), _listening(TransportOptions(max_frame_bytes=1000)) as lst:
        acc = asyncio.ensure_future(lst.accept())
        good = await connect(lst.uri, TransportOptions(max_frame_bytes=1000))
        good_srv = await acc
        acc = asyncio.ensure_future(lst.accept())
        reader, writer, _ = await _raw_peer(lst)
        bad_srv = await acc
        try:
            writer.write((10**9).to_bytes(4, "little"))  # announces 1 GB: must be refused without allocating it
            with pytest.raises(TransportBrokenError, match="1000000000"):
                await bad_srv.receive()
            assert bad_srv.stats.rejected == 1
            assert lst.rejected == 1
            assert await reader.read() == b""  # dropped
            await good.send(b"still here")
            assert bytes(await good_srv.receive()) == b"still here"
            await _exchange_works(lst, TransportOptions(max_frame_bytes=1000))
        finally:
            await _close(writer)
            for t in (good, good_srv, bad_srv):
                await t.aclose()


@pytest.mark.parametrize(
    "junk",
    [b"GET / HTTP/1.1\r\nHost: localhost\r\n\r\n", b"\x00" * 64, tcp.MAGIC[:5] + b"garbage" * 10],
    ids=["http", "zeros", "magic-prefix"],
)
async def test_garbage_hello_rejected_and_counted(junk: bytes) -> None:
    async with asyncio.timeout(T_S), _listening() as lst:
        reader, writer = await asyncio.open_connection(*lst.address)
        try:
            writer.write(junk)
            with contextlib.suppress(ConnectionResetError):
                await reader.read()  # the listener's hello, then its close
        finally:
            await _close(writer)
        for _ in range(100):
            if lst.rejected:
                break
            await asyncio.sleep(0.01)
        assert lst.rejected == 1
        await _exchange_works(lst)


async def test_silent_peer_times_out_in_the_handshake() -> None:
    async with asyncio.timeout(T_S), _listening(TransportOptions(handshake_timeout_s=0.2)) as lst:
        reader, writer = await asyncio.open_connection(*lst.address)
        try:
            t0 = time.monotonic()
            assert len(await reader.read()) == tcp.HELLO.size  # our hello, then the close after the timeout
            assert time.monotonic() - t0 < 2.0
        finally:
            await _close(writer)
        assert lst.rejected == 1
        await _exchange_works(lst)


async def test_wrong_version_rejected() -> None:
    async with asyncio.timeout(T_S), _listening() as lst:
        reader, writer, theirs = await _raw_peer(lst, version=99)
        try:
            assert tcp.HELLO.unpack(theirs)[1] == tcp.PROTOCOL_VERSION  # the peer learns which version we speak
            assert await reader.read() == b""
        finally:
            await _close(writer)
        assert lst.rejected == 1


async def test_wrong_proof_rejected_listener_keeps_serving() -> None:
    opts = TransportOptions(auth_key=b"k")
    async with asyncio.timeout(T_S), _listening(opts) as lst:
        reader, writer, _ = await _raw_peer(lst, flags=tcp.FLAG_AUTH)
        try:
            await reader.readexactly(tcp.PROOF_BYTES)  # the listener proves itself first
            writer.write(hmac.new(b"guess", b"x", hashlib.sha256).digest())
            assert await reader.read() == b""
        finally:
            await _close(writer)
        assert lst.rejected == 1
        await _exchange_works(lst, opts)


async def test_client_with_key_refuses_listener_without_key() -> None:
    async with asyncio.timeout(T_S), _listening() as lst:
        with pytest.raises(AuthenticationError, match="does not authenticate"):
            await connect(lst.uri, TransportOptions(auth_key=b"k", connect_timeout_s=2))
        for _ in range(100):
            if lst.rejected:
                break
            await asyncio.sleep(0.01)
        assert lst.rejected == 1


async def test_connect_to_a_non_uniros_server_fails_fast() -> None:
    async def http(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n" + b" " * 64)
        await writer.drain()
        writer.close()

    server = await asyncio.start_server(http, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        async with asyncio.timeout(T_S):
            with pytest.raises(TransportBrokenError, match="not a uniros tcp peer"):
                await connect(f"tcp://127.0.0.1:{port}", TransportOptions(connect_timeout_s=2))
    finally:
        server.close()
        await server.wait_closed()


# ------------------------------------------------------------------------------------------ broken peers


async def test_peer_disconnecting_mid_frame_breaks_only_that_connection() -> None:
    async with asyncio.timeout(T_S), _listening() as lst:
        acc = asyncio.ensure_future(lst.accept())
        good = await connect(lst.uri, TransportOptions())
        good_srv = await acc
        acc = asyncio.ensure_future(lst.accept())
        reader, writer, _ = await _raw_peer(lst)
        half_srv = await acc
        try:
            writer.write((5).to_bytes(4, "little") + b"whole")  # one complete frame first
            writer.write((1000).to_bytes(4, "little") + bytes(500))  # then half a frame
            await writer.drain()
            await _close(writer)
            assert bytes(await half_srv.receive()) == b"whole"  # complete frames are still delivered
            with pytest.raises(TransportBrokenError, match="middle of a frame"):
                await half_srv.receive()
            with pytest.raises(TransportBrokenError):
                await half_srv.send(b"x")
            await good.send(b"unaffected")
            assert bytes(await good_srv.receive()) == b"unaffected"
        finally:
            for t in (good, good_srv, half_srv):
                await t.aclose()


async def test_peer_reset_breaks_with_the_oserror_as_cause() -> None:
    async with asyncio.timeout(T_S), _listening() as lst:
        acc = asyncio.ensure_future(lst.accept())
        reader, writer, _ = await _raw_peer(lst)
        srv = await acc
        try:
            writer.write((5).to_bytes(4, "little") + b"whole")
            await writer.drain()
            assert bytes(await srv.receive()) == b"whole"
            sock = writer.get_extra_info("socket")
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # close() sends RST
            writer.transport.abort()
            with pytest.raises(TransportBrokenError) as info:
                await srv.receive()
            assert isinstance(info.value.__cause__, OSError)
        finally:
            await _close(writer)
            await srv.aclose()


async def test_peer_closing_cleanly_after_frames() -> None:
    async with asyncio.timeout(T_S), contract.open_pair("tcp://127.0.0.1:0") as (a, b, _):
        for i in range(5):
            await a.send(b"%d" % i)
        await a.aclose()
        for i in range(5):
            assert bytes(await b.receive()) == b"%d" % i
        with pytest.raises(TransportBrokenError, match="closed the connection"):
            await b.receive()


# ------------------------------------------------------------------------------------------ connecting


async def test_connect_to_nobody_times_out_within_connect_timeout() -> None:
    port = _free_port()
    t0 = time.monotonic()
    with pytest.raises(TimeoutError, match=f"tcp://127.0.0.1:{port}"):
        await connect(f"tcp://127.0.0.1:{port}", TransportOptions(connect_timeout_s=0.3))
    assert time.monotonic() - t0 < 5 * 0.3  # the 0.3 s asked for, not the default 10 s (slack for a busy host)


async def test_listener_started_after_connect_began_is_reached() -> None:
    port = _free_port()
    uri = f"tcp://127.0.0.1:{port}"
    async with asyncio.timeout(T_S):
        dialing = asyncio.ensure_future(connect(uri, TransportOptions(connect_timeout_s=3)))
        await asyncio.sleep(0.3)  # several refused attempts
        assert not dialing.done()
        async with _listening(uri=uri) as lst:
            s = await lst.accept()
            c = await dialing
            try:
                await c.send(b"made it")
                assert bytes(await s.receive()) == b"made it"
            finally:
                await c.aclose()
                await s.aclose()


async def test_binds_loopback_by_default() -> None:
    async with _listening(uri="tcp://:0") as lst:
        host, port = lst.address
        assert host == "127.0.0.1"
        assert lst.uri == f"tcp://127.0.0.1:{port}"
        acc = asyncio.ensure_future(lst.accept())
        c = await connect(lst.uri, TransportOptions())
        s = await acc
        try:
            assert s.sockname == ("127.0.0.1", port)
            assert c.peer == lst.uri
        finally:
            await c.aclose()
            await s.aclose()
    async with _listening(TransportOptions(bind_host="127.0.0.2"), uri="tcp://:0") as lst:
        assert lst.address[0] == "127.0.0.2"  # bind_host applies when the URI names no host
    async with _listening(TransportOptions(bind_host="127.0.0.2"), uri="tcp://127.0.0.1:0") as lst:
        assert lst.address[0] == "127.0.0.1"  # the URI's host wins


# ------------------------------------------------------------------------------------------ buffers and flow


async def test_peer_limit_refused_on_send() -> None:
    async with (
        asyncio.timeout(T_S),
        contract.open_pair("tcp://127.0.0.1:0", TransportOptions(), TransportOptions(max_frame_bytes=100_000)) as (
            small,
            big,
            _,
        ),
    ):
        with pytest.raises(FrameTooLargeError, match="peer's max_frame_bytes=100000"):
            await big.send(bytes(100_001))
        await big.send(bytes(100_000))
        assert (await small.receive()).nbytes == 100_000


async def test_held_views_survive_later_receives_and_sizes_mix() -> None:
    sizes = [300_000, 5, 1_000_000, 16 * 1024 - 1, 16 * 1024, 70_000, 0, 300_000, 300_000, 2_000_000, 300_000]
    payloads = [os.urandom(n) for n in sizes]
    async with asyncio.timeout(T_S), contract.open_pair("tcp://127.0.0.1:0") as (a, b, _):
        for p in payloads:
            await a.send(p)
        held = []
        for p in payloads:
            view = await b.receive()
            assert bytes(view) == p
            held.append(view)
        assert [bytes(v) for v in held] == payloads  # pooled buffers are reused only once nobody holds them
        assert b.stats.frames_received == len(sizes) and b.stats.bytes_received == sum(sizes)
        assert a.stats.frames_sent == len(sizes) and a.stats.bytes_sent == sum(sizes)


async def test_sender_may_reuse_its_buffer_at_once() -> None:
    image = bytearray(os.urandom(640 * 480 * 3))
    originals = []
    async with asyncio.timeout(T_S), contract.open_pair("tcp://127.0.0.1:0") as (a, b, _):
        for i in range(8):
            image[:4] = i.to_bytes(4, "little")
            originals.append(bytes(image))
            await a.send([memoryview(image)])
            image[:] = b"\xff" * 64 + image[64:]  # scribble on it right after send returns
        for expected in originals:
            assert bytes(await b.receive()) == expected


async def test_cancelled_send_under_backpressure_leaves_no_half_frame() -> None:
    chunk = 256 * 1024
    async with asyncio.timeout(T_S), contract.open_pair("tcp://127.0.0.1:0") as (a, b, _):
        sent = 0
        while True:  # nobody reads: eventually send must wait for the peer
            try:
                await asyncio.wait_for(a.send(sent.to_bytes(4, "little") + bytes(chunk)), 0.2)
            except TimeoutError:
                break
            sent += 1
            assert sent < 10_000, "send never applied backpressure"
        after = asyncio.ensure_future(a.send(b"after"))  # waits until the reader below catches up
        got = 0
        while True:
            frame = await b.receive()
            if bytes(frame) == b"after":
                break
            assert int.from_bytes(frame[:4], "little") == got and frame.nbytes == chunk + 4
            got += 1
        await after
        assert got in (sent, sent + 1)  # the cancelled frame went out whole or not at all


async def test_many_small_frames_coalesced_in_order() -> None:
    n = 20_000
    async with asyncio.timeout(T_S), contract.open_pair("tcp://127.0.0.1:0") as (a, b, _):

        async def produce() -> None:
            for i in range(n):
                await a.send(i.to_bytes(4, "little") * 8)

        async with asyncio.TaskGroup() as tg:
            tg.create_task(produce())
            for i in range(n):
                assert bytes(await b.receive()) == i.to_bytes(4, "little") * 8


async def test_any_contiguous_buffer_can_be_sent() -> None:
    np = pytest.importorskip("numpy")
    grid = np.arange(12, dtype=np.float64).reshape(3, 4)
    async with asyncio.timeout(T_S), contract.open_pair("tcp://127.0.0.1:0") as (a, b, _):
        await a.send(grid)  # a 2-D float array travels as its bytes
        assert bytes(await b.receive()) == grid.tobytes()
        big = np.ones((480, 640, 3), dtype=np.uint8)
        await a.send([b"head", grid, memoryview(big)])
        assert bytes(await b.receive()) == b"head" + grid.tobytes() + big.tobytes()


async def test_spinning_receive_round_trips_and_closes() -> None:
    async with asyncio.timeout(T_S), contract.open_pair("tcp://127.0.0.1:0") as (a, b, _):
        a.spin_ns = b.spin_ns = 50_000
        for i in range(200):
            await a.send(b"%d" % i)
            assert bytes(await b.receive()) == b"%d" % i
            await b.send(b"ok")
            assert bytes(await a.receive()) == b"ok"
        waiter = asyncio.ensure_future(b.receive())
        await asyncio.sleep(0.05)
        await b.aclose()
        with pytest.raises(TransportClosedError):
            await waiter


async def test_spin_reads_the_socket_without_the_event_loop() -> None:
    """The spin reads frames (small and large) straight from the socket: they are queued before the event loop runs
    again."""
    async with asyncio.timeout(T_S), contract.open_pair("tcp://127.0.0.1:0") as (a, b, _):
        await a.send(b"first")  # written to the socket at once, without a turn of the loop
        assert not b.has_news()
        b._spin(50_000_000)  # synchronous: the loop's reader cannot run meanwhile
        assert b.has_news() and b._spin_credit == SPIN_CREDIT
        assert bytes(await b.receive()) == b"first"
        big = bytes(range(256)) * 160  # 40 KiB: a large frame, read into its own buffer
        await a.send(big)
        assert a._tr.get_write_buffer_size() == 0 and not b.has_news()  # all of it is in the kernel
        b._spin(50_000_000)
        assert b.has_news()
        assert bytes(await b.receive()) == big


async def test_spin_credit_stops_spinning_on_an_idle_connection_and_comes_back() -> None:
    async with asyncio.timeout(T_S), contract.open_pair("tcp://127.0.0.1:0") as (a, b, _):
        b.spin_ns = 20_000
        for _ in range(3):  # only listening (nothing sent since the last receive): no poll, no credit spent
            with pytest.raises(TimeoutError):
                await asyncio.wait_for(b.receive(), 0.005)
        assert b._spin_credit == SPIN_CREDIT
        for _ in range(SPIN_CREDIT):  # a request without an answer: every spin misses and costs credit
            await b.send(b"request")
            with pytest.raises(TimeoutError):
                await asyncio.wait_for(b.receive(), 0.005)
        assert b._spin_credit == 0
        with pytest.raises(TimeoutError):  # no credit: no spin (the credit cannot go below 0)
            await asyncio.wait_for(b.receive(), 0.005)
        assert b._spin_credit == 0
        b.spin_ns = 1_000_000_000  # a window a wait on this loop is shorter than: a spin would have caught it
        await b.send(b"request")
        waiter = asyncio.ensure_future(b.receive())
        await asyncio.sleep(0)
        await a.send(b"soon")
        assert bytes(await waiter) == b"soon"
        assert b._spin_credit == 1  # try spinning again
        b.spin_ns = 0
        await a.send(b"no spin")
        assert bytes(await b.receive()) == b"no spin"


def test_contract_under_uvloop() -> None:
    uvloop = pytest.importorskip("uvloop")

    async def main() -> None:
        for check in contract.CHECKS + contract.AUTH_CHECKS:
            await check("tcp://127.0.0.1:0")
        await test_sender_may_reuse_its_buffer_at_once()
        await test_held_views_survive_later_receives_and_sizes_mix()
        await test_cancelled_send_under_backpressure_leaves_no_half_frame()
        await test_spinning_receive_round_trips_and_closes()
        await test_spin_reads_the_socket_without_the_event_loop()

    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        runner.run(main())


async def test_has_news_and_fileno_tell_a_caller_outside_the_loop_what_waits() -> None:
    import select

    async with _listening() as lst:
        acc = asyncio.ensure_future(lst.accept())
        c = await connect(lst.uri, TransportOptions())
        s = await acc
        assert isinstance(c, tcp.TcpTransport) and isinstance(s, tcp.TcpTransport)
        fd = c.fileno()
        assert fd >= 0 and not c.has_news()
        assert select.select([fd], [], [], 0)[0] == []
        await s.send(b"news")
        async with asyncio.timeout(5):
            while not c.has_news():  # noqa: ASYNC110 - the loop has read the frame: the socket is quiet, has_news not
                await asyncio.sleep(0.001)
        assert bytes(await c.receive()) == b"news" and not c.has_news()
        await s.aclose()
        async with asyncio.timeout(5):
            while not c.has_news():  # noqa: ASYNC110 - the peer's EOF: receive would raise at once
                await asyncio.sleep(0.001)
        await c.aclose()
        assert c.fileno() == -1


async def test_try_send_and_receive_blocking_go_without_the_loop_and_leave_what_they_cannot_take() -> None:
    """The supervisor's way to a tcp worker between calls (as for shm): a small frame written at once, a reply read
    from the socket in the caller's thread. What they cannot do (nothing came in time, a large frame, the peer's
    end of stream) they leave, consuming nothing, to ``send`` / ``receive``, which report it."""
    async with _listening() as lst:
        acc = asyncio.ensure_future(lst.accept())
        c = await connect(lst.uri, TransportOptions())
        s = await acc
        assert isinstance(c, tcp.TcpTransport)
        t0 = time.monotonic()
        assert c.receive_blocking(0.05) is None  # nothing came: it waited its time, took nothing
        assert time.monotonic() - t0 >= 0.04
        assert c.try_send(b"ping")
        assert bytes(await s.receive()) == b"ping"
        await s.send(b"pong")  # on the socket at once: read here, without the loop
        got = c.receive_blocking(T_S)
        assert got is not None and bytes(got) == b"pong"
        await s.send(b"queued")
        async with asyncio.timeout(T_S):
            while not c._frames:  # noqa: ASYNC110 - the loop's reader queues it; no event says when
                await asyncio.sleep(0.001)
        got = c.receive_blocking(0)  # already queued: no wait at all
        assert got is not None and bytes(got) == b"queued"
        assert not c.try_send(bytes(tcp._JOIN_MAX_BYTES + 1))  # a large frame is send's to write
        await c.send(bytes(tcp._JOIN_MAX_BYTES + 1))
        assert len(await s.receive()) == tcp._JOIN_MAX_BYTES + 1
        await s.aclose()
        t0 = time.monotonic()
        assert c.receive_blocking(T_S) is None  # the peer's end of stream, read here: left to receive
        assert time.monotonic() - t0 < T_S / 2
        with pytest.raises(TransportBrokenError, match="closed the connection"):
            await c.receive()
        assert not c.try_send(b"x")
        await c.aclose()
