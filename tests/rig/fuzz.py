"""Fuzz every parser of bytes from outside: ``python -m rig.fuzz --parser all --count 100000``.

Each parser gets generated inputs, mutated from valid seeds (bit flips, byte changes, inserted, deleted and repeated
runs, truncations, extreme length fields, splices of two seeds) with some purely random ones, and each input is
classified:

- accepted: parsed without error;
- rejected: refused with the error the parser documents (CodecError, TransportBrokenError, ...);
- crash: any other exception, or an exception an event loop callback raised (the loop's exception handler);
- hang: not finished within ``--time-limit-s`` (SIGALRM for plain functions, a timeout for coroutines).

The parsers, and what each run feeds them:

    tcp-handshake   TcpHandshake.feed (both roles, with and without a key), in random chunks
    tcp-frames      a TcpTransport reading a real socket (socketpair): a peer's HELLO, then frames, then EOF
    shm-handshake   the shm handshake's admit (listener) and join (peer) over a real SOCK_SEQPACKET pair
    codec           bus/codec.py decode (every message type of bus/messages.py) and decode_plain
    worker          the worker protocol's unpack and unpack_step_reply_into (runtime)
    tcpros-header   adapters/ros1/_tcpros.py read_header from a stream (length prefix, then fields)
    xmlrpc          an HTTP request read as the ROS 1 node's XML-RPC server reads it, then dispatched
    ros1-msgs       adapters/ros1/msgs.py deserialize of every ROS 1 message type
    dxl             hardware/dxl/protocol.py's PacketParser on a stream in random chunks, and fast sync read answers

The command prints a table of counts per parser and exits 1 if any crash or hang was found (listing the first
inputs of each). ``run(parser, count, seed)`` is the same from Python (the test suite runs a small sample).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import os
import random
import signal
import socket
import struct
import sys
import time
import traceback
from collections.abc import Awaitable, Callable, Sequence
from typing import Any

import numpy as np

__all__ = ["PARSERS", "FuzzCounts", "format_table", "main", "run"]

_MAX_EXAMPLES = 3


@dataclasses.dataclass
class FuzzCounts:
    """What one parser made of its inputs."""

    parser: str
    inputs: int = 0
    accepted: int = 0
    rejected: int = 0
    crashes: int = 0
    hangs: int = 0
    seconds: float = 0.0
    examples: list[tuple[str, bytes, str]] = dataclasses.field(default_factory=list)
    """(kind, input, traceback or reason) of the first crashes and hangs."""

    def note(self, kind: str, data: bytes, detail: str) -> None:
        if len(self.examples) < _MAX_EXAMPLES:
            self.examples.append((kind, data, detail))


class _Hang(BaseException):
    """Raised by the SIGALRM handler into a plain parser that overran its time limit."""


# ------------------------------------------------------------------------------------------- mutation


_INTERESTING_U32 = (0, 1, 3, 4, 7, 8, 0x7F, 0x80, 0xFF, 0x3FFF, 0x4000, 0xFFFF, 0x10000, 2**31 - 1, 2**31, 2**32 - 1)


def mutate(rng: random.Random, seeds: Sequence[bytes]) -> bytes:
    """One input: a seed changed by 1-4 mutations, a splice of two seeds, or (1 in 20) random bytes."""
    if rng.random() < 0.05:
        return rng.randbytes(rng.randrange(0, 256))
    data = bytearray(rng.choice(seeds))
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(9)
        n = len(data)
        if op == 0 and n:  # flip a bit
            i = rng.randrange(n)
            data[i] ^= 1 << rng.randrange(8)
        elif op == 1 and n:  # set a byte
            data[rng.randrange(n)] = rng.choice((0, 0xFF, 0x7F, 0x80, rng.randrange(256)))
        elif op == 2:  # insert bytes
            i = rng.randrange(n + 1)
            data[i:i] = rng.randbytes(rng.randint(1, 16))
        elif op == 3 and n:  # delete a run
            i = rng.randrange(n)
            del data[i : i + rng.randint(1, 16)]
        elif op == 4 and n:  # truncate
            del data[rng.randrange(n) :]
        elif op == 5 and n >= 4:  # an extreme little-endian u32 somewhere (length fields)
            i = rng.randrange(n - 3)
            data[i : i + 4] = struct.pack("<I", rng.choice(_INTERESTING_U32))
        elif op == 6 and n >= 4:  # the same, big-endian (HTTP numbers, msgpack lengths)
            i = rng.randrange(n - 3)
            data[i : i + 4] = struct.pack(">I", rng.choice(_INTERESTING_U32))
        elif op == 7 and n:  # repeat a run
            i = rng.randrange(n)
            data[i:i] = data[i : i + rng.randint(1, 32)] * rng.randint(1, 8)
        elif op == 8:  # splice with another seed
            other = rng.choice(seeds)
            cut = rng.randrange(n + 1)
            data = data[:cut] + other[rng.randrange(len(other) + 1) :]
    return bytes(data)


# ------------------------------------------------------------------------------------------- targets


@dataclasses.dataclass
class _Target:
    seeds: Callable[[], list[bytes]]
    rejects: Callable[[], tuple[type[BaseException], ...]]
    check: Callable[[bytes, random.Random], Any] | None = None
    """A plain function; its return value does not matter."""
    acheck: Callable[[bytes, random.Random], Awaitable[Any]] | None = None
    """A coroutine function, run in one event loop for all inputs."""


def _tcp_handshake_seeds() -> list[bytes]:
    from uniros_async.transports._tcp_handshake import TcpHandshake

    out = []
    for key in (None, b"fuzz-key"):
        a = TcpHandshake(key=key, listener=False, max_frame_bytes=1 << 20, peer="fuzz")
        b = TcpHandshake(key=key, listener=True, max_frame_bytes=1 << 20, peer="fuzz")
        _, reply_b = b.feed(a.hello())
        out.append(a.hello())
        out.append(b.hello() + reply_b)
        _, reply_a = a.feed(b.hello() + reply_b)
        out.append(a.hello() + reply_a + struct.pack("<I", 5) + b"hello")
    return out


def _tcp_handshake_check(data: bytes, rng: random.Random) -> None:
    from uniros_async.transports._tcp_handshake import TcpHandshake

    hs = TcpHandshake(
        key=rng.choice((None, b"fuzz-key")), listener=rng.random() < 0.5, max_frame_bytes=1 << 20, peer="fuzz"
    )
    pos = 0
    while pos < len(data) and not hs.done:
        chunk = data[pos : pos + rng.randint(1, 64)]
        used, _ = hs.feed(memoryview(chunk))
        if used > len(chunk):
            raise AssertionError(f"feed consumed {used} of {len(chunk)} bytes")
        pos += len(chunk) if used == 0 and len(chunk) < 8 else max(used, 1)


def _tcp_rejects() -> tuple[type[BaseException], ...]:
    from uniros_async.errors import AuthenticationError, TransportBrokenError

    return (TransportBrokenError, AuthenticationError)


def _tcp_frames_seeds() -> list[bytes]:
    from uniros_async.bus import codec
    from uniros_async.bus.messages import Header, JointState
    from uniros_async.transports._tcp_handshake import TcpHandshake

    hello = TcpHandshake(key=None, listener=True, max_frame_bytes=1 << 20, peer="fuzz").hello()
    js = b"".join(
        bytes(p)
        for p in codec.encode(
            JointState(
                header=Header(stamp_ns=1),
                name=("a", "b"),
                position=np.zeros(2),
                velocity=np.ones(2),
                effort=np.zeros(2),
            )
        )
    )

    def frames(*payloads: bytes) -> bytes:
        return b"".join(struct.pack("<I", len(p)) + p for p in payloads)

    return [
        hello + frames(js),
        hello + frames(b"", b"x" * 277, js),
        hello + frames(b"y" * 20_000),  # a large frame: the path that reads into a buffer of its own
        hello + frames(*(bytes([i]) * i for i in range(40))),
    ]


async def _tcp_frames_check(data: bytes, rng: random.Random) -> None:
    from uniros_async.errors import TransportBrokenError
    from uniros_async.transports.base import TransportOptions
    from uniros_async.transports.tcp import TcpTransport

    loop = asyncio.get_running_loop()
    ours, theirs = socket.socketpair()
    try:
        theirs.setblocking(False)
        opts = TransportOptions(max_frame_bytes=1 << 20)
        _, proto = await loop.create_connection(lambda: TcpTransport(opts, uri="tcp://fuzz:1"), sock=ours)
        try:
            await loop.sock_sendall(theirs, data)
            theirs.shutdown(socket.SHUT_WR)
            with contextlib.suppress(TransportBrokenError):  # a rejection, or the end of the stream
                await asyncio.shield(proto._ready)
                while True:
                    await proto.receive()
            if proto.stats.rejected or (proto._error is not None and "closed the connection:" not in proto._error[0]):
                raise TransportBrokenError(proto._error[0] if proto._error else "rejected")
        finally:
            await proto.aclose()
    finally:
        theirs.close()


def _shm_seeds() -> list[bytes]:
    from uniros_async.transports import _shm_handshake as hs

    nonce = bytes(range(32))
    hello = hs._HELLO.pack(hs._MAGIC, 0, 0, 1 << 16, nonce)
    proof = hs._PROOF.pack(hs._MAGIC, bytes(32))
    challenge = hs._CHALLENGE.pack(hs._MAGIC, 0, 0, nonce, bytes(32))
    setup = hs._SETUP.pack(hs._MAGIC, 1 << 16)
    # two packets in one input: a u16 length, the first packet, then the second
    return [
        struct.pack("<H", len(hello)) + hello + proof,
        struct.pack("<H", len(challenge)) + challenge + setup,
    ]


async def _shm_check(data: bytes, rng: random.Random) -> None:
    import dataclasses as dc

    from uniros_async.transports import _shm_handshake as hs
    from uniros_async.transports.base import TransportOptions

    n = struct.unpack_from("<H", data)[0] if len(data) >= 2 else 0
    first, second = data[2 : 2 + n], data[2 + n :]
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    ours.setblocking(False)
    opts = dc.replace(TransportOptions(), auth_key=rng.choice((None, b"fuzz-key")), ring_bytes=4096)
    try:
        for packet in (first, second):
            if packet:
                theirs.send(packet)
        theirs.shutdown(socket.SHUT_WR)
        if rng.random() < 0.5:
            setup = await hs.admit(ours, opts)
        else:
            setup = await hs.join(ours, "fuzz", opts)
        setup.mm.close()
        os.close(setup.doorbell_fd)
        os.close(setup.peer_doorbell_fd)
    finally:
        ours.close()
        theirs.close()


def _shm_rejects() -> tuple[type[BaseException], ...]:
    from uniros_async.errors import AuthenticationError, TransportBrokenError
    from uniros_async.transports._shm_handshake import Rejected

    return (Rejected, TransportBrokenError, AuthenticationError, OSError)


def _codec_seeds() -> list[bytes]:
    from uniros_async.bus import codec
    from uniros_async.bus import messages as m

    h = m.Header(stamp_ns=123, seq=4, frame_id="base")
    msgs: list[Any] = [
        h,
        m.JointState(
            header=h, name=("waist", "shoulder"), position=np.arange(2.0), velocity=np.ones(2), effort=np.zeros(2)
        ),
        m.JointCommand(header=h, position=np.zeros(5), velocity=np.ones(5), duration_s=0.1),
        m.Pose(header=h, position=np.zeros(3), orientation=np.array([1.0, 0, 0, 0])),
        m.Marker(header=h, ns="goal", position=np.zeros(3), points=np.zeros((2, 3))),
        m.Image(header=h, data=np.zeros((2, 3, 3), np.uint8)),
        m.Blob(header=h, data=np.arange(10, dtype=np.uint8)),
        m.ClockTick(sim_time_ns=5),
        m.Empty(),
        m.Trigger(success=True, message="ok"),
        m.Text(data="hi"),
        m.Data(value={"a": [1, 2.5, "x", None]}),
    ]
    seeds = [b"".join(bytes(p) for p in codec.encode(msg)) for msg in msgs]
    seeds.append(codec.encode_plain({"op": "subscribe", "topic": "/a", "type": "JointState", "qos": [1, 2]}))
    return seeds


def _codec_check(data: bytes, rng: random.Random) -> None:
    from uniros_async.bus import codec

    if data[:1] in (b"\x80", b"\x81", b"\x82", b"\x83", b"\x84", b"\x85") and rng.random() < 0.5:
        codec.decode_plain(data)
    else:
        codec.decode(data)


def _codec_rejects() -> tuple[type[BaseException], ...]:
    from uniros_async.errors import CodecError

    return (CodecError,)


def _worker_module() -> Any:
    import importlib

    for name in ("uniros_async.runtime.protocol", "uniros_async.runtime.wire", "uniros_async.runtime.worker"):
        with contextlib.suppress(ImportError):
            mod = importlib.import_module(name)
            if hasattr(mod, "unpack") and hasattr(mod, "pack_step_reply"):
                return mod
    raise ImportError("no module of uniros_async.runtime defines the worker protocol's unpack")


def _worker_seeds() -> list[bytes]:
    w = _worker_module()
    obs = np.arange(6, dtype=np.float32)
    return [
        w.pack({"op": "reset", "seed": 3, "options": None}),
        w.pack({"ok": True, "result": [obs, {"is_success": False}]}),
        bytes(w.pack(w.pack_step_request(np.zeros(4, np.float32), "next_step", 12345))),
        bytes(w.pack(w.pack_step_request([0.1, 0.2], None, None))),
        w.pack_step_reply([obs, 1.5, False, True, {"t": 1, "reason": "timeout"}]),
        w.pack_step_reply([{"a": 1}, 0.0, True, False, {}]),
    ]


def _worker_check(data: bytes, rng: random.Random) -> None:
    w = _worker_module()
    if rng.random() < 0.3:
        head = w.array_head(np.dtype(np.float32), (6,))
        out = bytearray(24)
        if w.unpack_step_reply_into(data, memoryview(out), head) is not None:
            return
    w.unpack(data)


def _tcpros_seeds() -> list[bytes]:
    from uniros_async.adapters.ros1 import _tcpros

    fields = {"callerid": "/talker", "topic": "/joint_states", "type": "sensor_msgs/JointState", "md5sum": "*"}
    return [_tcpros.frame(_tcpros.encode_header(fields)), _tcpros.frame(_tcpros.encode_header({"error": "no"}))]


async def _tcpros_check(data: bytes, rng: random.Random) -> None:
    from uniros_async.adapters.ros1 import _tcpros

    reader = asyncio.StreamReader()
    reader.feed_data(data)
    reader.feed_eof()
    await _tcpros.read_header(reader)


def _tcpros_rejects() -> tuple[type[BaseException], ...]:
    from uniros_async.errors import CodecError

    return (CodecError, asyncio.IncompleteReadError)


def _xmlrpc_seeds() -> list[bytes]:
    import xmlrpc.client

    out = []
    for method, params in (
        ("getPid", ("/caller",)),
        ("publisherUpdate", ("/master", "/joint_states", ["http://127.0.0.1:1/"])),
        ("requestTopic", ("/sub", "/joint_states", [["TCPROS"]])),
        ("paramUpdate", ("/m", "/p", {"a": 1.5, "b": [True, "x"]})),
    ):
        body = xmlrpc.client.dumps(params, method).encode()
        out.append(
            b"POST / HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: text/xml\r\n"
            + f"Content-Length: {len(body)}\r\n\r\n".encode()
            + body
        )
    return out


async def _xmlrpc_check(data: bytes, rng: random.Random) -> None:
    from uniros_async.adapters.ros1 import _xmlrpc

    def pid(caller: str) -> list[Any]:
        return [1, "", os.getpid()]

    def any_args(*args: Any) -> list[Any]:
        return [1, "", 0]

    server = _xmlrpc.XmlRpcServer(
        {"getPid": pid, "publisherUpdate": any_args, "requestTopic": any_args, "paramUpdate": any_args},
        spawn=lambda coro: asyncio.ensure_future(coro),
    )
    reader = asyncio.StreamReader()
    reader.feed_data(data)
    reader.feed_eof()
    _, _, body = await _xmlrpc._read_http_message(reader)
    reply = server._dispatch(body)
    if not reply.startswith(b"<?xml"):
        raise AssertionError(f"the server answered with {reply[:40]!r}, not XML-RPC")


def _xmlrpc_rejects() -> tuple[type[BaseException], ...]:
    from uniros_async.adapters.ros1._xmlrpc import XmlRpcCallError

    # what the server's connection handler catches and drops the connection for
    return (XmlRpcCallError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, ValueError)


def _ros1_seeds() -> list[bytes]:
    from uniros_async.adapters.ros1 import msgs

    h = msgs.RosHeader(seq=1, stamp_ns=1_500_000_000, frame_id="base")
    point = msgs.JointTrajectoryPoint(
        positions=np.zeros(2), velocities=np.ones(2), accelerations=np.zeros(0), effort=np.zeros(0),
        time_from_start_ns=100,
    )  # fmt: skip
    samples: list[Any] = [
        h,
        msgs.JointState(
            header=h, name=["waist", "shoulder"], position=np.zeros(2), velocity=np.ones(2), effort=np.zeros(0)
        ),
        msgs.Float64MultiArray(data=np.arange(3.0), dim=[("x", 3, 1)]),
        point,
        msgs.JointTrajectory(header=h, joint_names=["a", "b"], points=[point, point]),
        msgs.JointGroupCommand(name="arm", cmd=np.zeros(5, np.float32)),
    ]
    return [msgs.MESSAGE_TYPES[s._type]._type.encode() + b"\0" + s.serialize() for s in samples]


def _ros1_check(data: bytes, rng: random.Random) -> None:
    from uniros_async.adapters.ros1 import msgs

    name, sep, body = data.partition(b"\0")
    cls = msgs.MESSAGE_TYPES.get(name.decode(errors="replace")) if sep else None
    if cls is None:
        cls = rng.choice(list(msgs.MESSAGE_TYPES.values()))
    cls.deserialize(body)


def _ros1_rejects() -> tuple[type[BaseException], ...]:
    from uniros_async.errors import CodecError

    return (CodecError,)


def _dxl_seeds() -> list[bytes]:
    from uniros_async.hardware.dxl import protocol as p

    return [
        p.encode_status(1, 0, bytes((0x06, 0x04, 0x26))),
        p.encode_status(2, 0x80, bytes(range(10))),
        p.encode_status(3, 0, b"\xff\xff\xfd\x00\xff\xff\xfd"),
        p.encode_instruction(p.BROADCAST_ID, p.Instruction.SYNC_READ, p.sync_read_params(126, 10, [1, 2, 3])),
        p.encode_fast_sync_read_status([(1, 0, bytes(10)), (2, 0x80, b"\xff" * 10), (3, 1, bytes(range(10)))]),
        b"\x00\xff" + p.encode_status(4, 0, bytes(4)) + p.encode_status(5, 0, bytes(4)),
    ]


def _dxl_check(data: bytes, rng: random.Random) -> None:
    from uniros_async.hardware.dxl import protocol as p

    parser = p.PacketParser(raise_on_crc=rng.random() < 0.5)
    i = 0
    while i < len(data):
        n = rng.randint(1, 64)
        for pkt in parser.feed(data[i : i + n]):
            assert p.crc16(pkt.raw[:-2]) == pkt.raw[-2] | (pkt.raw[-1] << 8)
            if pkt.is_status and pkt.servo_id == p.BROADCAST_ID:
                p.parse_fast_sync_read(pkt, rng.choice((4, 10)))
        i += n
    assert parser.buffered <= len(data)


def _dxl_rejects() -> tuple[type[BaseException], ...]:
    from uniros_async.errors import CodecError, DxlCrcError

    return (CodecError, DxlCrcError)


PARSERS: dict[str, _Target] = {
    "tcp-handshake": _Target(_tcp_handshake_seeds, _tcp_rejects, check=_tcp_handshake_check),
    "tcp-frames": _Target(_tcp_frames_seeds, _tcp_rejects, acheck=_tcp_frames_check),
    "shm-handshake": _Target(_shm_seeds, _shm_rejects, acheck=_shm_check),
    "codec": _Target(_codec_seeds, _codec_rejects, check=_codec_check),
    "worker": _Target(_worker_seeds, _codec_rejects, check=_worker_check),
    "tcpros-header": _Target(_tcpros_seeds, _tcpros_rejects, acheck=_tcpros_check),
    "xmlrpc": _Target(_xmlrpc_seeds, _xmlrpc_rejects, acheck=_xmlrpc_check),
    "ros1-msgs": _Target(_ros1_seeds, _ros1_rejects, check=_ros1_check),
    "dxl": _Target(_dxl_seeds, _dxl_rejects, check=_dxl_check),
}


# ------------------------------------------------------------------------------------------- runner


def _on_alarm(signum: int, frame: Any) -> None:
    raise _Hang


def _run_plain(target: _Target, counts: FuzzCounts, inputs: Callable[[], bytes], n: int, limit_s: float) -> None:
    assert target.check is not None
    rejects = target.rejects()
    rng = random.Random(counts.inputs)
    old = signal.signal(signal.SIGALRM, _on_alarm)
    try:
        for _ in range(n):
            data = inputs()
            counts.inputs += 1
            try:
                signal.setitimer(signal.ITIMER_REAL, limit_s)
                try:
                    target.check(data, rng)
                finally:
                    signal.setitimer(signal.ITIMER_REAL, 0)
                counts.accepted += 1
            except _Hang:
                counts.hangs += 1
                counts.note("hang", data, f"over {limit_s} s")
            except rejects:
                counts.rejected += 1
            except Exception:
                counts.crashes += 1
                counts.note("crash", data, traceback.format_exc())
    finally:
        signal.signal(signal.SIGALRM, old)


async def _run_async(target: _Target, counts: FuzzCounts, inputs: Callable[[], bytes], n: int, limit_s: float) -> None:
    assert target.acheck is not None
    rejects = target.rejects()
    rng = random.Random(counts.inputs)
    loop = asyncio.get_running_loop()
    loop_errors: list[str] = []

    def handler(loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        exc = context.get("exception")
        tb = "".join(traceback.format_exception(exc)) if exc is not None else ""
        loop_errors.append(f"{context.get('message')}\n{tb}")

    loop.set_exception_handler(handler)
    for _ in range(n):
        data = inputs()
        counts.inputs += 1
        del loop_errors[:]
        outcome = "accepted"
        detail = ""
        try:
            async with asyncio.timeout(limit_s):
                await target.acheck(data, rng)
        except TimeoutError:
            outcome, detail = "hang", f"over {limit_s} s"
        except rejects:
            outcome = "rejected"
        except Exception:
            outcome, detail = "crash", traceback.format_exc()
        await asyncio.sleep(0)  # let callbacks scheduled by the input run before judging it
        if loop_errors and outcome != "crash":
            outcome, detail = "crash", loop_errors[0]
        if outcome == "accepted":
            counts.accepted += 1
        elif outcome == "rejected":
            counts.rejected += 1
        elif outcome == "hang":
            counts.hangs += 1
            counts.note("hang", data, detail)
        else:
            counts.crashes += 1
            counts.note("crash", data, detail)


def run(parser: str, count: int, *, seed: int = 0, time_limit_s: float = 2.0) -> FuzzCounts:
    """Feed ``count`` generated inputs to ``parser`` (a key of ``PARSERS``) and count what happened.

    Raises:
        KeyError: an unknown parser.
    """
    import logging

    target = PARSERS[parser]
    counts = FuzzCounts(parser)
    rng = random.Random(f"{parser}/{seed}")
    seeds = target.seeds()
    queue = list(seeds)  # the seeds themselves first: each must be accepted

    def inputs() -> bytes:
        return queue.pop(0) if queue else mutate(rng, seeds)

    t0 = time.perf_counter()
    logging.disable(logging.CRITICAL)  # rejections log warnings (rate-limited); a fuzz run is all rejections
    try:
        if target.check is not None:
            _run_plain(target, counts, inputs, count, time_limit_s)
        else:
            asyncio.run(_run_async(target, counts, inputs, count, time_limit_s))
    finally:
        logging.disable(logging.NOTSET)
    counts.seconds = time.perf_counter() - t0
    return counts


def format_table(results: Sequence[FuzzCounts]) -> str:
    """One row per parser: inputs, accepted, rejected, crashes, hangs, seconds."""
    head = f"{'parser':<14} {'inputs':>9} {'accepted':>9} {'rejected':>9} {'crashes':>8} {'hangs':>6} {'s':>7}"
    lines = [head, "-" * len(head)]
    for c in results:
        lines.append(
            f"{c.parser:<14} {c.inputs:>9,} {c.accepted:>9,} {c.rejected:>9,} {c.crashes:>8} {c.hangs:>6} "
            f"{c.seconds:>7.1f}"
        )
    for c in results:
        for kind, data, detail in c.examples:
            lines += ["", f"{c.parser}: {kind} on {data[:200]!r}", detail.rstrip()]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """The command line; returns 1 if any parser crashed or hung."""
    ap = argparse.ArgumentParser(prog="python -m rig.fuzz", description=__doc__.split("\n")[0])
    ap.add_argument("--parser", nargs="+", default=["all"], help=f"all, or some of: {', '.join(PARSERS)}")
    ap.add_argument("--count", type=int, default=10_000, help="inputs per parser (default %(default)s)")
    ap.add_argument("--seed", type=int, default=0, help="random seed (default %(default)s)")
    ap.add_argument("--time-limit-s", type=float, default=2.0, help="per input: longer is a hang (default 2)")
    args = ap.parse_args(argv)
    names = list(PARSERS) if "all" in args.parser else args.parser
    unknown = [n for n in names if n not in PARSERS]
    if unknown:
        ap.error(f"unknown parser(s) {unknown}; choose from {list(PARSERS)}")
    results = []
    for name in names:
        results.append(run(name, args.count, seed=args.seed, time_limit_s=args.time_limit_s))
        sys.stdout.write(format_table(results[-1:]).splitlines()[2] + "\n")  # progress: one row per parser
        sys.stdout.flush()
    sys.stdout.write("\n" + format_table(results) + "\n")
    return 1 if any(c.crashes or c.hangs for c in results) else 0


if __name__ == "__main__":
    raise SystemExit(main())
