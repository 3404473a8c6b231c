"""The Transport interface: a connection that moves whole frames, in order, between two endpoints.

A transport moves bytes; ``uniros_async.bus.codec`` turns messages into frames and the bus connects the two.
Every implementation passes ``uniros_async.testing.transport_contract`` (as trio's check_one_way_stream does for
streams). Implementations are chosen by URI scheme:

    memory://NAME           in-process (the reference implementation and test double)
    shm://NAME              same machine: shared-memory rings with eventfd wakeups
    tcp://HOST:PORT         network: length-prefixed frames over TCP (port 0: pick a free one)
    tls://HOST:PORT         network, encrypted: the same frames over mutual TLS (``tls_*`` options)

``listen(uri)`` returns a Listener whose ``uri`` is concrete (the chosen port or name) and whose ``accept()``
yields one Transport per peer; ``connect(uri)`` returns the peer's Transport.
"""

from __future__ import annotations

import abc
import contextlib
import ctypes
import dataclasses
import enum
import os
from collections.abc import AsyncIterator, Sequence
from types import TracebackType
from typing import Any, ClassVar, Self
from urllib.parse import urlsplit

from uniros_async.errors import ConfigError, FrameTooLargeError
from uniros_async.registry import Registry

__all__ = [
    "Buffer",
    "Delivery",
    "Listener",
    "Transport",
    "TransportOptions",
    "TransportStats",
    "connect",
    "frame_nbytes",
    "listen",
    "options_from_environ",
    "register_scheme",
    "split_uri",
]

Buffer = bytes | bytearray | memoryview
"""What ``send`` takes: one buffer, or a sequence of buffers sent as one frame without joining them first."""

DEFAULT_MAX_FRAME_BYTES = 64 * 1024 * 1024


def _cpu_getter() -> Any:
    try:
        getcpu = ctypes.CDLL(None, use_errno=True).sched_getcpu
        getcpu.restype, getcpu.argtypes = ctypes.c_int, []
        if getcpu() >= 0:
            return getcpu
    except (OSError, AttributeError):  # no such libc call here
        pass
    return lambda: -1


this_cpu = _cpu_getter()
"""The CPU this thread runs on now (glibc's sched_getcpu through ctypes: no syscall), or -1 where unknown."""


class Delivery(enum.Enum):
    """The guarantee of a transport."""

    RELIABLE = "reliable"
    """Every frame, in order, exactly once, or an error."""
    LATEST = "latest"
    """Frames may be dropped in favour of newer ones; those delivered are in order."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class TransportOptions:
    """Options every transport accepts (a transport ignores what does not apply to it, and says so in its doc).

    Attributes:
        max_frame_bytes: larger frames are refused by ``send`` (FrameTooLargeError) and, when announced by a
            peer, the connection is dropped and counted as a rejection without allocating the frame.
        auth_key: shared secret; when set, both ends prove knowledge of it (HMAC challenge-response) before any
            frame moves, and a peer that fails is rejected and counted. None disables authentication.
        connect_timeout_s: how long ``connect`` keeps trying (with exponential backoff) before TimeoutError.
        bind_host: for listeners on the network: the interface to bind (loopback unless told otherwise).
        ring_bytes: for shared memory: the capacity of each direction's ring.
        insecure: for listeners on the network: allow a non-loopback address without ``auth_key`` (and, for
            ``tls://``, without client certificates). Without it such a listener refuses to start.
        max_connections: for listeners on the network: connections open at once (handshaking, waiting for
            ``accept`` and accepted); a connection beyond it is closed at once, before any byte is read.
        max_handshakes: for listeners on the network: unfinished handshakes at once; a new connection beyond it
            evicts the oldest unfinished one if that has waited 1 s (a stranger holding connections open cannot
            lock peers out), else it is refused before the handshake (a burst of peers: ``connect`` retries).
        handshake_timeout_s: for listeners on the network: a peer that has not completed the handshake this long
            after connecting is dropped.
        tls_cert_file: for ``tls://``: this end's certificate chain (PEM).
        tls_key_file: for ``tls://``: this end's private key (PEM; None: in ``tls_cert_file``).
        tls_ca_file: for ``tls://``: the CA certificates the peer's certificate must chain to (PEM). Both ends
            require the other's certificate (mutual TLS).
    """

    max_frame_bytes: int = DEFAULT_MAX_FRAME_BYTES
    auth_key: bytes | None = None
    connect_timeout_s: float = 5.0
    bind_host: str = "127.0.0.1"
    ring_bytes: int = 4 * 1024 * 1024
    insecure: bool = False
    max_connections: int = 1024
    max_handshakes: int = 64
    handshake_timeout_s: float = 5.0
    tls_cert_file: str | None = None
    tls_key_file: str | None = None
    tls_ca_file: str | None = None

    def __post_init__(self) -> None:
        if self.max_frame_bytes <= 0:
            raise ConfigError(f"max_frame_bytes must be > 0, got {self.max_frame_bytes}")
        if self.connect_timeout_s <= 0:
            raise ConfigError(f"connect_timeout_s must be > 0, got {self.connect_timeout_s}")
        if self.auth_key is not None and not isinstance(self.auth_key, bytes | bytearray):
            raise ConfigError(f"auth_key must be bytes or None, got {type(self.auth_key).__name__}")
        if self.ring_bytes < 4096:
            raise ConfigError(f"ring_bytes must be >= 4096, got {self.ring_bytes}")
        if self.max_connections < 1 or self.max_handshakes < 1:
            raise ConfigError(
                f"max_connections and max_handshakes must be >= 1, got {self.max_connections}, {self.max_handshakes}"
            )
        if self.handshake_timeout_s <= 0:
            raise ConfigError(f"handshake_timeout_s must be > 0, got {self.handshake_timeout_s}")


AUTH_KEY_ENV = "UNIROS_AUTH_KEY"
"""The shared key ``options_from_environ`` reads: domains, nodes and ``uniros robot serve`` use it when no options
are given, so every process of one setup only needs the variable set."""


def options_from_environ() -> TransportOptions:
    """Default options, with ``auth_key`` from ``$UNIROS_AUTH_KEY`` when it is set and not empty."""
    key = os.environ.get(AUTH_KEY_ENV, "")
    return TransportOptions(auth_key=key.encode() if key else None)


@dataclasses.dataclass
class TransportStats:
    """Counters of one transport end (read them; the transport updates them)."""

    frames_sent: int = 0
    frames_received: int = 0
    bytes_sent: int = 0
    bytes_received: int = 0
    rejected: int = 0
    """Frames or peers refused: oversized, malformed, unauthenticated."""


class Transport(abc.ABC):
    """One end of a connection that moves whole frames.

    ``delivery`` states the guarantee. ``receive()`` returns a memoryview that stays valid until the next
    ``receive()`` on the same end (so shared memory can hand out a zero-copy view); copy what you keep longer.
    Both directions work at once; one task may send while another receives. Two concurrent ``send`` calls (or
    two ``receive`` calls) on one end are not allowed.
    """

    delivery: ClassVar[Delivery] = Delivery.RELIABLE
    scheme: ClassVar[str] = ""

    def __init__(self) -> None:
        self.stats = TransportStats()

    @property
    @abc.abstractmethod
    def peer(self) -> str:
        """A printable description of the other end (for logs and errors)."""

    @abc.abstractmethod
    async def send(self, frame: Buffer | Sequence[Buffer]) -> None:
        """Send one frame (a buffer, or buffers sent back to back as one frame).

        If cancelled, the frame may or may not have been sent, but the connection stays usable (no half frame).

        Raises:
            TransportClosedError: our own code closed this end.
            TransportBrokenError: the peer or the medium failed; ``__cause__`` holds the OSError.
            FrameTooLargeError: the frame is over ``max_frame_bytes``; nothing was sent, the connection stays.
        """

    @abc.abstractmethod
    async def receive(self) -> memoryview:
        """Wait for the next frame. Cancelling leaves no frame half-read.

        Raises:
            TransportClosedError: our own code closed this end.
            TransportBrokenError: the peer vanished or broke the protocol (EndOfStream-style clean close too:
                message "peer closed the connection").
        """

    @property
    def max_frame_bytes(self) -> int | None:
        """The largest frame ``send`` accepts on this end (None: not known before sending)."""
        return None

    def unsent_bytes(self) -> int:
        """Bytes of frames already sent that have not left this host yet: a send backlog, which grows when the
        medium is slower than the sender. 0 where the transport keeps none or cannot tell, and once the connection
        has ended."""
        return 0

    @contextlib.asynccontextmanager
    async def loan(self, nbytes: int) -> AsyncIterator[memoryview]:
        """A writable buffer for the next frame, ``nbytes`` long: write it in the block, and it is sent when the
        block ends (not if the block raises). A transport that can lend its own memory does (``shm``: the frame's
        place in the ring, so it is never copied); this default sends a buffer of its own (one copy, as ``send``).
        Nothing else may be sent on this end during the block; the view must not be used after it.

        Raises:
            as ``send``.
        """
        limit = self.max_frame_bytes
        if nbytes < 0 or (limit is not None and nbytes > limit):
            raise FrameTooLargeError(f"frame of {nbytes} bytes exceeds max_frame_bytes={limit}")
        buf = bytearray(nbytes)
        yield memoryview(buf)
        await self.send(buf)

    @abc.abstractmethod
    async def aclose(self) -> None:
        """Close this end; idempotent. A task blocked in ``receive`` or ``send`` gets TransportClosedError."""

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.aclose()


class Listener(abc.ABC):
    """Accepts connections; ``uri`` is the concrete address peers pass to ``connect``."""

    @property
    @abc.abstractmethod
    def uri(self) -> str:
        """The URI to connect to (with the port or name actually chosen)."""

    @abc.abstractmethod
    async def accept(self) -> Transport:
        """Wait for the next peer that completed the handshake (authentication included).

        Raises:
            TransportClosedError: the listener was closed.
        """

    @abc.abstractmethod
    async def aclose(self) -> None:
        """Stop listening and release names/ports/segments; idempotent. Accepted transports stay open."""

    @property
    def rejected(self) -> int:
        """Peers refused during the handshake (bad key, bad hello)."""
        return 0

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.aclose()


def frame_nbytes(frame: Buffer | Sequence[Buffer]) -> int:
    """Total size of a frame given as one buffer or a sequence of buffers."""
    if isinstance(frame, bytes | bytearray | memoryview):
        return memoryview(frame).nbytes
    return sum(memoryview(part).nbytes for part in frame)


# scheme -> the module of its transport, imported on first use so `memory://` users never import shm or tcp code
_SCHEMES = Registry[Any](
    "transport scheme",
    entry_points="module",
    describe=lambda entry: repr(getattr(entry, "__name__", entry)),
    note="register_scheme adds one",
)
for _scheme in ("memory", "shm", "tcp", "tls"):
    _SCHEMES.register(_scheme, f"uniros_async.transports.{_scheme}")


def register_scheme(scheme: str, module: str, *, override: bool = False) -> None:
    """Make ``scheme://`` URIs use ``module``, which must define ``async listen(uri, options)`` and
    ``async connect(uri, options)`` (see docs/howto/add-a-transport.md). Registering the same module again is a
    no-op.

    Raises:
        ConfigError: a malformed module name, or ``scheme`` is taken by another module and ``override`` is False.
    """
    _SCHEMES.register(scheme, module, override=override)


def split_uri(uri: str) -> tuple[str, str]:
    """Split ``scheme://rest`` and check the scheme is known.

    Raises:
        ConfigError: the URI has no scheme or an unknown one (the known ones are listed).
    """
    if "://" not in uri:
        raise ConfigError(
            f"transport URI {uri!r} has no scheme; expected one of {list(_SCHEMES.names())}, e.g. tcp://127.0.0.1:0"
        )
    scheme = urlsplit(uri).scheme
    if scheme not in _SCHEMES:
        raise _SCHEMES.unknown(scheme, message=f"unknown transport scheme {scheme!r} in {uri!r}")
    return scheme, uri.split("://", 1)[1]


def _module(uri: str) -> object:
    scheme, _ = split_uri(uri)
    return _SCHEMES.get(scheme)


async def listen(uri: str, options: TransportOptions | None = None) -> Listener:
    """Start listening at ``uri`` (``tcp://127.0.0.1:0``, ``shm://name``, ``memory://name``)."""
    mod = _module(uri)
    return await mod.listen(uri, options or TransportOptions())  # type: ignore[attr-defined, no-any-return]


async def connect(uri: str, options: TransportOptions | None = None) -> Transport:
    """Connect to a listener at ``uri``, retrying with backoff up to ``options.connect_timeout_s``.

    Raises:
        TimeoutError: nobody accepted within ``connect_timeout_s``.
        AuthenticationError: the listener refused our key (or we refused its proof).
    """
    mod = _module(uri)
    return await mod.connect(uri, options or TransportOptions())  # type: ignore[attr-defined, no-any-return]
