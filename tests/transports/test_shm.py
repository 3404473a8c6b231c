"""shm:// specifics beyond the contract: segment lifetime, idle CPU, hostile hellos, backpressure, streaming."""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing as mp
import os
import random
import signal
import socket
import threading
import time
from collections.abc import AsyncIterator, Callable, Iterator

import pytest

from uniros_async.errors import ConfigError, TransportBrokenError, TransportClosedError
from uniros_async.testing.transport_contract import open_pair
from uniros_async.transports import shm
from uniros_async.transports._shm_ring import PURE_PYTHON_ENV, compiled_ring_end
from uniros_async.transports.base import TransportOptions, connect, listen

T_S = 10.0
SMALL_RING = TransportOptions(ring_bytes=4096)


@pytest.fixture(autouse=True, params=["compiled", "python"])
def ring_end(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Every test here runs with either RingEnd on both ends (spawned peers inherit it with the environment)."""
    if request.param == "python":
        monkeypatch.setenv(PURE_PYTHON_ENV, "1")
    else:
        monkeypatch.delenv(PURE_PYTHON_ENV, raising=False)
        assert compiled_ring_end() is not None, "the compiled RingEnd is not built: pip install -e . needs gcc"
    return str(request.param)


def _dev_shm() -> set[str]:
    return set(os.listdir("/dev/shm"))


def _our_mappings() -> int:
    with open("/proc/self/maps") as f:
        return sum("memfd:uniros-shm" in line for line in f)


def _open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


@contextlib.contextmanager
def _no_spin() -> Iterator[None]:
    """Make receive() sleep at once, so tests exercise the doorbell path rather than the spin."""
    old = shm.ShmTransport.spin_ns
    shm.ShmTransport.spin_ns = 0
    try:
        yield
    finally:
        shm.ShmTransport.spin_ns = old


@contextlib.asynccontextmanager
async def _counting_listener(**kw: object) -> AsyncIterator[shm.ShmListener]:
    lst = await listen("shm://", TransportOptions(**kw))  # type: ignore[arg-type]
    assert isinstance(lst, shm.ShmListener)
    try:
        yield lst
    finally:
        await lst.aclose()


async def _until(cond: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + T_S
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.005)


# ---------------------------------------------------------------------------------------------- segment lifetime


async def test_nothing_left_after_clean_close() -> None:
    before_shm, before_fds, before_maps = _dev_shm(), _open_fds(), _our_mappings()
    async with open_pair("shm://") as (a, b, _):
        assert _our_mappings() == before_maps + 2  # one mapping per end, of one memfd
        await a.send(b"x" * 277)
        held = await b.receive()  # a zero-copy view outliving the transport must not crash anything
    assert bytes(held) == b"x" * 277
    del held
    assert _dev_shm() == before_shm
    assert _open_fds() == before_fds
    assert _our_mappings() == before_maps


def _client_then_hang(uri: str, conn: mp.connection.Connection) -> None:
    async def main() -> None:
        t = await connect(uri, TransportOptions())
        await t.send(b"from the doomed peer")
        conn.send("sent")
        await asyncio.sleep(60)  # until SIGKILLed

    asyncio.run(main())


@pytest.mark.slow
async def test_nothing_left_after_peer_is_killed() -> None:
    before_shm, before_maps = _dev_shm(), _our_mappings()
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    async with _counting_listener() as lst:
        proc = ctx.Process(target=_client_then_hang, args=(lst.uri, child), daemon=True)
        proc.start()
        child.close()
        try:
            async with asyncio.timeout(30):
                t = await lst.accept()
                try:
                    assert bytes(await t.receive()) == b"from the doomed peer"
                    assert await asyncio.to_thread(parent.poll, 20)
                    blocked = asyncio.ensure_future(t.receive())
                    await asyncio.sleep(0.05)
                    os.kill(proc.pid, signal.SIGKILL)
                    with pytest.raises(TransportBrokenError, match="peer .* closed the connection"):
                        await blocked
                    with pytest.raises(TransportBrokenError):
                        await t.send(b"to nobody")
                finally:
                    await t.aclose()
        finally:
            proc.kill()
            proc.join(10)
            parent.close()
    assert _dev_shm() == before_shm
    assert _our_mappings() == before_maps


@pytest.mark.slow
async def test_nothing_left_after_the_creating_listener_is_killed() -> None:
    """The listener process created the segment; SIGKILL it mid-connection and nothing stays behind."""
    before_shm, before_maps = _dev_shm(), _our_mappings()
    async with _echo_process() as (uri, proc):
        t = await connect(uri, TransportOptions())
        try:
            async with asyncio.timeout(T_S):
                await t.send(b"ping")
                assert bytes(await t.receive()) == b"ping"
                os.kill(proc.pid, signal.SIGKILL)
                with pytest.raises(TransportBrokenError, match="closed the connection"):
                    await t.receive()
        finally:
            await t.aclose()
    assert _dev_shm() == before_shm
    assert _our_mappings() == before_maps


# ---------------------------------------------------------------------------------------------------- idle CPU


def _cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime


@pytest.mark.slow
async def test_idle_ends_do_not_spin() -> None:
    """After a burst of round trips (spinning pays off then), both ends go idle without burning CPU."""
    async with _echo_process() as (uri, proc):
        t = await connect(uri, TransportOptions())
        try:
            async with asyncio.timeout(T_S):
                for _ in range(200):
                    await t.send(b"x" * 277)
                    await t.receive()
            cpu0, peer_cpu0, wall0 = time.process_time(), _cpu_s(proc.pid), time.monotonic()
            with pytest.raises(TimeoutError):
                async with asyncio.timeout(1.0):
                    await t.receive()
            wall = time.monotonic() - wall0
            cpu, peer_cpu = time.process_time() - cpu0, _cpu_s(proc.pid) - peer_cpu0
            assert cpu / wall < 0.05, f"an idle receive used {cpu / wall:.1%} of a CPU"
            assert peer_cpu / wall < 0.05, f"the idle echo process used {peer_cpu / wall:.1%} of a CPU"
            await t.send(b"still works")
            assert bytes(await t.receive()) == b"still works"
        finally:
            await t.aclose()


# ----------------------------------------------------------------------------------------------------- hostile


async def test_malformed_hello_is_rejected_and_counted() -> None:
    async with _counting_listener(connect_timeout_s=0.3) as lst:
        address = "\0uniros-shm-" + lst.uri.removeprefix("shm://")
        loop = asyncio.get_running_loop()
        for junk in (b"GET / HTTP/1.1\r\n\r\n", b"UNRSHM01" + bytes(3), b"UNRSHM01" + bytes(48), b""):
            with socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET) as raw:
                raw.setblocking(False)
                await loop.sock_connect(raw, address)
                if junk:
                    await loop.sock_sendall(raw, junk)
                    async with asyncio.timeout(T_S):
                        reply = await loop.sock_recv(raw, 256)  # a refusal, then EOF
                        while reply:
                            reply = await loop.sock_recv(raw, 256)
        await _until(lambda: lst.rejected == 4, "four rejections")
        with socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET) as silent:  # dropped after connect_timeout_s
            silent.setblocking(False)
            await loop.sock_connect(silent, address)
            await _until(lambda: lst.rejected == 5, "the silent peer to time out")
        acc = asyncio.ensure_future(lst.accept())
        c = await connect(lst.uri, TransportOptions())
        s = await acc
        await c.send(b"a good peer still gets in")
        assert bytes(await s.receive()) == b"a good peer still gets in"
        await c.aclose()
        await s.aclose()


async def test_frame_over_receivers_limit_drops_the_connection() -> None:
    async with (
        _counting_listener(max_frame_bytes=1000) as lst,
        contextlib.AsyncExitStack() as stack,
    ):
        acc = asyncio.ensure_future(lst.accept())
        c = await connect(lst.uri, TransportOptions())
        stack.push_async_callback(c.aclose)
        s = await acc
        stack.push_async_callback(s.aclose)
        await c.send(bytes(2000))
        with pytest.raises(TransportBrokenError, match="2000"):
            await s.receive()
        assert s.stats.rejected == 1
        with pytest.raises(TransportBrokenError):  # the sender learns: the receiver hung up
            async with asyncio.timeout(T_S):
                await c.receive()


async def test_name_taken_and_nobody_listening() -> None:
    async with _counting_listener() as lst:
        with pytest.raises(ConfigError, match="already listening"):
            await listen(lst.uri, TransportOptions())
    with pytest.raises(TimeoutError):
        await connect(lst.uri, TransportOptions(connect_timeout_s=0.2))
    with pytest.raises(ConfigError):
        await connect("shm://", TransportOptions())


# ------------------------------------------------------------------------------- backpressure, wrap, streaming


async def test_backpressure_wrap_and_streaming_through_a_small_ring() -> None:
    """Frames of every size (contiguous, wrapped, skipped, larger than the ring) arrive intact and in order while
    the writer keeps hitting a full ring and the reader an empty one."""
    rng = random.Random(7)
    sizes = [rng.choice([0, 1, 7, 8, 9, 100, 1000, 2040, 3000, 4088, 4089, 9000, 20000]) for _ in range(600)]
    payloads = [rng.randbytes(n) for n in sizes]
    with _no_spin():
        async with open_pair("shm://", SMALL_RING) as (a, b, _):

            async def produce() -> None:
                for p in payloads:
                    await a.send(p)

            async with asyncio.timeout(T_S), asyncio.TaskGroup() as tg:
                tg.create_task(produce())
                for i, p in enumerate(payloads):
                    got = await b.receive()
                    assert bytes(got) == p, f"frame {i} of {len(p)} bytes corrupted"
                    if i % 50 == 0:
                        await asyncio.sleep(0.002)
            assert b.stats.frames_received == len(payloads) and b.stats.bytes_received == sum(sizes)


async def test_zero_copy_views_are_read_only_and_multipart_of_any_format() -> None:
    import numpy as np  # here, not at the top: spawned helper processes import this module

    arr = np.arange(12, dtype=np.float64).reshape(3, 4)
    async with open_pair("shm://") as (a, b, _):
        await a.send([arr, memoryview(arr)[::2], b"end"])
        got = await b.receive()
        assert got.readonly
        assert bytes(got) == arr.tobytes() + arr[::2].tobytes() + b"end"
        out = np.frombuffer(got, dtype=np.float64, count=12).reshape(3, 4)
        assert np.array_equal(out, arr)


async def test_cancelled_streamed_send_is_finished_in_the_background() -> None:
    big = os.urandom(100_000)  # 25 rings' worth
    async with open_pair("shm://", SMALL_RING) as (a, b, _):
        async with asyncio.timeout(T_S):
            sender = asyncio.ensure_future(a.send(big))
            await asyncio.sleep(0.02)  # the ring is full, nobody reads
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await sender
            after = asyncio.ensure_future(a.send(b"after"))  # waits for the rest of the big frame to go
            assert bytes(await b.receive()) == big
            assert bytes(await b.receive()) == b"after"
            await after


async def test_cancelled_streamed_receive_resumes() -> None:
    big = os.urandom(50_000)
    async with open_pair("shm://", SMALL_RING) as (a, b, _):
        async with asyncio.timeout(T_S), asyncio.TaskGroup() as tg:
            tg.create_task(a.send(big))
            cancelled_mid_frame = 0
            for _ in range(3):  # cancel receive() as soon as it has collected more of the frame
                r = asyncio.ensure_future(b.receive())
                got_before = b._rx_partial.got if b._rx_partial else 0  # type: ignore[attr-defined]
                while not (b._rx_partial is not None and b._rx_partial.got > got_before):  # type: ignore[attr-defined]  # noqa: ASYNC110 - must observe every step
                    await asyncio.sleep(0)
                r.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await r
                cancelled_mid_frame += b._rx_partial is not None  # type: ignore[attr-defined]
            assert cancelled_mid_frame == 3
            assert bytes(await b.receive()) == big


async def test_try_send_sends_at_once_or_sends_nothing() -> None:
    """``try_send`` (the supervisor's send outside the event loop) writes a frame when the ring has room and
    returns False, having written nothing, when it would have to wait or stream, or the connection is closed."""
    async with open_pair("shm://", SMALL_RING) as (a, b, _):
        async with asyncio.timeout(T_S):
            assert a.try_send(b"first")
            assert a.try_send(bytes(3000))  # room for it beside the first
            assert not a.try_send(bytes(3000))  # the ring is full: nothing written
            assert not a.try_send(bytes(20000))  # larger than the ring: send() streams it
            assert a.stats.frames_sent == 2
            assert bytes(await b.receive()) == b"first"
            assert bytes(await b.receive()) == bytes(3000)
            await a.send(b"after")  # the ring is consistent: the next frames follow in order
            assert a.try_send(b"last")
            assert bytes(await b.receive()) == b"after"
            assert bytes(await b.receive()) == b"last"
            await a.aclose()
            assert not a.try_send(b"closed")


async def test_aclose_wakes_a_sender_blocked_on_a_full_ring() -> None:
    async with open_pair("shm://", SMALL_RING) as (a, b, _):
        async with asyncio.timeout(T_S):
            await a.send(bytes(3000))
            blocked = asyncio.ensure_future(a.send(bytes(3000)))
            await asyncio.sleep(0.02)
            assert not blocked.done()
            await a.aclose()
            with pytest.raises(TransportClosedError):
                await blocked


# ---------------------------------------------------------------------------------------------- cross-process


def _echo_main(uri_out: mp.connection.Connection, ring_bytes: int, spin_ns: int) -> None:
    shm.ShmTransport.spin_ns = spin_ns

    async def main() -> None:
        async with await listen("shm://", TransportOptions(ring_bytes=ring_bytes)) as lst:
            uri_out.send(lst.uri)
            async with await lst.accept() as t:
                with contextlib.suppress(TransportBrokenError):
                    while True:
                        await t.send(await t.receive())

    asyncio.run(main())


@contextlib.asynccontextmanager
async def _echo_process(
    ring_bytes: int = TransportOptions().ring_bytes, spin_ns: int = shm.ShmTransport.spin_ns
) -> AsyncIterator[tuple[str, mp.process.BaseProcess]]:
    """An echo server for one peer in a spawned process; yields its URI and the process."""
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_echo_main, args=(child, ring_bytes, spin_ns), daemon=True)
    proc.start()
    child.close()
    try:
        assert await asyncio.to_thread(parent.poll, 30), "echo process did not start"
        yield parent.recv(), proc
    finally:
        parent.close()
        await asyncio.to_thread(proc.join, 10)
        if proc.is_alive():
            proc.kill()
            proc.join(5)


@pytest.mark.slow
async def test_cross_process_no_lost_wakeups() -> None:
    """Both ends sleep on every empty or full ring (no spin), with many transitions: a lost wakeup would hang."""
    async with _echo_process(ring_bytes=4096, spin_ns=0) as (uri, _):
        with _no_spin():
            t = await connect(uri, SMALL_RING)
            try:
                async with asyncio.timeout(20):
                    n = 3000

                    async def produce() -> None:
                        for i in range(n):
                            await t.send(i.to_bytes(4, "little") * (1 + i % 200))

                    async with asyncio.TaskGroup() as tg:
                        tg.create_task(produce())
                        for i in range(n):
                            got = await t.receive()
                            assert bytes(got) == i.to_bytes(4, "little") * (1 + i % 200)
                    for i in range(300):  # ping-pong: every receive sleeps
                        await t.send(b"%d" % i)
                        assert bytes(await t.receive()) == b"%d" % i
            finally:
                await t.aclose()


async def test_receive_blocking_gets_replies_without_the_event_loop() -> None:
    """``receive_blocking`` (the supervisor's wait for its workers' replies, in the agent's thread) delivers what
    ``receive`` would, through both the spin and the sleep on the doorbell (an echo in another process); it returns
    None, consuming nothing, when nothing comes within its timeout, and when the peer hangs up, after which
    ``receive`` reports the hang-up."""
    async with _echo_process() as (uri, proc):
        t = await connect(uri)
        assert isinstance(t, shm.ShmTransport)
        try:
            for i in range(200):  # spinning: the echo answers within the window
                assert t.try_send(b"%d" % i)
                assert bytes(t.receive_blocking(T_S) or b"") == b"%d" % i
            with _no_spin():  # set on the open connection: it stops spinning at once
                for i in range(50):  # sleeping on the doorbell every time
                    assert t.try_send(b"x" * (i + 1))
                    assert bytes(t.receive_blocking(T_S) or b"") == b"x" * (i + 1)
            t0 = time.monotonic()
            assert t.receive_blocking(0.05) is None  # nothing was sent: nothing comes
            assert 0.04 < time.monotonic() - t0 < 2.0
            assert t.try_send(b"after the timeout")
            async with asyncio.timeout(T_S):
                assert bytes(await t.receive()) == b"after the timeout"  # nothing was lost or consumed
            proc.kill()
            await asyncio.to_thread(proc.join, T_S)
            assert t.receive_blocking(T_S) is None  # the control socket's EOF: handed to receive()
            with pytest.raises(TransportBrokenError):
                async with asyncio.timeout(T_S):
                    await t.receive()
        finally:
            await t.aclose()
        assert t.receive_blocking(0.0) is None  # closed


async def test_loan_writes_in_the_ring_and_guards_its_frame() -> None:
    """A loan is the frame's place in the ring (the receiver's view shows the same bytes with no copy in between);
    while it is out, nothing else is sent on that end; a loan whose end closed meanwhile sends nothing."""
    async with open_pair("shm://") as (a, b, _):
        assert isinstance(a, shm.ShmTransport)
        async with asyncio.timeout(T_S):
            for _ in range(3):
                async with a.loan(640 * 480 * 3) as buf:
                    assert buf.obj is a._tx.data.obj  # type: ignore[attr-defined]  # the ring's own memory
                    buf[:4] = b"\x01\x02\x03\x04"
                    with pytest.raises(RuntimeError, match="loaned frame"):
                        await a.send(b"in between")
                    assert not a.try_send(b"in between")
                got = await b.receive()
                assert got.nbytes == 640 * 480 * 3 and bytes(got[:4]) == b"\x01\x02\x03\x04"
            with pytest.raises(TransportClosedError):
                async with a.loan(100) as buf:
                    buf[:] = bytes(100)
                    await a.aclose()
            assert a.stats.frames_sent == 3


@pytest.mark.parametrize("where", ["spinning", "sleeping"])
async def test_aclose_while_another_thread_waits_in_receive_blocking(ring_end: str, where: str) -> None:
    """Closing is not meant to race a ``receive_blocking`` in another thread, but it must not fail, hang or crash.
    While that thread spins, the compiled ring end (whose poll runs without the GIL) keeps the ring's buffers until
    its poll ends, ``aclose`` leaves them to it, and the poll then gives up (None); the Python ring end's poll stops
    at the released views (ValueError). While it sleeps in poll(2), the closed doorbell wakes it (None)."""
    async with open_pair("shm://") as (_, b, _):
        assert isinstance(b, shm.ShmTransport)
        if where == "spinning":  # a 0.3 s poll (in one process an end does not spin unless told to)
            b.spin_ns = 300_000_000
            b._spin_allowed, b._spin_credit = True, 4
        out: list[object] = []

        def wait() -> None:
            try:
                out.append(b.receive_blocking(1.0))
            except ValueError as exc:  # "operation forbidden on released memoryview object"
                out.append(exc)

        thread = threading.Thread(target=wait)
        thread.start()
        await asyncio.sleep(0.05)
        await b.aclose()  # raised BufferError while the compiled ring end's poll held the views
        await asyncio.to_thread(thread.join, 5.0)
        assert not thread.is_alive()
        if where == "spinning" and ring_end == "python":
            assert len(out) == 1 and isinstance(out[0], ValueError)
        else:
            assert out == [None]  # nothing to return: receive() says why
        with pytest.raises(TransportClosedError):
            await b.receive()
