"""The control socket of ``shm://NAME``: an abstract Unix SOCK_SEQPACKET socket (``"\\0uniros-shm-NAME"``), on which
a listener admits peers through the handshake (``_shm_handshake``) in the background and a peer connects, retrying
with backoff until the name listens. Each admitted connection becomes a ``ShmTransport`` (``shm.listen`` and
``shm.connect`` pass the class)."""

from __future__ import annotations

import asyncio
import errno
import logging
import os
import secrets
import socket
from typing import Generic, Protocol, TypeVar

from uniros_async.backoff import Backoff
from uniros_async.errors import ConfigError, TransportBrokenError, TransportClosedError
from uniros_async.transports import _shm_handshake
from uniros_async.transports.base import Listener, Transport, TransportOptions, split_uri

_T = TypeVar("_T", bound=Transport)
_T_co = TypeVar("_T_co", bound=Transport, covariant=True)


class ShmEnd(Protocol[_T_co]):
    """What makes one end over a finished handshake: ``shm.ShmTransport`` (its class), passed in so that this
    module knows nothing of the ring it maps."""

    def __call__(
        self, *, name: str, sock: socket.socket, setup: _shm_handshake.Setup, options: TransportOptions
    ) -> _T_co: ...


__all__ = ["ShmEnd", "ShmListener", "open_shm_connection", "open_shm_listener", "open_transport"]

_ADDRESS_PREFIX = "\0uniros-shm-"
_MAX_NAME_BYTES = 100  # sun_path holds 108 bytes, the prefix included

logger = logging.getLogger("uniros_async.transports.shm")


class ShmListener(Listener, Generic[_T]):
    """Accepts ``shm://NAME`` connections on an abstract Unix socket; handshakes run in the background."""

    def __init__(self, name: str, sock: socket.socket, options: TransportOptions, transport_class: ShmEnd[_T]) -> None:
        self._name = name
        self._transport_class = transport_class
        self._sock = sock
        self._options = options
        self._ready: asyncio.Queue[_T | None] = asyncio.Queue()
        self._rejected = 0
        self._closed = False
        self._serving = asyncio.get_running_loop().create_task(self._serve(), name=f"shm://{name} listener")

    @property
    def uri(self) -> str:
        return f"shm://{self._name}"

    @property
    def rejected(self) -> int:
        return self._rejected

    async def accept(self) -> Transport:
        if self._closed:
            raise TransportClosedError(f"listener {self.uri} is closed")
        t = await self._ready.get()
        if t is None:
            self._ready.put_nowait(None)  # for the next waiter
            raise TransportClosedError(f"listener {self.uri} is closed")
        return t

    async def aclose(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._serving.cancel()
        await asyncio.wait({self._serving})
        self._sock.close()
        while not self._ready.empty():
            t = self._ready.get_nowait()
            if t is not None:
                await t.aclose()  # never accepted: its peer sees a closed connection
        self._ready.put_nowait(None)

    async def _serve(self) -> None:
        loop = asyncio.get_running_loop()
        async with asyncio.TaskGroup() as tg:
            while True:
                try:
                    conn, _ = await loop.sock_accept(self._sock)
                except OSError as exc:  # e.g. EMFILE: keep serving once descriptors free up
                    logger.warning("accept on %s failed: %s", self.uri, exc)
                    await asyncio.sleep(0.1)
                    continue
                conn.setblocking(False)
                tg.create_task(self._admit(conn))

    async def _admit(self, conn: socket.socket) -> None:
        """Handshake with one peer; never raises (a failure is counted and the peer dropped)."""
        try:
            async with asyncio.timeout(self._options.connect_timeout_s):
                setup = await _shm_handshake.admit(conn, self._options)
            t = open_transport(self._transport_class, self._name, conn, setup, self._options)
        except asyncio.CancelledError:
            conn.close()
            raise
        except Exception as exc:  # whatever a peer sends must not stop the listener
            self._rejected += 1
            logger.info("%s rejected a peer: %s", self.uri, exc)
            conn.close()
            return
        self._ready.put_nowait(t)


def open_transport(
    cls: ShmEnd[_T], name: str, sock: socket.socket, setup: _shm_handshake.Setup, options: TransportOptions
) -> _T:
    """A ``cls`` end over a finished handshake's ``setup``; on failure its descriptors and mapping are closed."""
    try:
        return cls(name=name, sock=sock, setup=setup, options=options)
    except BaseException:
        os.close(setup.doorbell_fd)
        os.close(setup.peer_doorbell_fd)
        setup.mm.close()
        raise


def _name(uri: str) -> str:
    scheme, name = split_uri(uri)
    if scheme != "shm":
        raise ConfigError(f"expected an shm:// URI, got {uri!r}")
    if "\0" in name or len(name.encode()) > _MAX_NAME_BYTES:
        raise ConfigError(f"shm name {name!r} must be at most {_MAX_NAME_BYTES} bytes without NUL")
    return name


async def open_shm_listener(uri: str, options: TransportOptions, cls: ShmEnd[_T]) -> ShmListener[_T]:
    """``shm.listen`` for ``cls``."""
    name = _name(uri) or f"{os.getpid()}-{secrets.token_hex(6)}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    try:
        sock.bind(_ADDRESS_PREFIX + name)
        sock.listen(socket.SOMAXCONN)
        sock.setblocking(False)
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            raise ConfigError(f"shm://{name} is already listening on this machine") from exc
        raise
    return ShmListener(name, sock, options, cls)


async def open_shm_connection(uri: str, options: TransportOptions, cls: ShmEnd[_T]) -> _T:
    """``shm.connect`` for ``cls``."""
    name = _name(uri)
    if not name:
        raise ConfigError(f"connect needs a name: shm://NAME, got {uri!r}")
    loop = asyncio.get_running_loop()
    backoff = Backoff(first_s=0.001, max_s=0.1)
    async with asyncio.timeout(options.connect_timeout_s):
        while True:
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            sock.setblocking(False)
            try:
                await loop.sock_connect(sock, _ADDRESS_PREFIX + name)
                break
            except (ConnectionRefusedError, FileNotFoundError, BlockingIOError):
                sock.close()
            except BaseException:
                sock.close()
                raise
            await backoff.sleep()
        try:
            setup = await _shm_handshake.join(sock, name, options)
            return open_transport(cls, name, sock, setup, options)
        except OSError as exc:
            sock.close()
            raise TransportBrokenError(f"handshake with shm://{name} failed: {exc}") from exc
        except BaseException:
            sock.close()
            raise
