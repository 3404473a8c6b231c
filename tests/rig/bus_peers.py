"""Bus nodes that run in another process, for cross-process tests: ``async with BusPeer(uri, "talker"): ...``, and
``check_talker``, what a test node checks of a talker."""

from __future__ import annotations

import asyncio
import multiprocessing as mp
import signal
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from uniros_async.bus.node import Node

__all__ = ["BusPeer", "check_talker", "peer_main"]


def peer_main(domain_uri: str, role: str, transport: str, conn: Connection) -> None:
    """Entry point of a peer process. Roles:

    - ``talker``: publishes JointState on /chatter at 200 Hz (seq counts up) and serves /add (Data -> Data).
    - ``echo``: subscribes /ping (Blob, reliable) and republishes each message on /pong.
    - ``frames`` (or ``frames:TOPIC``): reads /cam/color/image_raw (or TOPIC; Image, latest, zero_copy) and answers
      each frame on /frames_seen with Data ``[seq, pixel sum, read-only, shape, encoding, frame_id]``.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from uniros_async.bus import open_node, reliable
    from uniros_async.bus.messages import Blob, Data, Header, Image, JointState

    async def main() -> None:
        stop = asyncio.Event()
        asyncio.get_running_loop().add_reader(conn.fileno(), stop.set)
        async with open_node(role.partition(":")[0], domain=domain_uri, transport=transport) as node:
            if role == "talker":
                pub = await node.create_publisher(JointState, "/chatter", qos=reliable(1000))
                await node.create_service(Data, Data, "/add", lambda r: Data(value=sum(r.value)))
                seq = 0

                def tick() -> None:
                    nonlocal seq
                    seq += 1
                    pub.publish(
                        JointState(
                            header=Header(stamp_ns=node.now_ns(), seq=seq),
                            name=("j1", "j2"),
                            position=np.array([seq, -seq], float),
                            velocity=np.zeros(2),
                            effort=np.zeros(2),
                        )
                    )

                node.create_timer(0.005, tick)
            elif role == "echo":
                pong = await node.create_publisher(Blob, "/pong", qos=reliable(1000))
                await node.create_subscription(Blob, "/ping", pong.publish, qos=reliable(1000))
            elif role.startswith("frames"):
                seen = await node.create_publisher(Data, "/frames_seen", qos=reliable(1000))

                def check(m: Image) -> None:
                    d = m.data
                    info = [m.header.seq, int(d.sum(dtype=np.int64)), not d.flags.writeable, list(d.shape)]
                    seen.publish(Data(value=[*info, m.encoding, m.header.frame_id]))

                topic = role.partition(":")[2] or "/cam/color/image_raw"
                await node.create_subscription(Image, topic, check, zero_copy=True)
            conn.send("ready")
            await stop.wait()

    asyncio.run(main())


async def check_talker(node: Node, count: int = 20, timeout_s: float = 20.0) -> None:
    """From ``node``, check a ``talker`` peer: ``count`` of its JointStates on /chatter arrive reliably, in order and
    intact (none rejected), and its /add service answers.

    Raises:
        AssertionError: any of them did not hold.
        TimeoutError: nothing within ``timeout_s``.
    """
    from uniros_async.bus import reliable
    from uniros_async.bus.messages import Data, JointState

    sub = await node.create_subscription(JointState, "/chatter", qos=reliable(1000))
    async with asyncio.timeout(timeout_s):
        await sub.wait_for_publishers(1, timeout_s=timeout_s / 2)
        msgs = [await sub.receive() for _ in range(count)]
    seqs = [m.header.seq for m in msgs]
    assert seqs == list(range(seqs[0], seqs[0] + count)), f"reliable delivery in order, got {seqs}"
    assert all(m.position[0] == m.header.seq for m in msgs)
    assert sub.rejected == 0
    cli = node.create_client(Data, Data, "/add")
    assert (await cli.call(Data(value=[1, 2, 3]), timeout_s=5)).value == 6, "the talker's /add"


class BusPeer:
    """Runs ``peer_main`` in a spawned process: ``async with BusPeer(uri, "talker"):``; leaving the block stops it
    (closing the pipe), or kill() it."""

    def __init__(self, domain_uri: str, role: str, transport: str = "auto") -> None:
        ctx = mp.get_context("spawn")
        self._parent, child = ctx.Pipe()
        self.proc = ctx.Process(target=peer_main, args=(domain_uri, role, transport, child), daemon=True)
        self._child = child

    async def __aenter__(self) -> BusPeer:
        # The domain may be served by this very event loop: wait for "ready" without blocking it.
        self.proc.start()
        self._child.close()
        loop = asyncio.get_running_loop()
        ready = asyncio.Event()
        loop.add_reader(self._parent.fileno(), ready.set)
        try:
            async with asyncio.timeout(60):
                await ready.wait()
        except TimeoutError:
            self.proc.kill()
            self.proc.join(5)
            raise TimeoutError("bus peer did not start within 60 s") from None
        finally:
            loop.remove_reader(self._parent.fileno())
        msg = self._parent.recv() if self._parent.poll(0) else None
        if msg != "ready":
            self.proc.join(5)
            raise RuntimeError(f"bus peer failed to start (exit code {self.proc.exitcode})")
        return self

    def kill(self) -> None:
        self.proc.kill()
        self.proc.join(5)

    async def __aexit__(self, *exc: object) -> None:
        self._parent.close()
        for _ in range(200):  # up to 10 s, without blocking the loop that may serve the domain
            if not self.proc.is_alive():
                break
            await asyncio.sleep(0.05)
        self.proc.join(0.1)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(5)
            raise AssertionError("bus peer did not stop within 10 s")
