"""The handshake of a ``tcp://`` (and ``tls://``) connection: a byte-fed state machine, free of sockets.

Wire format (little-endian)::

    hello   client -> listener   HELLO = MAGIC(8s) version(u16) flags(u16) max_frame_bytes(u64) nonce(32s)
            listener -> client   HELLO, then proof(32s) if flags has FLAG_AUTH
            client -> listener   proof(32s)                                     (only with FLAG_AUTH)

Both ends send their HELLO as soon as the connection is made. With a shared ``auth_key`` each side proves knowledge
of it without sending it: the listener sends HMAC-SHA256(key, b"uniros-tcp listener" + client_nonce +
listener_nonce), the client answers with the same over b"uniros-tcp client"; both are checked with
hmac.compare_digest. Fresh random nonces on both sides defeat replay, and the two labels defeat reflection. Both ends
refuse a peer whose key setting differs from their own. Each side announces its ``max_frame_bytes``.

``TcpHandshake.feed`` takes whatever bytes arrived, consumes what belongs to the handshake and returns what to write
back; it raises on the first byte that cannot start a valid handshake, so a stranger is refused early, without the
listener reading or allocating more than one HELLO.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import struct

from uniros_async.errors import AuthenticationError, TransportBrokenError

__all__ = ["FLAG_AUTH", "HELLO", "MAGIC", "PROOF_BYTES", "PROTOCOL_VERSION", "TcpHandshake"]

MAGIC = b"\x89UNIROS\n"
"""First bytes of every uniros tcp connection (high bit and newline catch 7-bit and text-mode mangling)."""
PROTOCOL_VERSION = 1
FLAG_AUTH = 1
HELLO = struct.Struct("<8sHHQ32s")
"""magic, version, flags, max_frame_bytes, nonce."""
PROOF_BYTES = 32
_LISTENER_LABEL = b"uniros-tcp listener"
_CLIENT_LABEL = b"uniros-tcp client"

_WANT_HELLO, _WANT_PROOF, _DONE, _FAILED = 0, 1, 2, 3


def _proof(key: bytes, label: bytes, client_nonce: bytes, listener_nonce: bytes) -> bytes:
    return hmac.new(key, label + client_nonce + listener_nonce, hashlib.sha256).digest()


class TcpHandshake:
    """One end's side of the handshake.

    Args:
        key: the shared auth key, or None (no authentication).
        listener: True on the accepting end (it proves itself first).
        max_frame_bytes: what this end accepts, announced in its HELLO.
        peer: how errors name the other end.
    """

    def __init__(self, *, key: bytes | None, listener: bool, max_frame_bytes: int, peer: str) -> None:
        self._key = key
        self._listener = listener
        self._max_frame = max_frame_bytes
        self.peer = peer
        self._nonce = os.urandom(32)
        self._peer_nonce = b""
        self._step = _WANT_HELLO
        self.peer_max_frame_bytes: int | None = None
        """What the peer announced it accepts (set once its HELLO arrived)."""

    @property
    def done(self) -> bool:
        """The handshake completed: frames may flow."""
        return self._step == _DONE

    def hello(self) -> bytes:
        """This end's HELLO, to send as soon as the connection is made."""
        flags = FLAG_AUTH if self._key is not None else 0
        return HELLO.pack(MAGIC, PROTOCOL_VERSION, flags, self._max_frame, self._nonce)

    def feed(self, data: memoryview | bytes) -> tuple[int, bytes]:
        """Consume handshake bytes from the start of ``data`` (which may hold less, or more: frames behind it).

        Returns:
            (bytes consumed, bytes to write back). Once ``done``, nothing more is consumed.

        Raises:
            TransportBrokenError: the peer is not a uniros tcp peer, or speaks another version.
            AuthenticationError: the key settings differ, or the peer failed to prove the shared key.
        """
        used = 0
        out = b""
        avail = len(data)
        while True:
            if self._step == _WANT_HELLO:
                check = min(avail - used, len(MAGIC))
                if bytes(data[used : used + check]) != MAGIC[:check]:
                    self._step = _FAILED
                    head = bytes(data[used : used + min(avail - used, 16)])
                    raise TransportBrokenError(f"{self.peer} is not a uniros tcp peer: it sent {head!r}")
                if avail - used < HELLO.size:
                    return used, out
                _, version, flags, max_frame, nonce = HELLO.unpack_from(data, used)
                used += HELLO.size
                out += self._hello_received(version, flags, max_frame, nonce)
            elif self._step == _WANT_PROOF:
                if avail - used < PROOF_BYTES:
                    return used, out
                proof = bytes(data[used : used + PROOF_BYTES])
                used += PROOF_BYTES
                out += self._proof_received(proof)
            else:
                return used, out

    def _hello_received(self, version: int, flags: int, max_frame: int, nonce: bytes) -> bytes:
        if version != PROTOCOL_VERSION:
            self._step = _FAILED
            raise TransportBrokenError(f"{self.peer} speaks uniros tcp version {version}, we speak {PROTOCOL_VERSION}")
        if bool(flags & FLAG_AUTH) != (self._key is not None):
            self._step = _FAILED
            if self._key is None:
                raise AuthenticationError(f"{self.peer} requires an auth_key and we have none")
            raise AuthenticationError(f"{self.peer} does not authenticate (no auth_key) but ours is set")
        self.peer_max_frame_bytes = max_frame
        self._peer_nonce = nonce
        if self._key is None:
            self._step = _DONE
            return b""
        self._step = _WANT_PROOF
        if self._listener:
            return _proof(self._key, _LISTENER_LABEL, nonce, self._nonce)
        return b""

    def _proof_received(self, proof: bytes) -> bytes:
        assert self._key is not None
        if self._listener:
            expected = _proof(self._key, _CLIENT_LABEL, self._peer_nonce, self._nonce)
            if not hmac.compare_digest(proof, expected):
                self._step = _FAILED
                raise AuthenticationError(f"{self.peer} failed to prove the shared auth_key")
            self._step = _DONE
            return b""
        expected = _proof(self._key, _LISTENER_LABEL, self._nonce, self._peer_nonce)
        if not hmac.compare_digest(proof, expected):
            self._step = _FAILED
            raise AuthenticationError(f"listener {self.peer} failed to prove the shared auth_key (keys differ)")
        self._step = _DONE
        return _proof(self._key, _CLIENT_LABEL, self._nonce, self._peer_nonce)
