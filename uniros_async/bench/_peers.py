"""Echo servers for the transport benchmark, one per implementation, each run in its own (spawned) process.

Every server takes (address, ready pipe): it binds, sends its concrete address on the pipe, then echoes every
frame back until the peer sends the 4-byte frame b"STOP" (or the pipe closes), and for throughput counts frames:
a frame starting with b"COUNT" makes it reply, after that many frames arrived, with one ack frame.
Peers are imported inside their functions so a missing optional package only disables that peer.
"""

from __future__ import annotations

import asyncio
import signal
import struct
from multiprocessing.connection import Connection
from typing import Any

STOP = b"STOP"
COUNT = b"COUNT"
_Q = struct.Struct("<Q")


def _quiet() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def serve_uniros(uri: str, ready: Connection, loan: bool = False) -> None:
    """Echo server on one of our transports (shm://, tcp://).

    ``loan``: answer each frame with a frame of the same size loaned from the ring (``ShmTransport.loan``) that
    carries only the request's first 8 bytes (the client's stamp), the way iceoryx2's publish-subscribe benchmark
    answers (it loans and sends without writing the payload): the round trip of a zero-copy producer, no payload
    copy on either side. Without it every frame goes back with ``send`` (one copy into the ring)."""
    _quiet()
    from uniros_async.errors import TransportBrokenError, TransportClosedError
    from uniros_async.transports.base import TransportOptions, listen

    async def main() -> None:
        lst = await listen(uri, TransportOptions())
        ready.send(lst.uri)
        t = await lst.accept()
        try:
            while True:
                f = await t.receive()
                if f.nbytes == 4 and bytes(f) == STOP:
                    break
                if f.nbytes == 13 and bytes(f[:5]) == COUNT:
                    (n,) = _Q.unpack(f[5:13])
                    for _ in range(n):
                        await t.receive()
                    await t.send(b"ACK")
                    continue
                if loan:
                    async with t.loan(f.nbytes) as buf:
                        buf[:8] = f[:8]
                    continue
                await t.send(f)
        except (TransportBrokenError, TransportClosedError):
            pass
        finally:
            await t.aclose()
            await lst.aclose()

    asyncio.run(main())


def serve_pipe(_addr: str, ready: Connection, conn: Connection) -> None:
    """multiprocessing.Pipe echo (the connection is passed in at spawn)."""
    _quiet()
    ready.send("pipe")
    while True:
        try:
            f = conn.recv_bytes()
        except EOFError:
            return
        if f == STOP:
            return
        if len(f) == 13 and f[:5] == COUNT:
            (n,) = _Q.unpack(f[5:13])
            for _ in range(n):
                conn.recv_bytes()
            conn.send_bytes(b"ACK")
            continue
        conn.send_bytes(f)


def serve_zmq(addr: str, ready: Connection) -> None:
    """pyzmq PAIR echo, blocking sockets (no asyncio overhead: the strongest form of this peer)."""
    _quiet()
    import zmq

    ctx = zmq.Context()
    s = ctx.socket(zmq.PAIR)
    if addr.startswith("tcp://"):
        port = s.bind_to_random_port("tcp://127.0.0.1")
        addr = f"tcp://127.0.0.1:{port}"
    else:
        s.bind(addr)
    ready.send(addr)
    try:
        while True:
            f = s.recv(copy=False)
            b = f.buffer
            if len(b) == 4 and bytes(b) == STOP:
                break
            if len(b) == 13 and bytes(b[:5]) == COUNT:
                (n,) = _Q.unpack(bytes(b[5:13]))
                for _ in range(n):
                    s.recv(copy=False)
                s.send(b"ACK")
                continue
            s.send(f, copy=False)
    finally:
        s.close(linger=0)
        ctx.term()


def zenoh_config(port: int, listen: bool) -> Any:
    import json

    import zenoh

    # no multicast scouting (loopback only) and no shared memory: zenoh otherwise leaves <pid>.zenoh files in
    # /dev/shm behind, and this peer is measured over tcp anyway
    conf: dict[str, Any] = {
        "mode": "peer",
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"shared_memory": {"enabled": False}},
    }
    if listen:
        conf["listen"] = {"endpoints": [f"tcp/127.0.0.1:{port}"]}
    else:
        conf["connect"] = {"endpoints": [f"tcp/127.0.0.1:{port}"]}
    return zenoh.Config.from_json5(json.dumps(conf))


def serve_zenoh(addr: str, ready: Connection) -> None:
    """zenoh peer: subscribes bench/ping, republishes on bench/pong."""
    _quiet()
    import threading

    import zenoh

    port = int(addr.rsplit(":", 1)[1])
    session = zenoh.open(zenoh_config(port, listen=True))
    pong = session.declare_publisher("bench/pong")
    done = threading.Event()
    counting = {"left": 0}

    def on_ping(sample: Any) -> None:
        b = sample.payload.to_bytes()
        if b == STOP:
            done.set()
            return
        if counting["left"] > 0:
            counting["left"] -= 1
            if counting["left"] == 0:
                pong.put(b"ACK")
            return
        if len(b) == 13 and b[:5] == COUNT:
            counting["left"] = _Q.unpack(b[5:13])[0]
            return
        pong.put(b)

    sub = session.declare_subscriber("bench/ping", on_ping)
    ready.send(addr)
    done.wait(600)
    sub.undeclare()  # type: ignore[no-untyped-call]  # zenoh ships no annotations here
    session.close()  # type: ignore[no-untyped-call]


def iceoryx2_ports(node: Any, name: str, max_len: int, *, send: str, receive: str) -> tuple[Any, Any]:
    """A publisher on ``name/send`` and a subscriber of ``name/receive``: iceoryx2 publish-subscribe services of
    byte slices up to ``max_len`` bytes, that block a publisher whose subscriber's buffer is full (no loss)."""
    import ctypes

    import iceoryx2 as iox2

    def service(topic: str) -> Any:
        return (
            node.service_builder(iox2.ServiceName.new(f"{name}/{topic}"))
            .publish_subscribe(iox2.Slice[ctypes.c_uint8])
            .enable_safe_overflow(False)
            .subscriber_max_buffer_size(16)
            .open_or_create()
        )

    pub = (
        service(send)
        .publisher_builder()
        .initial_max_slice_len(max_len)
        .backpressure_strategy(iox2.BackpressureStrategy.RetryUntilDelivered)
        .create()
    )
    sub = service(receive).subscriber_builder().buffer_size(16).create()
    return pub, sub


def iceoryx2_bytes(sample: Any) -> Any:
    """A sample's payload as a uint8 numpy array over its shared memory (iceoryx2's memoryview has format '<B')."""
    import numpy as np

    return np.frombuffer(sample.payload().as_memory_view(), np.uint8)


def iceoryx2_receive(sub: Any) -> Any:
    """The next sample of ``sub``, polled (iceoryx2's own benchmark polls too: no event wakes the reader)."""
    while True:
        sample = sub.receive()
        if sample is not None:
            return sample


def serve_iceoryx2(addr: str, ready: Connection, copy: bool, max_len: int) -> None:
    """iceoryx2 echo: receives on ``addr/ping``, answers on ``addr/pong`` with a loaned sample of the same size.

    ``copy``: the answer carries the whole payload (copied from the received sample into the loan, as ``shm``
    copies it); else only its first 8 bytes (the stamp), as ``shm-loan`` does."""
    _quiet()
    import iceoryx2 as iox2
    import numpy as np

    iox2.set_log_level_from_env_or(iox2.LogLevel.Warn)
    node = iox2.NodeBuilder.new().create(iox2.ServiceType.Ipc)
    pub, sub = iceoryx2_ports(node, addr, max_len, send="pong", receive="ping")
    ready.send(addr)
    counting = 0
    while True:
        sample = iceoryx2_receive(sub)
        view = iceoryx2_bytes(sample)
        n = view.nbytes
        if n == 4 and view.tobytes() == STOP:
            break
        if counting:
            counting -= 1
            if counting == 0:
                ack = pub.loan_slice_uninit(3)
                iceoryx2_bytes(ack)[:] = np.frombuffer(b"ACK", np.uint8)
                ack.assume_init().send()
            continue
        if n == 13 and view[:5].tobytes() == COUNT:
            counting = _Q.unpack(view[5:13].tobytes())[0]
            continue
        out = pub.loan_slice_uninit(n)
        dst = iceoryx2_bytes(out)
        if copy:
            dst[:] = view
        else:
            dst[: min(8, n)] = view[: min(8, n)]
        del view, dst, sample
        out.assume_init().send()
    del pub, sub, node
