"""The contract of ``Publisher.loan`` over each transport, with the subscriber in another process.

``check_publisher_loans(kind)`` runs a domain of its own and a publisher on transport ``kind`` (``shm``, ``tcp``,
``tls``; ``memory`` is in-process only), and a subscriber process (``python -m
uniros_async.testing.transport_contract_loans``) that reads each frame in place (``zero_copy``) and reports what it
saw. It checks:

- every loaned frame arrives as written: pixels, shape, encoding, ``frame_id``; where the transport lends, as a
  read-only view of the reader's ring;
- ``loan.in_place`` is True on a transport that lends (``LENDING``: the frame's place in the reader's shm ring,
  counted by the transport as a loaned frame) and False on the others (a buffer of the publisher's own);
- a slow reader: frames loaned faster than it reads never change under a view it holds, and the newest arrives;
- a publisher that restarts on the same topic reaches the same reader;
- a reader that dies holding a frame: the publisher drops it and goes on loaning, and a new reader gets frames.

``memory`` has no remote reader: ``check_publisher_loans("memory")`` checks that in-process subscribers get the
loaned message itself. ``require_lending(kind)`` raises ConfigError naming the transports that lend when ``kind``
does not: the check to run for in-place loans on a transport that only copies.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import sys
import time
from collections.abc import AsyncIterator
from typing import Any

import numpy as np

from uniros_async.errors import ConfigError

__all__ = ["KINDS", "LENDING", "check_publisher_loans", "require_lending"]

LENDING = ("shm",)
"""Transports whose ``Publisher.loan`` lends the subscriber's own memory (no copy after the producer's write)."""
COPYING = ("tcp", "tls")
"""Transports whose loans are a buffer of the publisher's own, sent with one copy as ``publish`` sends."""
KINDS = ("memory", *LENDING, *COPYING)
T_S = 20.0
TOPIC = "/contract/camera/color/image_raw"
SHAPE = (120, 160, 3)


def require_lending(kind: str) -> None:
    """Raise unless ``kind``'s ``Publisher.loan`` lends the subscriber's memory.

    Raises:
        ConfigError: ``kind`` copies (names the transports that lend) or is unknown.
    """
    if kind in LENDING:
        return
    if kind in COPYING or kind == "memory":
        how = "in-process subscribers get the message itself" if kind == "memory" else "sent with one copy"
        raise ConfigError(
            f"transport {kind!r} does not lend memory to Publisher.loan: its loans are a buffer of the publisher's "
            f"own ({how}; loan.in_place is False); in-place loans need one of {list(LENDING)}"
        )
    raise ConfigError(f"unknown transport {kind!r}; expected one of {list(KINDS)}")


def _frame(seq: int) -> int:
    return seq % 251


class _Reader:
    """The subscriber process: ``hold_s`` is how long it holds each frame's view before letting it go."""

    def __init__(self, domain_uri: str, kind: str, hold_s: float) -> None:
        self.args = [domain_uri, kind, str(hold_s)]
        self.proc: asyncio.subprocess.Process | None = None

    async def __aenter__(self) -> _Reader:
        self.proc = await asyncio.create_subprocess_exec(
            sys.executable,
            "-m",
            "uniros_async.testing.transport_contract_loans",
            *self.args,
            stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE,
        )
        assert self.proc.stdout is not None
        try:
            async with asyncio.timeout(60):
                line = await self.proc.stdout.readline()
        except TimeoutError:
            self.kill()
            raise TimeoutError("the loan contract's reader did not start within 60 s") from None
        if line.strip() != b"ready":
            await self.proc.wait()
            raise RuntimeError(f"the loan contract's reader failed to start (exit code {self.proc.returncode})")
        return self

    def kill(self) -> None:
        if self.proc is not None and self.proc.returncode is None:
            self.proc.kill()

    async def __aexit__(self, *exc: object) -> None:
        proc = self.proc
        if proc is None:
            return
        if proc.returncode is None and proc.stdin is not None:
            proc.stdin.close()  # the reader's cue to stop
        try:
            async with asyncio.timeout(10):
                await proc.wait()
        except TimeoutError:
            proc.kill()
            await proc.wait()
            raise AssertionError("the loan contract's reader did not stop within 10 s of being told to") from None


async def _loan(pub: Any, seq: int) -> bool:
    from uniros_async.bus.messages import Header, Image

    async with pub.loan(SHAPE) as loan:
        loan.array[...] = _frame(seq)  # the producer's one write
        loan.message = Image(header=Header(stamp_ns=seq, seq=seq, frame_id="contract"), data=loan.array)
    return bool(loan.in_place)


async def _until(sub: Any, seq: int) -> list[list[Any]]:
    """The reader's reports up to and including frame ``seq``."""
    got: list[list[Any]] = []
    while not got or got[-1][0] < seq:
        got.append(list((await sub.receive()).value))
    return got


def _check_report(report: list[Any], lends: bool) -> None:
    seq, before, after, read_only, shape, encoding, frame_id = report
    want = _frame(seq) * int(np.prod(SHAPE))
    assert before == want, f"frame {seq}: the reader saw pixel sum {before}, expected {want}"
    assert after == before, f"frame {seq} changed under the reader's view while it held it ({before} -> {after})"
    if lends:  # the reader's view is the frame's place in its ring (over tcp, its own receive buffer)
        assert read_only, f"frame {seq}: the reader's view of the ring is writable"
    assert shape == list(SHAPE) and encoding == "rgb8" and frame_id == "contract", report


async def _wait_subscribers(pub: Any, n: int) -> None:
    async with asyncio.timeout(T_S):
        while pub.subscription_count != n:  # noqa: ASYNC110 - the sinks come and go with connections
            await asyncio.sleep(0.02)


@contextlib.asynccontextmanager
async def _publisher_node(kind: str) -> AsyncIterator[tuple[Any, Any, Any]]:
    from uniros_async.bus import open_domain, open_node, reliable
    from uniros_async.bus.messages import Data

    uri = "tls://127.0.0.1:0" if kind == "tls" else "tcp://127.0.0.1:0"
    async with open_domain(uri) as domain, open_node("camera", domain=domain, transport=kind) as node:
        seen = await node.create_subscription(Data, "/contract/seen", qos=reliable(1000))
        yield domain, node, seen


async def _in_process(kind: str) -> None:
    from uniros_async.bus import latest, open_domain, open_node
    from uniros_async.bus.messages import Image

    async with open_domain("memory://") as domain, open_node("camera", domain=domain, transport=kind) as node:
        pub = await node.create_publisher(Image, TOPIC, qos=latest())
        sub = await node.create_subscription(Image, TOPIC, qos=latest())
        for seq in (1, 2):
            assert not await _loan(pub, seq), "an in-process loan is the publisher's own buffer"
            got = sub.latest()
            assert got is not None and got.header.seq == seq and int(got.data.sum()) == _frame(seq) * np.prod(SHAPE)
        assert pub.published == 2 and pub.loaned_in_place == 0


async def check_publisher_loans(kind: str) -> None:
    """The whole contract of ``Publisher.loan`` on transport ``kind`` (see the module docstring).

    Raises:
        AssertionError: a clause did not hold (named).
        ConfigError: ``kind`` is not a transport of ``KINDS``.
    """
    from uniros_async.bus import latest
    from uniros_async.bus.messages import Image

    if kind not in KINDS:
        raise ConfigError(f"unknown transport {kind!r}; expected one of {list(KINDS)}")
    if kind == "memory":
        await _in_process(kind)
        return
    lends = kind in LENDING
    async with _publisher_node(kind) as (domain, node, seen):
        pub = await node.create_publisher(Image, TOPIC, qos=latest())
        async with _Reader(domain.uri, kind, hold_s=0.02):
            await pub.wait_for_subscribers(1, timeout_s=T_S)
            await seen.wait_for_publishers(1, timeout_s=T_S)
            conn: Any = pub._sinks[0].conn
            loaned0 = getattr(conn, "frames_loaned", 0)
            async with asyncio.timeout(T_S):
                # in step: each frame arrives, as written, in place where the transport lends
                for seq in range(1, 6):
                    assert await _loan(pub, seq) is lends, f"{kind}: loan.in_place should be {lends}"
                    reports = await _until(seen, seq)
                    assert [r[0] for r in reports] == [seq], reports
                    _check_report(reports[0], lends)
                # a slow reader (it holds each view 20 ms): 40 frames loaned as fast as the ring takes them
                for seq in range(6, 46):
                    await _loan(pub, seq)
                reports = await _until(seen, 45)
                seqs = [r[0] for r in reports]
                assert seqs == sorted(set(seqs)) and seqs[-1] == 45, f"{kind}: out of order or the newest lost: {seqs}"
                for r in reports:
                    _check_report(r, lends)
            assert pub.loaned_in_place == (45 if lends else 0), f"{kind}: {pub.loaned_in_place} loaned in place"
            if lends:
                assert conn.frames_loaned - loaned0 == 45, "every in-place loan went out as a loaned frame"
            # the publisher restarts: a new one on the same topic reaches the same reader
            await pub.aclose()
            pub = await node.create_publisher(Image, TOPIC, qos=latest())
            await pub.wait_for_subscribers(1, timeout_s=T_S)
            async with asyncio.timeout(T_S):
                assert await _loan(pub, 46) is lends
                _check_report((await _until(seen, 46))[-1], lends)
        async with _Reader(domain.uri, kind, hold_s=60.0) as reader:
            await _wait_subscribers(pub, 1)
            async with asyncio.timeout(T_S):
                await _loan(pub, 47)
                await asyncio.sleep(0.2)  # the reader now holds frame 47's view
                reader.kill()  # a reader gone while it holds a frame
                await _wait_subscribers(pub, 0)
                t = time.monotonic()
                for seq in range(48, 51):
                    assert not await _loan(pub, seq), "a loan with no reader is the publisher's own buffer"
                assert time.monotonic() - t < 5.0, "loans waited on the dead reader's slot"
        async with _Reader(domain.uri, kind, hold_s=0.0):
            await pub.wait_for_subscribers(1, timeout_s=T_S)
            async with asyncio.timeout(T_S):
                seq = 50
                while True:  # until the new reader's reports reach us (its /contract/seen is new too)
                    seq += 1
                    assert await _loan(pub, seq) is lends
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(0.5):
                            _check_report((await _until(seen, seq))[-1], lends)
                            break


def _reader_main(domain_uri: str, kind: str, hold_s: float) -> None:
    """The subscriber process: reads ``TOPIC`` in place, holds each view ``hold_s`` s, and reports on
    /contract/seen ``[seq, pixel sum, pixel sum after holding, read-only, shape, encoding, frame_id]``; stops when
    its stdin closes."""
    from uniros_async.bus import latest, open_node, reliable
    from uniros_async.bus.messages import Data, Image

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        loop.add_reader(sys.stdin.fileno(), stop.set)
        async with open_node("reader", domain=domain_uri, transport=kind) as node:
            seen = await node.create_publisher(Data, "/contract/seen", qos=reliable(1000))

            def check(m: Image) -> None:
                d = m.data
                before = int(d.sum(dtype=np.int64))
                time.sleep(hold_s)  # a slow reader holds the view (and its place in the ring) meanwhile
                after = int(d.sum(dtype=np.int64))
                info = [m.header.seq, before, after, not d.flags.writeable, list(d.shape)]
                seen.publish(Data(value=[*info, m.encoding, m.header.frame_id]))

            await node.create_subscription(Image, TOPIC, check, qos=latest(), zero_copy=True)
            os.write(sys.stdout.fileno(), b"ready\n")
            await stop.wait()

    asyncio.run(main())


if __name__ == "__main__":
    _reader_main(sys.argv[1], sys.argv[2], float(sys.argv[3]))
