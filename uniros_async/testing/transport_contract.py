"""The contract every Transport must pass, written once and run against each implementation.

Each check is ``async def check_x(uri: str) -> None`` where ``uri`` is a listen URI of the transport under test
(``memory://``, ``shm://``, ``tcp://127.0.0.1:0``). ``CHECKS`` lists them; ``AUTH_CHECKS`` only apply to
transports that authenticate peers. ``echo_server_main`` runs in a separate process for the cross-process checks.
"""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing as mp
import os
from collections.abc import AsyncIterator, Awaitable, Callable

from uniros_async.errors import (
    AuthenticationError,
    FrameTooLargeError,
    TransportBrokenError,
    TransportClosedError,
)
from uniros_async.transports.base import Listener, Transport, TransportOptions, connect, listen

__all__ = ["AUTH_CHECKS", "CHECKS", "EchoServer", "echo_server_main", "open_pair"]

T_S = 10.0  # every wait in a check is bounded; a hang is a failure, not a stuck CI


@contextlib.asynccontextmanager
async def open_pair(
    uri: str, options: TransportOptions | None = None, client_options: TransportOptions | None = None
) -> AsyncIterator[tuple[Transport, Transport, Listener]]:
    """Listen at ``uri``, connect once, and yield (client end, server end, listener); close all afterwards."""
    options = options or TransportOptions()
    async with asyncio.timeout(T_S):
        lst = await listen(uri, options)
    try:
        async with asyncio.timeout(T_S):
            accept = asyncio.ensure_future(lst.accept())
            try:
                client = await connect(lst.uri, client_options or options)
            except BaseException:
                accept.cancel()
                raise
            server = await accept
        try:
            yield client, server, lst
        finally:
            await client.aclose()
            await server.aclose()
    finally:
        await lst.aclose()


async def check_round_trip_small(uri: str) -> None:
    async with open_pair(uri) as (a, b, _):
        async with asyncio.timeout(T_S):
            for i in range(200):
                payload = i.to_bytes(4, "little") * 70  # 280 B, about a joint state
                await a.send(payload)
                got = await b.receive()
                assert bytes(got) == payload, f"frame {i} corrupted"
                await b.send(got)
                back = await a.receive()
                assert bytes(back) == payload
        assert a.stats.frames_sent == 200 and b.stats.frames_received == 200


async def check_order_and_backpressure(uri: str) -> None:
    """Many frames sent faster than they are read all arrive, in order (RELIABLE)."""
    n = 3000
    async with open_pair(uri) as (a, b, _):

        async def produce() -> None:
            for i in range(n):
                await a.send(i.to_bytes(4, "little") + bytes(i % 300))

        async with asyncio.timeout(T_S * 3), asyncio.TaskGroup() as tg:
            tg.create_task(produce())
            for i in range(n):
                got = await b.receive()
                assert int.from_bytes(got[:4], "little") == i, f"expected frame {i}, got {bytes(got[:4])!r}"
                assert len(got) == 4 + i % 300
                if i % 500 == 0:
                    await asyncio.sleep(0.01)  # a slow reader


async def check_multipart_and_empty(uri: str) -> None:
    async with open_pair(uri) as (a, b, _):
        async with asyncio.timeout(T_S):
            await a.send([b"head", memoryview(b"-middle-"), bytearray(b"tail")])
            assert bytes(await b.receive()) == b"head-middle-tail"
            await a.send(b"")
            assert bytes(await b.receive()) == b""
            await a.send([])
            assert bytes(await b.receive()) == b""


async def check_large_frames(uri: str) -> None:
    image = os.urandom(640 * 480 * 3)
    big = os.urandom(3 * 1024 * 1024)
    async with open_pair(uri) as (a, b, _):
        async with asyncio.timeout(T_S):
            for payload in (image, big, image):
                await a.send(payload)
                assert bytes(await b.receive()) == payload


async def check_oversize_rejected_connection_survives(uri: str) -> None:
    opts = TransportOptions(max_frame_bytes=1000)
    async with open_pair(uri, opts) as (a, b, _):
        async with asyncio.timeout(T_S):
            try:
                await a.send(bytes(1001))
            except FrameTooLargeError as exc:
                assert "1001" in str(exc), f"error should name the size: {exc}"
            else:
                raise AssertionError("an oversize frame was sent")
            await a.send(b"still fine")
            assert bytes(await b.receive()) == b"still fine"


async def check_close_semantics(uri: str) -> None:
    async with open_pair(uri) as (a, b, _):
        async with asyncio.timeout(T_S):
            await a.send(b"before close")
            await a.aclose()
            await a.aclose()  # idempotent
            for op in (a.send(b"x"), a.receive()):
                try:
                    await op
                except TransportClosedError:
                    pass
                else:
                    raise AssertionError("an operation on a closed end succeeded")
            # what was sent before the close is not lost, then the peer learns of the close
            assert bytes(await b.receive()) == b"before close"
            try:
                await b.receive()
            except TransportBrokenError:
                pass
            else:
                raise AssertionError("receive after the peer closed did not raise TransportBrokenError")


async def check_close_with_a_full_backlog_loses_nothing(uri: str) -> None:
    """Frames the peer accepted before closing are all delivered, even when the reader had fallen behind."""
    n = 1024
    async with open_pair(uri) as (a, b, _):
        async with asyncio.timeout(T_S):
            for i in range(n):
                await a.send(i.to_bytes(4, "little"))
            await a.aclose()
            for i in range(n):
                got = await b.receive()
                assert int.from_bytes(got, "little") == i, f"frame {i} lost or reordered at close"
            try:
                await b.receive()
            except TransportBrokenError:
                pass
            else:
                raise AssertionError("receive after the backlog did not report the closed peer")


async def check_close_wakes_blocked_receiver(uri: str) -> None:
    async with open_pair(uri) as (a, b, _):
        async with asyncio.timeout(T_S):
            waiter = asyncio.ensure_future(b.receive())
            await asyncio.sleep(0.05)
            await b.aclose()
            try:
                await waiter
            except TransportClosedError:
                pass
            else:
                raise AssertionError("a blocked receive survived aclose")


async def check_cancelled_receive_leaves_connection_usable(uri: str) -> None:
    async with open_pair(uri) as (a, b, _):
        async with asyncio.timeout(T_S):
            for _ in range(3):
                waiter = asyncio.ensure_future(b.receive())
                await asyncio.sleep(0.02)
                waiter.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await waiter
            await a.send(b"after cancels")
            assert bytes(await b.receive()) == b"after cancels"


async def check_both_directions_at_once(uri: str) -> None:
    n = 500
    async with open_pair(uri) as (a, b, _):

        async def pump(src: Transport, dst: Transport, tag: bytes) -> None:
            async def tx() -> None:
                for i in range(n):
                    await src.send(tag + i.to_bytes(4, "little"))

            async with asyncio.TaskGroup() as tg:
                tg.create_task(tx())
                for i in range(n):
                    got = bytes(await dst.receive())
                    assert got == tag + i.to_bytes(4, "little")

        async with asyncio.timeout(T_S), asyncio.TaskGroup() as tg:
            tg.create_task(pump(a, b, b"ab"))
            tg.create_task(pump(b, a, b"ba"))


async def check_several_peers(uri: str) -> None:
    """One listener serves several connections independently."""
    async with asyncio.timeout(T_S):
        lst = await listen(uri, TransportOptions())
        clients: list[Transport] = []
        servers: list[Transport] = []
        try:
            for _ in range(3):
                acc = asyncio.ensure_future(lst.accept())
                clients.append(await connect(lst.uri, TransportOptions()))
                servers.append(await acc)
            for i, c in enumerate(clients):
                await c.send(b"client %d" % i)
            for i, s in enumerate(servers):
                assert bytes(await s.receive()) == b"client %d" % i
            await clients[0].aclose()
            await clients[1].send(b"others keep working")
            assert bytes(await servers[1].receive()) == b"others keep working"
        finally:
            for t in clients + servers:
                await t.aclose()
            await lst.aclose()


async def check_auth_accepts_right_key(uri: str) -> None:
    opts = TransportOptions(auth_key=b"secret-key")
    async with open_pair(uri, opts) as (a, b, _):
        async with asyncio.timeout(T_S):
            await a.send(b"authenticated")
            assert bytes(await b.receive()) == b"authenticated"


async def check_auth_rejects_wrong_key(uri: str) -> None:
    good = TransportOptions(auth_key=b"secret-key", connect_timeout_s=2.0)
    bad = TransportOptions(auth_key=b"wrong-key", connect_timeout_s=2.0)
    none = TransportOptions(connect_timeout_s=2.0)
    async with asyncio.timeout(T_S):
        lst = await listen(uri, good)
        try:
            for opts in (bad, none):
                acc = asyncio.ensure_future(lst.accept())
                try:
                    t = await connect(lst.uri, opts)
                except (AuthenticationError, TransportBrokenError, TimeoutError):
                    pass
                else:
                    # the server may only notice after the client's first frame
                    try:
                        await t.send(b"intruder")
                        await asyncio.wait_for(t.receive(), 1.0)
                    except (TransportBrokenError, TimeoutError, AuthenticationError):
                        pass
                    else:
                        raise AssertionError("an unauthenticated peer exchanged frames")
                    finally:
                        await t.aclose()
                await asyncio.sleep(0.1)
                assert not acc.done() or acc.exception() is not None, "accept() returned an unauthenticated peer"
                acc.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await acc
            assert lst.rejected >= 2, f"listener counted {lst.rejected} rejections, expected >= 2"
            # the listener still serves a good peer
            acc = asyncio.ensure_future(lst.accept())
            c = await connect(lst.uri, good)
            s = await acc
            await c.send(b"welcome")
            assert bytes(await s.receive()) == b"welcome"
            await c.aclose()
            await s.aclose()
        finally:
            await lst.aclose()


async def check_loaned_frames(uri: str) -> None:
    """``loan``: a frame written in place arrives as written, between ordinary frames and in order, also when a
    loan waits for room or is larger than any ring; a loan whose block raises sends nothing; a loan over
    ``max_frame_bytes`` is refused and the connection stays."""
    async with open_pair(uri, TransportOptions(ring_bytes=64 * 1024, max_frame_bytes=1 << 20)) as (a, b, _):
        async with asyncio.timeout(T_S):
            sizes = [0, 1, 277, 5000, 40_000, 40_000, 200_000]  # two 40 KB loans cannot share a 64 KiB ring
            for i, n in enumerate(sizes):
                pattern = bytes([i + 1]) * n

                async def reader(n: int = n, pattern: bytes = pattern) -> None:
                    assert bytes(await b.receive()) == b"before"
                    got = await b.receive()
                    assert got.nbytes == n and bytes(got) == pattern
                    assert bytes(await b.receive()) == b"after"

                task = asyncio.ensure_future(reader())
                await a.send(b"before")
                async with a.loan(n) as buf:
                    assert len(buf) == n and not buf.readonly
                    buf[:] = pattern
                await a.send(b"after")
                await task
            with contextlib.suppress(ZeroDivisionError):
                async with a.loan(100) as buf:
                    buf[:] = b"z" * 100
                    raise ZeroDivisionError  # an error while writing: nothing goes out
            try:
                async with a.loan((1 << 20) + 1):
                    raise AssertionError("a loan over max_frame_bytes was granted")
            except FrameTooLargeError:
                pass
            await a.send(b"next")
            assert bytes(await b.receive()) == b"next"
            assert a.stats.frames_sent == 3 * len(sizes) + 1


async def check_loans_wait_for_a_slow_reader(uri: str) -> None:
    """``loan`` beside a slow reader: a loan waits for room rather than write over a frame the reader still holds
    (a received view stays as sent until the next ``receive``), and every loaned frame arrives, in order."""
    async with open_pair(uri, TransportOptions(ring_bytes=64 * 1024, max_frame_bytes=1 << 20)) as (a, b, _):
        async with asyncio.timeout(T_S):
            n, size = 12, 30_000  # two frames fill the ring: every loan after them waits for the reader

            async def slow_reader() -> None:
                for i in range(n):
                    got = await b.receive()
                    await asyncio.sleep(0.005)  # holding the view while the writer wants room
                    assert got.nbytes == size and bytes(got[:1]) == bytes(got[-1:]) == bytes([i + 1]), i

            task = asyncio.ensure_future(slow_reader())
            for i in range(n):
                async with a.loan(size) as buf:
                    buf[:] = bytes([i + 1]) * size
            await task


CHECKS: list[Callable[[str], Awaitable[None]]] = [
    check_round_trip_small,
    check_order_and_backpressure,
    check_multipart_and_empty,
    check_large_frames,
    check_oversize_rejected_connection_survives,
    check_close_semantics,
    check_close_with_a_full_backlog_loses_nothing,
    check_close_wakes_blocked_receiver,
    check_cancelled_receive_leaves_connection_usable,
    check_both_directions_at_once,
    check_several_peers,
    check_loaned_frames,
    check_loans_wait_for_a_slow_reader,
]
AUTH_CHECKS: list[Callable[[str], Awaitable[None]]] = [check_auth_accepts_right_key, check_auth_rejects_wrong_key]


# ---------------------------------------------------------------- cross-process: an echo server in its own process


def echo_server_main(uri: str, auth_key: bytes | None, conn: mp.connection.Connection) -> None:
    """Entry point of the echo process: listen at ``uri``, send the concrete URI back over ``conn``, then echo
    every frame of every peer until the parent closes ``conn``."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)

    async def main() -> None:
        opts = TransportOptions(auth_key=auth_key)
        lst = await listen(uri, opts)
        conn.send(lst.uri)
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        loop.add_reader(conn.fileno(), stop.set)  # parent closed the pipe (or died): stop

        async def echo(t: Transport) -> None:
            try:
                while True:
                    await t.send(await t.receive())
            except (TransportBrokenError, TransportClosedError):
                pass
            finally:
                await t.aclose()

        async def serve() -> None:
            async with asyncio.TaskGroup() as tg:
                while True:
                    tg.create_task(echo(await lst.accept()))

        async with asyncio.TaskGroup() as tg:
            server = tg.create_task(serve())
            await stop.wait()
            server.cancel()
        await lst.aclose()

    asyncio.run(main())


class EchoServer:
    """An echo server in a spawned process: ``with EchoServer("tcp://127.0.0.1:0") as uri: ...``."""

    def __init__(self, uri: str, auth_key: bytes | None = None) -> None:
        self._uri = uri
        self._auth_key = auth_key
        ctx = mp.get_context("spawn")
        self._parent, child = ctx.Pipe()
        self._proc = ctx.Process(target=echo_server_main, args=(uri, auth_key, child), daemon=True)
        self._child = child

    def __enter__(self) -> str:
        self._proc.start()
        self._child.close()
        if not self._parent.poll(30):
            self._proc.kill()
            raise TimeoutError("echo server did not start within 30 s")
        return str(self._parent.recv())

    def __exit__(self, *exc: object) -> None:
        self._parent.close()
        self._proc.join(10)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(5)
            raise AssertionError("echo server did not stop within 10 s of being told to")
