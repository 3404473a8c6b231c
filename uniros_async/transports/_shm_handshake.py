"""The handshake of an ``shm://`` connection, on the listener's Unix SOCK_SEQPACKET socket.

One message per packet::

    peer -> listener   HELLO      magic, flags (bit 0: has a key), ring_bytes wanted, nonce
    listener -> peer   CHALLENGE  magic, status, flags, nonce, proof = HMAC(key, "listener" | both nonces)
    peer -> listener   PROOF      magic, HMAC(key, "peer" | both nonces) (zeros without a key)
    listener -> peer   SETUP      magic, ring capacity; SCM_RIGHTS: memfd, listener's doorbell, peer's doorbell

Both ends prove the key (HMAC-SHA256, compared with hmac.compare_digest) before the listener creates any shared
memory. The capacity is the larger of the two ends' ``ring_bytes`` (rounded to pages, at most 1 GiB). After SETUP
the socket carries nothing; it stays open so that EOF tells each end that the other is gone.
"""

from __future__ import annotations

import asyncio
import dataclasses
import hashlib
import hmac
import mmap
import os
import socket
import struct

from uniros_async.errors import AuthenticationError, TransportBrokenError
from uniros_async.transports._shm_ring import MAX_CAPACITY, attach_segment, create_segment, round_capacity
from uniros_async.transports.base import TransportOptions

__all__ = ["Rejected", "Setup", "admit", "join"]

_MAGIC = b"UNRSHM01"
_HELLO = struct.Struct("<8sIIQ32s")  # magic, flags, reserved, ring_bytes wanted, nonce
_CHALLENGE = struct.Struct("<8sII32s32s")  # magic, status, flags, nonce, listener's proof
_PROOF = struct.Struct("<8s32s")  # magic, peer's proof (zeros without auth)
_SETUP = struct.Struct("<8sQ")  # magic, ring capacity; fds: memfd, listener's doorbell, peer's doorbell
_FLAG_AUTH = 1
_STATUS_OK, _STATUS_AUTH_REQUIRED, _STATUS_BAD_HELLO = 0, 1, 2
_MSG_MAX = 256


@dataclasses.dataclass(frozen=True, kw_only=True)
class Setup:
    """What a finished handshake hands to the transport (which then owns the mapping and both descriptors)."""

    mm: mmap.mmap
    cap: int
    rx_index: int
    doorbell_fd: int
    peer_doorbell_fd: int


class Rejected(Exception):
    """The peer failed the handshake."""


def _mac(key: bytes, role: bytes, nonce_peer: bytes, nonce_listener: bytes) -> bytes:
    return hmac.new(key, b"uniros-shm/" + role + nonce_peer + nonce_listener, hashlib.sha256).digest()


async def admit(conn: socket.socket, options: TransportOptions) -> Setup:
    """The listener's side: check the hello (and the peer's proof of the key), then create and send the segment.

    Raises:
        Rejected: the peer sent something malformed, has no key or the wrong one, or hung up.
        OSError: the socket failed.
    """
    loop = asyncio.get_running_loop()
    hello = await loop.sock_recv(conn, _MSG_MAX)
    if len(hello) != _HELLO.size or hello[:8] != _MAGIC:
        await _send_quietly(loop, conn, _CHALLENGE.pack(_MAGIC, _STATUS_BAD_HELLO, 0, bytes(32), bytes(32)))
        raise Rejected(
            f"malformed hello: {len(hello)} bytes starting {hello[:8]!r}, expected {_HELLO.size} from {_MAGIC!r}"
        )
    _, flags, _, ring_bytes, nonce_peer = _HELLO.unpack(hello)
    key = options.auth_key
    if key is not None and not flags & _FLAG_AUTH:
        await _send_quietly(
            loop, conn, _CHALLENGE.pack(_MAGIC, _STATUS_AUTH_REQUIRED, _FLAG_AUTH, bytes(32), bytes(32))
        )
        raise Rejected("peer has no auth_key, this listener requires one")
    nonce = os.urandom(32)
    proof = _mac(key, b"listener", nonce_peer, nonce) if key is not None else bytes(32)
    await loop.sock_sendall(conn, _CHALLENGE.pack(_MAGIC, _STATUS_OK, _FLAG_AUTH if key else 0, nonce, proof))
    msg = await loop.sock_recv(conn, _MSG_MAX)
    if not msg:
        raise Rejected("peer hung up during the handshake (did it refuse our key?)")
    if len(msg) != _PROOF.size or msg[:8] != _MAGIC:
        raise Rejected(f"malformed proof: {len(msg)} bytes")
    if key is not None and not hmac.compare_digest(msg[8:], _mac(key, b"peer", nonce_peer, nonce)):
        raise Rejected("peer's proof of auth_key is wrong")
    cap = round_capacity(max(options.ring_bytes, min(ring_bytes, MAX_CAPACITY)))
    memfd, mm = create_segment(cap)
    doorbell = peer_doorbell = -1
    try:
        doorbell = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        peer_doorbell = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        await _send_fds(loop, conn, _SETUP.pack(_MAGIC, cap), [memfd, doorbell, peer_doorbell])
        return Setup(mm=mm, cap=cap, rx_index=1, doorbell_fd=doorbell, peer_doorbell_fd=peer_doorbell)
    except BaseException:
        for fd in (doorbell, peer_doorbell):
            if fd >= 0:
                os.close(fd)
        mm.close()
        raise
    finally:
        os.close(memfd)  # both mappings keep the memory; nobody needs the descriptor any more


async def join(sock: socket.socket, name: str, options: TransportOptions) -> Setup:
    """The connecting side: say hello, check the listener's proof, prove ours, and map the segment it sends.

    Raises:
        AuthenticationError: the listener refused our key, wants one we lack, or failed to prove its own.
        TransportBrokenError: the listener sent something malformed or hung up.
        OSError: the socket failed.
    """
    loop = asyncio.get_running_loop()
    key = options.auth_key
    nonce = os.urandom(32)
    await loop.sock_sendall(sock, _HELLO.pack(_MAGIC, _FLAG_AUTH if key else 0, 0, options.ring_bytes, nonce))
    msg = await loop.sock_recv(sock, _MSG_MAX)
    if len(msg) != _CHALLENGE.size or msg[:8] != _MAGIC:
        raise TransportBrokenError(f"shm://{name} answered the hello with {len(msg)} bytes, not a challenge")
    _, status, flags, nonce_listener, proof = _CHALLENGE.unpack(msg)
    if status == _STATUS_AUTH_REQUIRED:
        raise AuthenticationError(f"shm://{name} requires an auth_key and none is set")
    if status != _STATUS_OK:
        raise TransportBrokenError(f"shm://{name} refused the hello (status {status})")
    if key is not None:
        if not flags & _FLAG_AUTH:
            raise AuthenticationError(f"shm://{name} does not authenticate, but auth_key is set")
        if not hmac.compare_digest(proof, _mac(key, b"listener", nonce, nonce_listener)):
            raise AuthenticationError(f"shm://{name} failed to prove knowledge of auth_key")
    mine = _mac(key, b"peer", nonce, nonce_listener) if key is not None else bytes(32)
    await loop.sock_sendall(sock, _PROOF.pack(_MAGIC, mine))
    msg, fds = await _recv_fds(loop, sock, 3)
    try:
        if not msg and not fds:
            if key is not None:
                raise AuthenticationError(f"shm://{name} refused our auth_key")
            raise TransportBrokenError(f"shm://{name} hung up during the handshake")
        if len(msg) != _SETUP.size or msg[:8] != _MAGIC or len(fds) != 3:
            raise TransportBrokenError(f"shm://{name} sent a malformed setup ({len(msg)} bytes, {len(fds)} fds)")
        _, cap = _SETUP.unpack(msg)
        try:
            mm = attach_segment(fds[0], cap)
        except ValueError as exc:
            raise TransportBrokenError(f"shm://{name} sent an unusable segment: {exc}") from exc
    except BaseException:
        for fd in fds:
            os.close(fd)
        raise
    os.close(fds[0])  # the mapping keeps the memory
    return Setup(mm=mm, cap=cap, rx_index=0, doorbell_fd=fds[2], peer_doorbell_fd=fds[1])


async def _send_quietly(loop: asyncio.AbstractEventLoop, sock: socket.socket, data: bytes) -> None:
    try:
        await loop.sock_sendall(sock, data)
    except OSError:
        pass


async def _wait_fd(loop: asyncio.AbstractEventLoop, fd: int, *, writable: bool) -> None:
    fut = loop.create_future()

    def ready() -> None:
        if not fut.done():
            fut.set_result(None)

    if writable:
        loop.add_writer(fd, ready)
    else:
        loop.add_reader(fd, ready)
    try:
        await fut
    finally:
        if writable:
            loop.remove_writer(fd)
        else:
            loop.remove_reader(fd)


async def _send_fds(loop: asyncio.AbstractEventLoop, sock: socket.socket, data: bytes, fds: list[int]) -> None:
    while True:
        try:
            socket.send_fds(sock, [data], fds)
            return
        except (BlockingIOError, InterruptedError):
            await _wait_fd(loop, sock.fileno(), writable=True)


async def _recv_fds(loop: asyncio.AbstractEventLoop, sock: socket.socket, maxfds: int) -> tuple[bytes, list[int]]:
    while True:
        try:
            msg, fds, flags, _ = socket.recv_fds(sock, _MSG_MAX, maxfds, socket.MSG_CMSG_CLOEXEC)
        except (BlockingIOError, InterruptedError):
            await _wait_fd(loop, sock.fileno(), writable=False)
            continue
        if flags & socket.MSG_CTRUNC:
            for fd in fds:
                os.close(fd)
            raise TransportBrokenError(f"descriptors were truncated in transit ({len(fds)} arrived)")
        return msg, fds
