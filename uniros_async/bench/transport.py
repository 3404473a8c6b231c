"""``uniros bench transport``: round-trip latency and one-way throughput of every transport and installed peer.

In one run, for each payload (277-byte joint state, 64 KiB blob, 640x480x3 uint8 image) and each
implementation (our memory, shm and tcp transports; multiprocessing.Pipe, pyzmq ipc and tcp, zenoh when
installed), a client in this process ping-pongs frames with an echo server in another process (memory:
in-process, by definition) and records every round trip; then it streams frames one way and times until the
server acknowledges the last one. Latencies are reported as percentiles, never means.

Where this process may use two cores or more, every row's client runs on one core and its echo on another
(``_cores``): a round trip between two processes then measures the transport, not where the scheduler happened to
put the two (on one core each hand-off is a context switch, and the same transport's p50 is several times higher).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import multiprocessing as mp
import os
import shutil
import socket
import struct
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from uniros_async.bench import _peers
from uniros_async.bench.common import progress_counter, report
from uniros_async.errors import ConfigError
from uniros_async.stats import summary

__all__ = ["ALL", "PAYLOADS", "TransportBenchConfig", "format_table", "main"]

logger = logging.getLogger(__name__)

PAYLOADS: dict[str, int] = {"small": 277, "64k": 64 * 1024, "image": 640 * 480 * 3, "hd": 1280 * 720 * 3}
OURS = ("memory", "shm", "shm-loan", "tcp", "tls")
"""shm-loan: the shm transport with both ends writing each frame in place (``ShmTransport.loan``) instead of
copying it in: a producer that renders into the loan (a camera, a renderer) pays no send copy. The client writes an
8-byte sequence stamp into each loaned frame; the echo server answers with a loaned frame of the same size that
carries the stamp back (the client checks it), and writes nothing else: the method of iceoryx2's publish-subscribe
benchmark, which loans and sends without writing the payload. So this row is the transport's own cost for a frame
of that size (ring space, wake-ups, views), with no payload copy; the ``shm`` row copies the payload in on both
sides (``send``).

tls: the tcp transport inside mutual TLS (``tls://``), with throw-away certificates written for the run
(``uniros_async.testing.tls``, ``openssl`` needed); its row beside tcp's is the price of encryption."""
PEERS = ("mp-pipe", "zmq-ipc", "zmq-tcp", "zenoh", "iceoryx2", "iceoryx2-loan", "rclpy")
"""iceoryx2: its Python binding's publish-subscribe over shared memory, an echo answering on a second service; the
reader polls for samples (as iceoryx2's own benchmark does). ``iceoryx2`` copies the payload into each loaned
sample on both sides (as ``shm`` copies it); ``iceoryx2-loan`` writes only an 8-byte stamp, as ``shm-loan``.
rclpy: ``sensor_msgs/Image`` through an rclpy echo, both in the rclpy venv (``_rclpy_frames``)."""
COPYING_PEERS = ("mp-pipe", "zmq-ipc", "zmq-tcp", "zenoh", "iceoryx2", "rclpy")
NETWORK_PEERS = ("zmq-tcp", "zenoh")
FLOOR = ("memcpy", "copy-pingpong")
"""memcpy: one copy of the payload into a buffer of its size (numpy ``copyto``), timed as a round trip is: the
floor a copying transport is measured against. copy-pingpong: the payload copied there and back between two
processes, one copy each way into a shared buffer and nothing else: the least a copying round trip between
processes costs here, each copy meeting lines the other core holds. Both in ``_copy_floor``."""
ALL = FLOOR + OURS + PEERS


@dataclasses.dataclass(frozen=True, kw_only=True)
class TransportBenchConfig:
    """What to run. ``quick`` shrinks the sample counts so the whole run takes under a minute on 2 cores."""

    transports: tuple[str, ...] = ALL
    payloads: tuple[str, ...] = tuple(PAYLOADS)
    quick: bool = False
    rtt_samples: int = 0  # 0: by payload and quick
    throughput_frames: int = 0
    json_path: str | None = None
    progress: bool = True

    def __post_init__(self) -> None:
        bad = [t for t in self.transports if t not in FLOOR + OURS + PEERS]
        if bad:
            raise ConfigError(f"unknown transport(s) {bad}; choose from {list(FLOOR + OURS + PEERS)}")
        badp = [p for p in self.payloads if p not in PAYLOADS]
        if badp:
            raise ConfigError(f"unknown payload(s) {badp}; choose from {list(PAYLOADS)}")

    def n_rtt(self, payload: str) -> int:
        if self.rtt_samples:
            return self.rtt_samples
        base = {"small": 5000, "64k": 2000, "image": 500, "hd": 300}[payload]
        return base // 5 if self.quick else base

    def n_tput(self, payload: str) -> int:
        if self.throughput_frames:
            return self.throughput_frames
        base = {"small": 50000, "64k": 5000, "image": 2000, "hd": 1000}[payload]
        return base // 10 if self.quick else base


# ------------------------------------------------------------------------------------------------- clients


class _Client:
    name = ""

    def rtt(self, payload: bytes, n: int) -> list[float]:
        raise NotImplementedError

    def throughput(self, payload: bytes, n: int) -> float:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


def _count_frame(n: int) -> bytes:
    return _peers.COUNT + struct.pack("<Q", n)


class _UnirosClient(_Client):
    """Our transports, driven from an asyncio loop in this process."""

    def __init__(self, kind: str) -> None:
        self.name = kind
        self._loan = kind == "shm-loan"
        self._runner = asyncio.Runner()
        self._proc: Any = None
        self._echo_task: Any = None
        self._t: Any = None
        self._tmp: str | None = None
        self._runner.run(self._open(kind))

    async def _open(self, kind: str) -> None:
        from uniros_async.transports.base import TransportOptions, connect, listen

        opts = TransportOptions()
        if kind == "memory":
            lst = await listen("memory://", opts)
            acc = asyncio.ensure_future(lst.accept())
            self._t = await connect(lst.uri, opts)
            server = await acc
            await lst.aclose()
            self._echo_task = asyncio.ensure_future(self._memory_echo(server))
            return
        uri = {"shm": "shm://", "shm-loan": "shm://", "tcp": "tcp://127.0.0.1:0", "tls": "tls://127.0.0.1:0"}[kind]
        if kind == "tls":
            from uniros_async.testing.tls import write_test_certs

            self._tmp = tempfile.mkdtemp(prefix="uniros-bench-tls-")
            os.environ.update(write_test_certs(self._tmp).environ())  # the spawned echo server reads them too
        ctx = mp.get_context("spawn")
        parent, child = ctx.Pipe()
        self._proc = ctx.Process(target=_peers.serve_uniros, args=(uri, child, self._loan), daemon=True)
        self._proc.start()
        child.close()
        if not parent.poll(30):
            raise TimeoutError(f"{kind} echo server did not start")
        self._t = await connect(parent.recv(), opts)
        parent.close()

    @staticmethod
    async def _memory_echo(t: Any) -> None:
        from uniros_async.errors import TransportError

        try:
            while True:
                f = await t.receive()
                if f.nbytes == 13 and bytes(f[:5]) == _peers.COUNT:
                    (n,) = struct.unpack("<Q", f[5:13])
                    for _ in range(n):
                        await t.receive()
                    await t.send(b"ACK")
                    continue
                await t.send(f)
        except TransportError:
            await t.aclose()

    def rtt(self, payload: bytes, n: int) -> list[float]:
        async def run() -> list[float]:
            t = self._t
            out = []
            clock = time.perf_counter_ns
            async with asyncio.timeout(120):
                if self._loan:
                    size, stamp_of = len(payload), struct.Struct("<Q").pack
                    for i in range(n):
                        stamp = stamp_of(i)
                        t0 = clock()
                        async with t.loan(size) as buf:
                            buf[:8] = stamp
                        reply = await t.receive()
                        out.append((clock() - t0) / 1e3)
                        if reply.nbytes != size or reply[:8] != stamp:
                            raise RuntimeError(f"shm-loan echo answered frame {i} with the wrong frame")
                    return out
                for _ in range(n):
                    t0 = clock()
                    await t.send(payload)
                    await t.receive()
                    out.append((clock() - t0) / 1e3)
            return out

        return self._runner.run(run())

    def throughput(self, payload: bytes, n: int) -> float:
        async def run() -> float:
            t = self._t
            async with asyncio.timeout(300):
                t0 = time.perf_counter()
                await t.send(_count_frame(n))
                size, stamp = len(payload), payload[:8]
                for _ in range(n):
                    if self._loan:
                        async with t.loan(size) as buf:
                            buf[: len(stamp)] = stamp
                    else:
                        await t.send(payload)
                ack = await t.receive()
                assert bytes(ack) == b"ACK"
                return n / (time.perf_counter() - t0)

        return self._runner.run(run())

    def close(self) -> None:
        async def run() -> None:
            if self._proc is not None:
                await self._t.send(_peers.STOP)
            await self._t.aclose()
            if self._echo_task is not None:
                self._echo_task.cancel()

        try:
            self._runner.run(run())
        finally:
            self._runner.close()
            if self._proc is not None:
                self._proc.join(10)
                if self._proc.is_alive():
                    self._proc.kill()
            if self._tmp is not None:
                shutil.rmtree(self._tmp, ignore_errors=True)
                for var in ("UNIROS_TLS_CERT", "UNIROS_TLS_KEY", "UNIROS_TLS_CA"):
                    os.environ.pop(var, None)


class _PipeClient(_Client):
    name = "mp-pipe"

    def __init__(self) -> None:
        ctx = mp.get_context("spawn")
        self._conn, child_conn = ctx.Pipe()
        ready_parent, ready_child = ctx.Pipe()
        self._proc = ctx.Process(target=_peers.serve_pipe, args=("", ready_child, child_conn), daemon=True)
        self._proc.start()
        child_conn.close()
        if not ready_parent.poll(30):
            raise TimeoutError("pipe echo server did not start")
        ready_parent.recv()

    def rtt(self, payload: bytes, n: int) -> list[float]:
        c, clock, out = self._conn, time.perf_counter_ns, []
        for _ in range(n):
            t0 = clock()
            c.send_bytes(payload)
            c.recv_bytes()
            out.append((clock() - t0) / 1e3)
        return out

    def throughput(self, payload: bytes, n: int) -> float:
        c = self._conn
        t0 = time.perf_counter()
        c.send_bytes(_count_frame(n))
        for _ in range(n):
            c.send_bytes(payload)
        c.recv_bytes()
        return n / (time.perf_counter() - t0)

    def close(self) -> None:
        self._conn.send_bytes(_peers.STOP)
        self._conn.close()
        self._proc.join(10)


class _ZmqClient(_Client):
    def __init__(self, kind: str) -> None:
        import zmq

        self.name = kind
        ctx = mp.get_context("spawn")
        ready_parent, ready_child = ctx.Pipe()
        addr = f"ipc:///tmp/uniros-bench-{os.getpid()}.ipc" if kind == "zmq-ipc" else "tcp://127.0.0.1:0"
        self._ipc = addr if kind == "zmq-ipc" else None
        self._proc = ctx.Process(target=_peers.serve_zmq, args=(addr, ready_child), daemon=True)
        self._proc.start()
        if not ready_parent.poll(30):
            raise TimeoutError("zmq echo server did not start")
        addr = ready_parent.recv()
        self._ctx = zmq.Context()
        self._s = self._ctx.socket(zmq.PAIR)
        self._s.connect(addr)

    def rtt(self, payload: bytes, n: int) -> list[float]:
        s: Any = self._s  # pyzmq's send overloads want a literal copy=, and ours depends on the size
        clock, out = time.perf_counter_ns, []
        big = len(payload) > 16384
        for _ in range(n):
            t0 = clock()
            s.send(payload, copy=not big)
            s.recv(copy=not big)
            out.append((clock() - t0) / 1e3)
        return out

    def throughput(self, payload: bytes, n: int) -> float:
        s: Any = self._s  # as in rtt()
        big = len(payload) > 16384
        t0 = time.perf_counter()
        s.send(_count_frame(n))
        for _ in range(n):
            s.send(payload, copy=not big)
        s.recv()
        return n / (time.perf_counter() - t0)

    def close(self) -> None:
        self._s.send(_peers.STOP)
        self._proc.join(10)
        self._s.close(linger=0)
        self._ctx.term()
        if self._ipc:
            Path(self._ipc.removeprefix("ipc://")).unlink(missing_ok=True)


class _ZenohClient(_Client):
    name = "zenoh"

    def __init__(self) -> None:
        import zenoh

        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        ctx = mp.get_context("spawn")
        ready_parent, ready_child = ctx.Pipe()
        self._proc = ctx.Process(target=_peers.serve_zenoh, args=(f"tcp:127.0.0.1:{port}", ready_child), daemon=True)
        self._proc.start()
        if not ready_parent.poll(30):
            raise TimeoutError("zenoh echo server did not start")
        ready_parent.recv()
        self._session = zenoh.open(_peers.zenoh_config(port, listen=False))
        self._pub = self._session.declare_publisher("bench/ping", congestion_control=zenoh.CongestionControl.BLOCK)
        self._sub = self._session.declare_subscriber("bench/pong")
        # wait until the route exists both ways
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            self._pub.put(b"hello")
            if self._sub.try_recv() is not None:
                break
            time.sleep(0.05)
        else:
            raise TimeoutError("zenoh peers did not connect within 10 s")
        time.sleep(0.1)
        while self._sub.try_recv() is not None:
            pass

    def rtt(self, payload: bytes, n: int) -> list[float]:
        pub, sub, clock, out = self._pub, self._sub, time.perf_counter_ns, []
        for _ in range(n):
            t0 = clock()
            pub.put(payload)
            sub.recv()
            out.append((clock() - t0) / 1e3)
        return out

    def throughput(self, payload: bytes, n: int) -> float:
        t0 = time.perf_counter()
        self._pub.put(_count_frame(n))
        for _ in range(n):
            self._pub.put(payload)
        self._sub.recv()
        return n / (time.perf_counter() - t0)

    def close(self) -> None:
        self._pub.put(_peers.STOP)
        self._proc.join(10)
        if self._proc.is_alive():
            self._proc.kill()
        self._sub.undeclare()  # type: ignore[no-untyped-call]  # zenoh ships no annotations here
        self._pub.undeclare()  # type: ignore[no-untyped-call]
        self._session.close()  # type: ignore[no-untyped-call]


class _Iceoryx2Client(_Client):
    """iceoryx2's Python binding: loaned samples to an echo in another process (``_peers.serve_iceoryx2``)."""

    def __init__(self, kind: str) -> None:
        import iceoryx2 as iox2

        self.name = kind
        self._copy = kind == "iceoryx2"
        iox2.set_log_level_from_env_or(iox2.LogLevel.Warn)
        name = f"uniros_bench_{os.getpid()}_{kind}"
        max_len = max(PAYLOADS.values())
        ctx = mp.get_context("spawn")
        ready_parent, ready_child = ctx.Pipe()
        self._proc = ctx.Process(
            target=_peers.serve_iceoryx2, args=(name, ready_child, self._copy, max_len), daemon=True
        )
        self._proc.start()
        if not ready_parent.poll(30):
            self._proc.kill()
            raise TimeoutError("iceoryx2 echo server did not start")
        ready_parent.recv()
        self._node = iox2.NodeBuilder.new().create(iox2.ServiceType.Ipc)
        self._pub, self._sub = _peers.iceoryx2_ports(self._node, name, max_len, send="ping", receive="pong")
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:  # until the echo's publisher sees our subscriber
            self._send(b"hello")
            time.sleep(0.05)
            if self._sub.receive() is not None:
                break
        else:
            raise TimeoutError("iceoryx2 peers did not connect within 10 s")
        time.sleep(0.1)
        while self._sub.receive() is not None:
            pass

    def _send(self, payload: bytes, stamp: bytes = b"") -> None:
        import numpy as np

        sample = self._pub.loan_slice_uninit(len(payload))
        dst = _peers.iceoryx2_bytes(sample)
        if stamp:
            dst[: len(stamp)] = np.frombuffer(stamp, np.uint8)
        else:
            dst[:] = np.frombuffer(payload, np.uint8)
        del dst
        sample.assume_init().send()

    def rtt(self, payload: bytes, n: int) -> list[float]:
        clock, out, stamp_of = time.perf_counter_ns, [], struct.Struct("<Q").pack
        size = len(payload)
        for i in range(n):
            stamp = stamp_of(i) if not self._copy else b""
            t0 = clock()
            self._send(payload, stamp)
            reply = _peers.iceoryx2_receive(self._sub)
            out.append((clock() - t0) / 1e3)
            got = _peers.iceoryx2_bytes(reply)
            if got.nbytes != size or (stamp and got[:8].tobytes() != stamp):
                raise RuntimeError(f"{self.name} echo answered frame {i} with the wrong frame")
            del got, reply
        return out

    def throughput(self, payload: bytes, n: int) -> float:
        t0 = time.perf_counter()
        self._send(_count_frame(n))
        stamp = b"" if self._copy else payload[:8]
        for _ in range(n):
            self._send(payload, stamp)
        ack = _peers.iceoryx2_receive(self._sub)
        assert _peers.iceoryx2_bytes(ack).tobytes() == b"ACK"
        del ack
        return n / (time.perf_counter() - t0)

    def close(self) -> None:
        self._send(_peers.STOP)
        self._proc.join(10)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(5)
        del self._pub, self._sub, self._node


def _make_client(kind: str) -> _Client:
    if kind == "memcpy":
        from uniros_async.bench._copy_floor import MemcpyFloor

        return MemcpyFloor()  # type: ignore[return-value]  # the same methods, outside _Client
    if kind == "copy-pingpong":
        from uniros_async.bench._copy_floor import CopyPingPong

        return CopyPingPong(max(PAYLOADS.values()))  # type: ignore[return-value]
    if kind in ("iceoryx2", "iceoryx2-loan"):
        return _Iceoryx2Client(kind)
    if kind == "rclpy":
        from uniros_async.bench._rclpy_frames import RclpyImageClient

        return RclpyImageClient()  # type: ignore[return-value]  # the same methods, outside _Client
    if kind in OURS:
        return _UnirosClient(kind)
    if kind == "mp-pipe":
        return _PipeClient()
    if kind in ("zmq-ipc", "zmq-tcp"):
        return _ZmqClient(kind)
    if kind == "zenoh":
        return _ZenohClient()
    raise ConfigError(f"unknown transport {kind!r}")


def _available(kind: str) -> str | None:
    """None if ``kind`` can run here, else why not."""
    if kind == "rclpy":
        from uniros_async.bench._rclpy_frames import rclpy_missing

        return rclpy_missing()
    mod = {
        "zmq-ipc": "zmq",
        "zmq-tcp": "zmq",
        "zenoh": "zenoh",
        "iceoryx2": "iceoryx2",
        "iceoryx2-loan": "iceoryx2",
    }.get(kind)
    if mod is None:
        return None
    try:
        __import__(mod)
    except ImportError:
        return f"{mod} is not installed (pip install 'uniros-async[bench]')"
    return None


# ------------------------------------------------------------------------------------------------- driver


def main(config: TransportBenchConfig, *, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Run the benchmark; print the table; write JSON when asked. Returns the records."""
    records: list[dict[str, Any]] = []
    skipped: list[str] = []
    todo = [(k, p) for k in config.transports for p in config.payloads]
    bar = progress_counter(len(todo), config.progress, "transport bench", "case")
    client_cpus, echo_cpus = _cores()
    with _on_cores(client_cpus):
        _run(config, records, skipped, bar, echo_cpus)
    bar(0, done=True)
    table = format_table(records) + "".join(f"\nskipped {s}" for s in skipped)
    report(table, records, config.json_path, log)
    return records


def _cores() -> tuple[set[int] | None, set[int] | None]:
    """The client's core and the echoes' core: two of the cores this process may use, or (None, None) with one."""
    from uniros_async.runtime.cores import usable_cpus

    cpus = usable_cpus()
    return ({cpus[0]}, {cpus[1]}) if len(cpus) >= 2 and hasattr(os, "sched_setaffinity") else (None, None)


@contextlib.contextmanager
def _on_cores(cpus: set[int] | None) -> Iterator[None]:
    """This thread on ``cpus`` for the block (None: unchanged), then back on the cores it had."""
    if cpus is None:
        yield
        return
    before = os.sched_getaffinity(0)
    os.sched_setaffinity(0, cpus)
    try:
        yield
    finally:
        os.sched_setaffinity(0, before)


def _run(
    config: TransportBenchConfig,
    records: list[dict[str, Any]],
    skipped: list[str],
    bar: Callable[..., None],
    echo_cpus: set[int] | None,
) -> None:
    """Every case of ``config``: its record appended to ``records``, or why not to ``skipped``."""
    for kind in config.transports:
        why = _available(kind)
        if why is not None:
            skipped.append(f"{kind}: {why}")
            bar(len(config.payloads))
            continue
        try:
            with _on_cores(echo_cpus):  # the echo processes it starts inherit these cores
                client = _make_client(kind)
        except Exception as exc:  # noqa: BLE001 - a peer that cannot start is reported, the others still run
            skipped.append(f"{kind}: could not start: {exc}")
            bar(len(config.payloads))
            continue
        try:
            for pname in config.payloads:
                payload = os.urandom(PAYLOADS[pname])
                n = config.n_rtt(pname)
                try:
                    client.rtt(payload, max(10, n // 10))  # warm-up, discarded
                    rtts = client.rtt(payload, n)
                    tput = client.throughput(payload, config.n_tput(pname))
                except Exception as exc:  # noqa: BLE001 - a peer failing one case is reported; the run goes on
                    skipped.append(f"{kind} {pname}: failed: {exc}")
                    bar(1)
                    continue
                s = summary(rtts)
                records.append(
                    {
                        "transport": kind,
                        "payload": pname,
                        "rtt_p50_us": round(s["p50"], 2),
                        "rtt_p90_us": round(s["p90"], 2),
                        "rtt_p99_us": round(s["p99"], 2),
                        "throughput_msg_s": round(tput, 1),
                    }
                )
                bar(1)
        finally:
            client.close()


def format_table(records: list[dict[str, Any]]) -> str:
    """A fixed-width table, one row per (payload, transport), ours and peers side by side per payload."""
    head = f"{'payload':<8} {'transport':<13} {'rtt p50 us':>11} {'p90 us':>9} {'p99 us':>9} {'msgs/s one way':>15}"
    lines = [head, "-" * len(head)]
    for pname in PAYLOADS:
        rows = [r for r in records if r["payload"] == pname]
        for r in rows:
            lines.append(
                f"{pname:<8} {r['transport']:<13} {r['rtt_p50_us']:>11.1f} {r['rtt_p90_us']:>9.1f} "
                f"{r['rtt_p99_us']:>9.1f} {r['throughput_msg_s']:>15,.0f}"
            )
        if rows:
            # shm competes with every same-machine peer; tcp with the peers that cross a network
            for ours, peers in (("shm", COPYING_PEERS), ("shm-loan", PEERS), ("tcp", NETWORK_PEERS)):
                mine = next((r for r in rows if r["transport"] == ours), None)
                best = min((r for r in rows if r["transport"] in peers), key=lambda r: r["rtt_p50_us"], default=None)
                if mine and best:
                    ratio = best["rtt_p50_us"] / mine["rtt_p50_us"]
                    verdict = f"{ratio:.2f}x lower" if ratio >= 1 else f"{1 / ratio:.2f}x HIGHER"
                    kind = "network peer" if ours == "tcp" else "peer"
                    lines.append(f"{'':<8} {ours} p50 vs fastest {kind} ({best['transport']}): {verdict}")
            floor = next((r for r in rows if r["transport"] == "memcpy"), None)
            for ours in ("shm", "shm-loan"):
                mine = next((r for r in rows if r["transport"] == ours), None)
                if floor and mine:
                    x = mine["rtt_p50_us"] / floor["rtt_p50_us"]
                    lines.append(f"{'':<8} {ours} p50 vs one memcpy of the payload: {x:.2f}x")
            two = next((r for r in rows if r["transport"] == "copy-pingpong"), None)
            mine = next((r for r in rows if r["transport"] == "shm"), None)
            if two and mine:
                x = mine["rtt_p50_us"] / two["rtt_p50_us"]
                lines.append(f"{'':<8} shm p50 vs two copies between processes and nothing else: {x:.2f}x")
            tcp_row = next((r for r in rows if r["transport"] == "tcp"), None)
            tls_row = next((r for r in rows if r["transport"] == "tls"), None)
            if tcp_row and tls_row:
                extra = tls_row["rtt_p50_us"] - tcp_row["rtt_p50_us"]
                lines.append(
                    f"{'':<8} tls p50 vs tcp: {extra:+.1f} us ({tls_row['rtt_p50_us'] / tcp_row['rtt_p50_us']:.2f}x)"
                )
            lines.append("")
    if any(r["transport"] == "shm-loan" for r in records):
        lines += [
            "shm-loan: both ends write their frames in place (ShmTransport.loan) and only an 8-byte stamp of the",
            "  payload (iceoryx2's method): zero-copy round trips; shm and tcp copy the payload in on both sides",
        ]
    return "\n".join(lines)
