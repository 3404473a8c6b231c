"""A delaying tcp relay for the fault tests: delay and jitter on an arm's link, which this kernel's qdiscs cannot add
(it has no ``netem``: CONFIG_NET_SCH_NETEM is off).

Every chunk read from one end is written to the other ``delay_s`` later, give or take a uniform ``jitter_s``, never
before the chunk read ahead of it (the byte stream keeps its order, as TCP's does). Each direction holds at most
``max_buffer_bytes`` (default 1 MiB); while it is full the relay stops reading that end, so the sender is slowed by
TCP's own window instead of the relay's memory growing. Connection setup is not delayed (the relay accepts and
connects at once), only the bytes; a reset or an end on one side is passed on.

Transparent use in a network namespace (``NetnsPair.delay_through``): nftables redirects every tcp connection that
enters the arm's namespace over the veth link, and every one its processes open across it, to the relay's port; the
relay reads each connection's original destination (``SO_ORIGINAL_DST``) and connects there itself, its own outgoing
connections marked (``SO_MARK``) so that they are not redirected again. So each byte that crosses the link passes
the relay once, whichever side opened the connection::

    python -m rig.delayrelay --port 7100 --delay 0.2 --jitter 0.02 --mark 1   # until SIGTERM

It prints ``ready`` once listening, and on SIGTERM the chunk counts and the largest delay it applied as JSON. With
``--control`` it reads lines ``delay SECONDS JITTER`` on stdin and holds every chunk read from then on that long
(what it holds already goes out when due, and the chunks behind it no earlier), printing ``{"ev": "delay", ...}``
when set: a delay that goes away, or comes, on a link that stays up.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import random
import signal
import socket
import struct
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass

__all__ = ["DelayRelay", "RelayStats", "original_destination"]

SO_ORIGINAL_DST = 80  # linux/netfilter_ipv4.h
CHUNK_BYTES = 65536


@dataclass
class RelayStats:
    """What a relay did, over all its connections."""

    connections: int = 0
    chunks: int = 0
    bytes: int = 0
    max_delay_s: float = 0.0
    min_delay_s: float = float("inf")
    backpressure_waits: int = 0


def original_destination(sock: socket.socket) -> tuple[str, int]:
    """Where a connection that nftables redirected to us was going (``SO_ORIGINAL_DST``, IPv4)."""
    raw = sock.getsockopt(socket.SOL_IP, SO_ORIGINAL_DST, 16)
    port, addr = struct.unpack_from("!2xH4s", raw)
    return socket.inet_ntoa(addr), int(port)


class _Budget:
    """Bytes a direction may hold; ``acquire`` waits while it is spent (a chunk larger than the whole budget waits
    for an empty buffer)."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.held = 0
        self._freed = asyncio.Condition()

    async def acquire(self, n: int, stats: RelayStats) -> None:
        async with self._freed:
            if self.held and self.held + n > self.limit:
                stats.backpressure_waits += 1
                await self._freed.wait_for(lambda: not self.held or self.held + n <= self.limit)
            self.held += n

    async def release(self, n: int) -> None:
        async with self._freed:
            self.held -= n
            self._freed.notify_all()


class DelayRelay:
    """The relay (see the module docstring).

    Args:
        delay_s: how long each chunk is held, on average.
        jitter_s: each chunk's delay is ``delay_s`` plus a uniform draw from ``[-jitter_s, jitter_s]`` (at least 0,
            and never earlier than the chunk before it).
        target: where to connect; None: each connection's original destination (a redirect by nftables).
        mark: ``SO_MARK`` of the relay's outgoing connections (so nftables can leave them alone), or None.
        max_buffer_bytes: what each direction of a connection may hold.
        seed: of the jitter's random draws.
    """

    def __init__(
        self,
        delay_s: float,
        jitter_s: float = 0.0,
        *,
        target: tuple[str, int] | None = None,
        mark: int | None = None,
        max_buffer_bytes: int = 1 << 20,
        seed: int = 0,
    ) -> None:
        if delay_s < 0 or jitter_s < 0 or max_buffer_bytes < 1:
            raise ValueError(
                f"DelayRelay: expected delay_s >= 0, jitter_s >= 0 and max_buffer_bytes >= 1, got {delay_s}, "
                f"{jitter_s}, {max_buffer_bytes}"
            )
        self.delay_s = delay_s
        self.jitter_s = jitter_s
        self.target = target
        self.mark = mark
        self.max_buffer_bytes = max_buffer_bytes
        self.stats = RelayStats()
        self._rng = random.Random(seed)

    async def serve(self, host: str, port: int, ready: asyncio.Event | None = None) -> None:
        """Relay every connection to ``host:port`` until cancelled."""
        async with asyncio.TaskGroup() as tg:

            def on_connect(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
                tg.create_task(self._relay(reader, writer))

            server = await asyncio.start_server(on_connect, host, port)
            try:
                if ready is not None:
                    ready.set()
                await asyncio.Event().wait()
            finally:
                server.close()

    async def _connect(self, dest: tuple[str, int]) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            if self.mark is not None:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_MARK, self.mark)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.setblocking(False)
            async with asyncio.timeout(10):
                await asyncio.get_running_loop().sock_connect(sock, dest)
        except BaseException:
            sock.close()
            raise
        return await asyncio.open_connection(sock=sock, limit=CHUNK_BYTES)

    async def _relay(self, a_reader: asyncio.StreamReader, a_writer: asyncio.StreamWriter) -> None:
        self.stats.connections += 1
        b_writer: asyncio.StreamWriter | None = None
        clean = False
        try:
            sock = a_writer.get_extra_info("socket")
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            dest = self.target or original_destination(sock)
            b_reader, b_writer = await self._connect(dest)
            async with asyncio.TaskGroup() as tg:
                tg.create_task(self._pump(a_reader, b_writer))
                tg.create_task(self._pump(b_reader, a_writer))
            clean = True
        except* (OSError, TimeoutError):
            pass  # a reset or a refusal on one side: both are closed below, with a reset
        except* Exception as group:  # a bug of the relay: told, and only this connection ends
            for exc in group.exceptions:
                print(f"delayrelay: connection failed: {exc!r}", file=sys.stderr, flush=True)
        finally:
            for w in (a_writer, b_writer):
                if w is not None:
                    if clean:
                        w.close()
                    else:
                        w.transport.abort()

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        queue: asyncio.Queue[tuple[int, bytes]] = asyncio.Queue()
        budget = _Budget(self.max_buffer_bytes)

        async def read_side() -> None:
            last_due = 0
            while chunk := await reader.read(CHUNK_BYTES):
                await budget.acquire(len(chunk), self.stats)
                now = time.monotonic_ns()
                jitter = self._rng.uniform(-self.jitter_s, self.jitter_s) if self.jitter_s else 0.0
                due = max(last_due, now + round(max(self.delay_s + jitter, 0.0) * 1e9))
                last_due = due
                queue.put_nowait((due, chunk))
            queue.put_nowait((0, b""))  # the end, after everything read before it

        async def write_side() -> None:
            while True:
                due, chunk = await queue.get()
                if not chunk:
                    if writer.can_write_eof():
                        writer.write_eof()
                    return
                wait_ns = due - time.monotonic_ns()
                if wait_ns > 0:
                    await asyncio.sleep(wait_ns / 1e9)
                writer.write(chunk)
                await writer.drain()
                await budget.release(len(chunk))
                held_s = self.delay_s + (time.monotonic_ns() - due) / 1e9 if wait_ns > 0 else None
                st = self.stats
                st.chunks += 1
                st.bytes += len(chunk)
                if held_s is not None:
                    st.max_delay_s = max(st.max_delay_s, held_s)
                    st.min_delay_s = min(st.min_delay_s, held_s)

        async with asyncio.TaskGroup() as tg:
            tg.create_task(read_side())
            tg.create_task(write_side())


def _read_control(relay: DelayRelay) -> None:
    """Set the relay's delay from ``delay SECONDS JITTER`` lines on stdin (a thread: two floats the relay reads per
    chunk); a malformed line is reported and ignored."""
    for line in sys.stdin:
        try:
            word, delay, jitter = line.split()
            if word != "delay" or float(delay) < 0 or float(jitter) < 0:
                raise ValueError(line)
        except ValueError:
            print(f"delayrelay: expected 'delay SECONDS JITTER' (both >= 0), got {line.strip()!r}", file=sys.stderr)
            continue
        relay.delay_s, relay.jitter_s = float(delay), float(jitter)
        print(json.dumps({"ev": "delay", "t_ns": time.monotonic_ns(), "delay_s": relay.delay_s}), flush=True)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m rig.delayrelay``: see the module docstring."""
    parser = argparse.ArgumentParser(prog="python -m rig.delayrelay")
    parser.add_argument("--host", default="0.0.0.0", help="listen address (default %(default)s)")  # noqa: S104
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--delay", type=float, required=True, help="seconds each chunk is held")
    parser.add_argument("--jitter", type=float, default=0.0, help="+- this, uniform (seconds)")
    parser.add_argument("--target", default=None, help="HOST:PORT; default: each connection's original destination")
    parser.add_argument("--mark", type=int, default=None, help="SO_MARK of the relay's own outgoing connections")
    parser.add_argument("--max-buffer", type=int, default=1 << 20, help="bytes held per direction")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--control", action="store_true", help="read 'delay SECONDS JITTER' lines on stdin")
    args = parser.parse_args(argv)
    target = None
    if args.target:
        host, _, port = args.target.rpartition(":")
        target = (host, int(port))
    relay = DelayRelay(
        args.delay, args.jitter, target=target, mark=args.mark, max_buffer_bytes=args.max_buffer, seed=args.seed
    )

    if args.control:
        threading.Thread(target=_read_control, args=(relay,), daemon=True).start()

    async def run() -> None:
        ready = asyncio.Event()
        task = asyncio.create_task(relay.serve(args.host, args.port, ready))
        asyncio.get_running_loop().add_signal_handler(signal.SIGTERM, task.cancel)
        await ready.wait()
        print("ready", flush=True)
        with contextlib.suppress(asyncio.CancelledError):
            await task

    asyncio.run(run())
    stats = asdict(relay.stats)
    if stats["min_delay_s"] == float("inf"):
        stats["min_delay_s"] = None
    print(json.dumps({"ev": "relay_stats", **stats}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
