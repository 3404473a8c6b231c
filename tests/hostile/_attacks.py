"""What a hostile peer does to a port, over real loopback sockets: garbage, oversized length announcements, half
frames, slow drips, connections held open by the thousand, and valid handshakes followed by malformed requests.

A ``Protocol`` says what valid and broken bytes look like for one kind of port (the uniros tcp transport, ROS 1's
XML-RPC slave API, TCPROS); ``run_attacks`` throws every attack at a port and returns how many of each it made.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import random
import resource
import struct
import time
from collections.abc import Callable

from uniros_async.transports._tcp_handshake import TcpHandshake

_U32 = struct.Struct("<I")


@dataclasses.dataclass(frozen=True)
class Protocol:
    """Byte strings that attack one kind of port."""

    name: str
    valid_prefix: bytes
    """What a legitimate peer sends first (a hello, a request's start): dripped slowly, or cut in half."""
    oversized: bytes
    """A length announcement far over any limit."""
    half: bytes
    """The start of a message whose rest never comes."""
    malformed: Callable[[random.Random], bytes]
    """After ``valid_prefix``: one malformed request."""


def uniros_tcp() -> Protocol:
    hello = TcpHandshake(key=None, listener=False, max_frame_bytes=1 << 20, peer="attacker").hello()

    def malformed(rng: random.Random) -> bytes:
        body = rng.choice(
            (
                rng.randbytes(rng.randrange(1, 64)),  # not msgpack
                b"\x93\x01\x02\x03",  # msgpack, but a list, not a request map
                b"\x81\xa2op\xa7no_such",  # an unknown op
                b"\x82\xa2op\xa9subscribe\xa2id\x01",  # a known op without its fields
            )
        )
        return _U32.pack(len(body)) + body

    return Protocol(
        name="uniros-tcp",
        valid_prefix=hello,
        oversized=hello + _U32.pack(0xFFFFFFFF),
        half=hello + _U32.pack(1000) + b"x" * 10,
        malformed=malformed,
    )


def xmlrpc() -> Protocol:
    def malformed(rng: random.Random) -> bytes:
        body = rng.choice(
            (
                b"<?xml version='1.0'?><methodCall><methodName>getPid</methodName><params><param>",  # cut XML
                b"<methodCall><methodName>requestTopic</methodName><params><param><value><int>1</int></value>"
                b"</param></params></methodCall>",  # wrong arguments
                b"<methodCall><methodName>shutdown</methodName><params><param><value>x</value></param>"
                b"</params></methodCall>",
                b"<!DOCTYPE x [<!ENTITY a 'aaaaaaaaaa'><!ENTITY b '&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;'>]><x>&b;</x>",
                rng.randbytes(rng.randrange(1, 200)),
            )
        )
        return b"Content-Type: text/xml\r\n" + f"Content-Length: {len(body)}\r\n\r\n".encode() + body

    return Protocol(
        name="xmlrpc",
        valid_prefix=b"POST / HTTP/1.1\r\nHost: 127.0.0.1\r\n",
        oversized=b"POST / HTTP/1.1\r\nContent-Length: 99999999999\r\n\r\n",
        half=b"POST / HTTP/1.1\r\nContent-Length: 1000\r\n\r\n<?xml",
        malformed=malformed,
    )


def tcpros(topic: str) -> Protocol:
    def field(s: str) -> bytes:
        return _U32.pack(len(s)) + s.encode()

    def malformed(rng: random.Random) -> bytes:
        return rng.choice(
            (
                b"".join(field(f) for f in ("callerid=/x", f"topic={topic}", "md5sum=0123", "type=wrong/Type")),
                field("no-equals-sign") + b"\x00\x00",
                _U32.pack(100) + b"short",
                rng.randbytes(rng.randrange(1, 100)),
            )
        )

    def header(fields: bytes) -> bytes:
        return _U32.pack(len(fields)) + fields

    return Protocol(
        name="tcpros",
        valid_prefix=b"",
        oversized=_U32.pack(0xFFFFFFFF),
        half=_U32.pack(500) + field("callerid=/half"),
        malformed=lambda rng: header(malformed(rng)),
    )


def raise_fd_limit() -> None:
    """Soft RLIMIT_NOFILE up to the hard limit: a thousand held connections need a thousand descriptors."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < hard:
        resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))


def rss_bytes(pid: int) -> int:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    raise AssertionError(f"no VmRSS for pid {pid}")


@dataclasses.dataclass
class AttackReport:
    connections: int = 0
    refused: int = 0
    """Connections the server closed or reset before we were done with them (refusals, evictions)."""
    peak_rss_growth: int = 0
    held: int = 0


async def _open(host: str, port: int, report: AttackReport) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    report.connections += 1
    return await asyncio.open_connection(host, port)


async def _close(writer: asyncio.StreamWriter) -> None:
    writer.close()
    with contextlib.suppress(OSError):
        await writer.wait_closed()


async def _send_and_close(host: str, port: int, data: bytes, report: AttackReport) -> None:
    try:
        _, w = await _open(host, port, report)
    except OSError:
        report.refused += 1
        return
    try:
        w.write(data)
        await w.drain()
    except OSError:
        report.refused += 1
    finally:
        await _close(w)


async def _drip(host: str, port: int, data: bytes, delay_s: float, report: AttackReport) -> None:
    try:
        _, w = await _open(host, port, report)
    except OSError:
        report.refused += 1
        return
    try:
        for i in range(len(data)):
            w.write(data[i : i + 1])
            await w.drain()
            await asyncio.sleep(delay_s)
    except OSError:
        report.refused += 1
    finally:
        await _close(w)


async def run_attacks(
    host: str,
    port: int,
    proto: Protocol,
    *,
    server_pid: int,
    hold: int = 1000,
    hold_prefix: bytes = b"",
    rounds: int = 40,
    seed: int = 0,
) -> AttackReport:
    """Every attack on ``host:port``; ``hold`` connections stay open (after sending ``hold_prefix``) while the
    server's RSS is sampled. Returns the counts and the peak RSS growth of ``server_pid``."""
    rng = random.Random(seed)
    report = AttackReport()
    base_rss = rss_bytes(server_pid)
    # garbage, oversized announcements, half messages, and valid starts followed by malformed requests
    jobs = []
    for _ in range(rounds):
        jobs.append(_send_and_close(host, port, rng.randbytes(rng.randrange(1, 512)), report))
        jobs.append(_send_and_close(host, port, proto.oversized, report))
        jobs.append(_send_and_close(host, port, proto.half, report))
        bad = proto.valid_prefix + b"".join(proto.malformed(rng) for _ in range(rng.randint(1, 20)))
        jobs.append(_send_and_close(host, port, bad, report))
    drips = [_drip(host, port, proto.valid_prefix or proto.half, 0.05, report) for _ in range(10)]
    await asyncio.gather(*jobs, *drips)
    # a thousand connections held open at once
    held: list[asyncio.StreamWriter] = []
    try:
        for i in range(hold):
            try:
                _, w = await _open(host, port, report)
            except OSError:
                report.refused += 1
                continue
            held.append(w)
            if hold_prefix:
                w.write(hold_prefix)
            if i % 100 == 99:
                report.peak_rss_growth = max(report.peak_rss_growth, rss_bytes(server_pid) - base_rss)
                await asyncio.sleep(0)
        report.held = len(held)
        t_end = time.monotonic() + 2.0  # hold them a while: the server's timers and caps act meanwhile
        while time.monotonic() < t_end:
            report.peak_rss_growth = max(report.peak_rss_growth, rss_bytes(server_pid) - base_rss)
            await asyncio.sleep(0.2)
    finally:
        for w in held:
            w.close()
        await asyncio.sleep(0.1)
    return report
