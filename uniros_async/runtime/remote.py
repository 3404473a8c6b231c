"""Workers on another host: the launcher (``uniros worker serve``) and the agent side's handle on what it started.

The agent side talks to workers over the project's own transports, shm on one machine and tcp
to a worker on another host. A spec is placed on a launcher with the ``worker`` keyword (never passed to the env)::

    make_vec([("uniros/Rx200Reach-v0", {"worker": "tcp://10.0.0.5:7000"}), "uniros/Ned2Reach-v0"])
    make("uniros/Ned2Reach-v0", worker=RemoteWorker("tcp://10.0.0.5:7000", auth_key=b"..."))

Protocol (msgpack frames of ``protocol.pack``, over one tcp connection per remote worker, HMAC-authenticated when the
launcher has a key): the agent sends ``{"op": "start", "index", "env_id", "kwargs", "start_timeout_s"}``; the
launcher checks the id and kwargs against its own registry (``check_env_args``), spawns a worker exactly as the
supervisor does (``worker_entry``, a ``WorkerSpec`` whose parent is the launcher), reads the worker's listen URI
from the start-up pipe and replies ``{"ok": True, "result": {"uri", "pid"}}`` (or ``{"ok": False, "error",
"type", "traceback"}``, and the connection is closed: a bad request never stops the launcher). The worker listens
on ``tcp://<the launcher's bind host>:0`` with the launcher's key; the agent connects to it directly and from then
on it is an ordinary worker (``supervisor.WorkerHandle``). The launcher connection stays open as the worker's
lifeline: the launcher sends ``{"event": "exited", "pid", "exitcode"}`` when the worker ends (the agent reads it
to say why a connection broke, and to join on close), and takes ``{"op": "terminate"}`` / ``{"op": "kill"}``.

Lifetime: a launched worker stops when its agent connection goes away (EOF on tcp, as on shm), when its launcher
connection goes away (the launcher gives it ``stop_timeout_s`` to leave on its own, then terminates and kills it),
when the launcher stops (terminate, then kill; every worker is reaped), and when the launcher dies (the worker's
parent-pid watchdog). A wildcard bind (``0.0.0.0``) is answered with the host the agent used to reach the
launcher. Not handled: a host that vanishes without closing its sockets (no TCP keepalive; the call timeout
still bounds every wait on the agent side).

A launched worker listens on tcp with the launcher's key (``WorkerSpec.auth_key``).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import multiprocessing
import multiprocessing.connection
import os
import select
import signal
from collections.abc import AsyncIterator, Callable
from typing import Any
from urllib.parse import urlsplit

import numpy as np

from uniros_async._signals import cancel_on_signals
from uniros_async.bus.codec import encode_plain
from uniros_async.errors import CodecError, ConfigError, TransportError, WorkerError
from uniros_async.runtime.protocol import error_reply, pack, unpack
from uniros_async.runtime.worker import WorkerSpec, worker_entry
from uniros_async.transports.base import Transport, TransportOptions
from uniros_async.transports.tcp import TcpTransport

__all__ = [
    "AUTH_KEY_ENV",
    "Launcher",
    "RemoteWorker",
    "RemoteWorkerProcess",
    "parse_placement",
    "run_launcher",
    "serve_launcher",
]

logger = logging.getLogger(__name__)

AUTH_KEY_ENV = "UNIROS_WORKER_AUTH_KEY"
"""The environment variable both sides read the shared key from by default (``uniros worker serve`` and a
``worker="tcp://..."`` given as a plain string)."""

_WILDCARD_HOSTS = {"0.0.0.0", "::", ""}


def _key_bytes(key: Any, what: str) -> bytes | None:
    if key is None or isinstance(key, bytes):
        return key
    if isinstance(key, bytearray):
        return bytes(key)
    if isinstance(key, str):
        return key.encode()
    raise ConfigError(f"{what} must be bytes, str or None, got {type(key).__name__}")


def _tcp_host_port(uri: str, what: str) -> tuple[str, int]:
    if not isinstance(uri, str) or not uri.startswith("tcp://"):
        raise ConfigError(f"{what} must be a tcp://HOST:PORT URI, got {uri!r}")
    parts = urlsplit(uri)
    try:
        port = parts.port
    except ValueError:
        port = None
    if not parts.hostname or not port or parts.path not in ("", "/"):
        raise ConfigError(f"{what} must be tcp://HOST:PORT with a host and a nonzero port, got {uri!r}")
    return parts.hostname, port


def _format_uri(host: str, port: int) -> str:
    return f"tcp://[{host}]:{port}" if ":" in host else f"tcp://{host}:{port}"


@dataclasses.dataclass(frozen=True)
class RemoteWorker:
    """Where a spec's worker runs: a launcher (``uniros worker serve``), usually on another host.

    Attributes:
        uri: the launcher's ``tcp://HOST:PORT``.
        auth_key: the launcher's shared key (str or bytes); None: ``$UNIROS_WORKER_AUTH_KEY`` when set, else none.
        connect_timeout_s: how long to keep trying to reach the launcher before WorkerError.
    """

    uri: str
    auth_key: bytes | None = None
    connect_timeout_s: float = 5.0

    def __post_init__(self) -> None:
        _tcp_host_port(self.uri, "worker")
        key = _key_bytes(self.auth_key, "worker auth_key")
        if key is None and os.environ.get(AUTH_KEY_ENV):
            key = os.environ[AUTH_KEY_ENV].encode()
        object.__setattr__(self, "auth_key", key or None)
        if not self.connect_timeout_s > 0:
            raise ConfigError(f"connect_timeout_s must be > 0, got {self.connect_timeout_s}")

    @property
    def host(self) -> str:
        return _tcp_host_port(self.uri, "worker")[0]

    def __repr__(self) -> str:  # never print the key
        return f"RemoteWorker({self.uri!r}, auth_key={'***' if self.auth_key else None})"


def parse_placement(value: Any) -> RemoteWorker | None:
    """The ``worker`` keyword of a spec: None (a local worker), a launcher URI ``"tcp://HOST:PORT"``, a
    ``RemoteWorker``, or a mapping of its fields (for YAML configs).

    Raises:
        ConfigError: anything else, or a malformed URI.
    """
    if value is None or isinstance(value, RemoteWorker):
        return value
    if isinstance(value, str):
        return RemoteWorker(value)
    if isinstance(value, dict):
        unknown = set(value) - {"uri", "auth_key", "connect_timeout_s"}
        if unknown or "uri" not in value:
            raise ConfigError(
                f"worker mapping needs 'uri' (and optionally auth_key, connect_timeout_s), got {sorted(value)}"
            )
        return RemoteWorker(**value)
    raise ConfigError(f"worker must be None, a launcher URI tcp://HOST:PORT or a RemoteWorker, got {value!r:.80}")


def _strict_default(value: Any) -> Any:
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    if isinstance(value, tuple):
        return list(value)
    raise TypeError(f"{type(value).__name__} is not plain data")


def check_plain(kwargs: dict[str, Any], env_id: str) -> None:
    """ConfigError unless ``kwargs`` can travel to a launcher as plain data (no pickles cross the wire)."""
    for k, v in kwargs.items():
        try:
            encode_plain(v, _strict_default)
        except CodecError as exc:
            raise ConfigError(
                f"{env_id}: keyword {k!r} cannot be sent to a remote worker ({exc}); use plain data"
            ) from None


# ---------------------------------------------------------------- the agent side


class RemoteWorkerProcess:
    """Stands in for ``multiprocessing.Process`` for a worker a launcher started: ``pid`` (on the launcher's host),
    ``exitcode`` (as the launcher reported it) and ``is_alive()``; the coroutines run on the supervisor's loop."""

    def __init__(self, placement: RemoteWorker) -> None:
        self.placement = placement
        self.pid: int | None = None
        self.exitcode: int | None = None
        self.worker_uri = ""
        self.launcher_lost: str | None = None  # why the launcher connection ended without an exit report
        self._control: Transport | None = None
        self._fd = -1  # the launcher connection's socket, for ``lifeline_has_news``

    def where(self) -> str:
        return f"pid {self.pid} via launcher {self.placement.uri}"

    def is_alive(self) -> bool:
        return self.pid is not None and self.exitcode is None and self.launcher_lost is None

    async def start(self, index: int, env_id: str, kwargs: dict[str, Any], timeout_s: float) -> str:
        """Ask the launcher for a worker; returns the worker's URI (a wildcard host replaced by the launcher's).

        Raises:
            ConfigError: the launcher refused the env id or kwargs (its registry decides).
            WorkerError: the launcher is unreachable, refused the key or the request, or the worker did not start.
        """
        from uniros_async.transports.base import connect

        p = self.placement
        where = f"launcher {p.uri}"
        connect_s = max(0.1, min(p.connect_timeout_s, timeout_s))
        options = TransportOptions(auth_key=p.auth_key, connect_timeout_s=connect_s)
        try:
            self._control = await connect(p.uri, options)
        except TimeoutError as exc:
            raise WorkerError(index, f"{env_id}: {where} is unreachable: {exc}") from exc
        except Exception as exc:  # noqa: BLE001 - AuthenticationError, TransportError, OSError
            hint = " (the auth keys differ: see --auth-key-env and $UNIROS_WORKER_AUTH_KEY)"
            why = f"{type(exc).__name__}: {exc}{hint if 'key' in str(exc) else ''}"
            raise WorkerError(index, f"{env_id}: {where} refused the connection: {why}") from exc
        request = {"op": "start", "index": index, "env_id": env_id, "kwargs": kwargs, "start_timeout_s": timeout_s}
        try:
            async with asyncio.timeout(timeout_s):
                await self._control.send(pack(request))
                reply = unpack(await self._control.receive())
        except TimeoutError:
            raise WorkerError(index, f"{env_id}: {where} did not start the worker within {timeout_s} s") from None
        except TransportError as exc:
            raise WorkerError(index, f"{env_id}: {where} closed the connection before answering: {exc}") from exc
        if not reply.get("ok"):
            message = f"{env_id}: {where} refused: {reply.get('error')}"
            if reply.get("type") == "ConfigError":
                raise ConfigError(f"worker {index}: {message}")
            raise WorkerError(index, message, remote_traceback=str(reply.get("traceback", "")))
        result = reply["result"]
        self._fd = self._control.fileno() if isinstance(self._control, TcpTransport) else -1
        self.pid = int(result["pid"])
        host, port = _tcp_host_port(str(result["uri"]), "worker URI")
        self.worker_uri = _format_uri(p.host if host in _WILDCARD_HOSTS else host, port)
        return self.worker_uri

    def lifeline_has_news(self) -> bool:
        """Whether the launcher connection holds anything unread (the exit report, or the launcher's EOF): then the
        worker has ended or is about to (its launcher died, and its watchdog follows). Checked before every request
        to a remote worker (~2 us: a zero-timeout select), so a dead launcher fails the very next step instead of
        the one after the worker's watchdog fired. Reads the TcpTransport's own state first: once the event loop
        has taken the data (or the EOF closed the socket), the socket says nothing any more."""
        control = self._control
        if control is None:
            return self.exitcode is not None or self.launcher_lost is not None
        if isinstance(control, TcpTransport) and control.has_news():
            return True
        if self._fd < 0:
            return False
        try:
            return bool(select.select([self._fd], [], [], 0)[0])
        except (OSError, ValueError):
            return True

    async def poll_exit(self, timeout_s: float) -> int | None:
        """Wait at most ``timeout_s`` for the launcher's report that the worker ended; its exit code, or None."""
        control = self._control
        if self.exitcode is not None or control is None or self.launcher_lost is not None:
            return self.exitcode
        try:
            async with asyncio.timeout(max(0.0, timeout_s)):
                while self.exitcode is None:
                    msg = unpack(await control.receive())
                    if msg.get("event") == "exited":
                        code = msg.get("exitcode")
                        self.exitcode = int(code) if code is not None else -1
        except TimeoutError:
            pass
        except TransportError as exc:
            self.launcher_lost = f"its launcher {self.placement.uri} is gone ({exc})"
        except Exception as exc:  # noqa: BLE001 - a malformed frame: the lifeline is useless from here on
            self.launcher_lost = f"its launcher {self.placement.uri} sent a malformed message ({exc})"
        return self.exitcode

    async def stop(self, timeout_s: float, *, asked: bool) -> None:
        """Make sure the worker ends: wait ``timeout_s`` for it (if it was ``asked`` to close), else have the launcher
        terminate it, then kill it; close the launcher connection. Bounded by about 2 x ``timeout_s`` + 1 s."""
        try:
            if self._control is None or self.pid is None:
                return
            if asked:
                await self.poll_exit(timeout_s)
            for op, wait_s in (("terminate", timeout_s), ("kill", 1.0)):
                if self.exitcode is not None or self.launcher_lost is not None:
                    break
                try:
                    async with asyncio.timeout(1.0):
                        await self._control.send(pack({"op": op}))
                except (TransportError, TimeoutError) as exc:
                    self.launcher_lost = f"its launcher {self.placement.uri} is gone ({exc})"
                    break
                await self.poll_exit(wait_s)
        finally:
            await self.aclose()

    async def aclose(self) -> None:
        self._fd = -1
        control, self._control = self._control, None
        if control is not None:
            await control.aclose()


# ---------------------------------------------------------------- the launcher


@dataclasses.dataclass(eq=False)
class _Launched:
    process: multiprocessing.process.BaseProcess
    conn: multiprocessing.connection.Connection
    env_id: str
    uri: str = ""  # where the worker listens
    exited: asyncio.Event = dataclasses.field(default_factory=asyncio.Event)


class Launcher:
    """Starts env workers for agents on other hosts (see the module docstring); ``serve_launcher`` runs one.

    Args:
        uri: where to listen, ``tcp://HOST:PORT`` (port 0: a free one; ``uri`` then reports it).
        auth_key: shared key agents must prove (HMAC); None: no authentication.
        max_workers: refuse to start more than this many workers at once (None: no limit).
        start_timeout_s: upper bound on a worker's start (the agent's own, smaller, bound applies first).
        request_timeout_s: how long a new connection has to send its request.
        stop_timeout_s: how long a worker whose agent left gets to exit on its own, and how long after terminate
            before kill.
    """

    def __init__(
        self,
        uri: str = "tcp://127.0.0.1:0",
        *,
        auth_key: bytes | str | None = None,
        max_workers: int | None = None,
        start_timeout_s: float = 120.0,
        request_timeout_s: float = 10.0,
        stop_timeout_s: float = 3.0,
    ) -> None:
        if not isinstance(uri, str) or not uri.startswith("tcp://"):
            raise ConfigError(f"the launcher listens on tcp://HOST:PORT, got {uri!r}")
        if max_workers is not None and max_workers < 1:
            raise ConfigError(f"max_workers must be >= 1 or None, got {max_workers}")
        self._listen_uri = uri
        self._key = _key_bytes(auth_key, "auth_key") or None
        self.max_workers = max_workers
        self.start_timeout_s = start_timeout_s
        self.request_timeout_s = request_timeout_s
        self.stop_timeout_s = stop_timeout_s
        self._listener: Any = None
        self._workers: set[_Launched] = set()
        self._next_index = 0

    @property
    def uri(self) -> str:
        """The URI agents connect to (the bound port; a wildcard host stays a wildcard)."""
        return str(self._listener.uri) if self._listener is not None else self._listen_uri

    def worker_pids(self) -> list[int]:
        """The pids of the workers running now."""
        return [w.process.pid for w in self._workers if w.process.pid is not None and not w.exited.is_set()]

    async def start(self) -> None:
        """Bind the listening socket (and import the env registry, so the first request is quick).

        Raises:
            OSError: the address cannot be bound.
        """
        from uniros_async.transports.base import listen as listen_uri

        self._listener = await listen_uri(self._listen_uri, TransportOptions(auth_key=self._key))
        host = self._listener.address[0]
        if self._key is None and host not in ("127.0.0.1", "::1", "localhost"):
            logger.warning(
                "worker launcher %s has no auth key: anyone who can reach it can start workers (set $%s)",
                self.uri,
                AUTH_KEY_ENV,
            )
        await asyncio.to_thread(_warm_registry)

    async def serve(self) -> None:
        """Accept agents until cancelled; then stop every worker (terminate, kill, reap) and close the listener."""
        if self._listener is None:
            await self.start()
        try:
            async with asyncio.TaskGroup() as tg:
                while True:
                    transport = await self._listener.accept()
                    tg.create_task(self._handle(transport))
        finally:
            await self.aclose()

    async def aclose(self) -> None:
        """Close the listener and stop every worker still running; idempotent, bounded."""
        if self._listener is not None:
            await self._listener.aclose()
        workers = list(self._workers)
        await asyncio.gather(*(self._stop(w, grace_s=0.0) for w in workers), return_exceptions=True)
        for w in workers:  # the backstop: nothing outlives the launcher
            if w.process.is_alive():
                w.process.kill()
                w.process.join(1.0)

    # ---- one agent connection = one worker

    async def _handle(self, transport: Transport) -> None:
        peer = transport.peer
        w: _Launched | None = None
        try:
            try:
                async with asyncio.timeout(self.request_timeout_s):
                    request = unpack(await transport.receive())
                w = await self._launch(request, peer)
            except TransportError:
                return
            except Exception as exc:  # noqa: BLE001 - a bad request: say so, keep serving
                logger.warning("worker launcher: refused a request from %s: %s", peer, exc)
                with contextlib.suppress(TransportError, TimeoutError):
                    async with asyncio.timeout(2.0):
                        await transport.send(pack(error_reply(exc, "could not start a worker")))
                return
            async with asyncio.timeout(5.0):
                await transport.send(pack({"ok": True, "result": {"uri": w.uri, "pid": w.process.pid}}))
            await self._supervise(w, transport)
        except (TransportError, TimeoutError):
            pass
        except Exception:  # a failure in one connection must never end the launcher (a TaskGroup child)
            logger.exception("worker launcher: the connection from %s failed", peer)
        finally:
            if w is not None:  # the agent left: the worker gets a moment to see its own EOF; shutting down: none
                task = asyncio.current_task()
                cancelled = task is not None and task.cancelling() > 0
                await self._stop(w, grace_s=0.0 if cancelled else self.stop_timeout_s)
                if cancelled and w.exited.is_set():  # the launcher stops: tell the agent what became of its worker
                    with contextlib.suppress(TransportError, TimeoutError):
                        async with asyncio.timeout(1.0):
                            exitcode = w.process.exitcode
                            await transport.send(pack({"event": "exited", "pid": w.process.pid, "exitcode": exitcode}))
            await transport.aclose()

    async def _launch(self, request: dict[str, Any], peer: str) -> _Launched:
        from uniros_async.runtime.envargs import check_env_args

        if request.get("op") != "start":
            op = request.get("op")
            raise ConfigError(f"expected a start request {{'op': 'start', 'env_id': ...}}, got op {op!r}")
        env_id, kwargs = request.get("env_id"), request.get("kwargs", {})
        if not isinstance(env_id, str) or not isinstance(kwargs, dict):
            raise ConfigError(f"expected env_id: str and kwargs: map, got {env_id!r:.80} and {kwargs!r:.80}")
        if "worker" in kwargs:
            raise ConfigError("a launcher does not forward workers to other launchers ('worker' in kwargs)")
        await asyncio.to_thread(check_env_args, env_id, kwargs)
        # no await from this check to self._workers.add below: concurrent requests cannot both pass it
        if self.max_workers is not None and len(self._workers) >= self.max_workers:
            n = self.max_workers
            raise RuntimeError(f"the launcher runs {n} workers already (--max-workers {n})")
        timeout_s = min(float(request.get("start_timeout_s") or self.start_timeout_s), self.start_timeout_s)
        index = request.get("index")
        index = int(index) if isinstance(index, int) else self._next_index
        self._next_index += 1
        host = self._listener.address[0]
        listen_uri = f"tcp://[{host}]:0" if ":" in host else f"tcp://{host}:0"
        spec = WorkerSpec(
            index=index,
            env_id=env_id,
            kwargs=kwargs,
            parent_pid=os.getpid(),
            accept_timeout_s=timeout_s,
            listen_uri=listen_uri,
            auth_key=self._key,
        )
        ctx = multiprocessing.get_context("spawn")
        parent_conn, child_conn = ctx.Pipe(duplex=False)
        # daemon=True: if the launcher exits, multiprocessing terminates its workers (a SIGKILLed launcher is
        # noticed by each worker's parent-pid watchdog)
        proc = ctx.Process(
            target=worker_entry,
            args=(spec, child_conn),
            name=f"uniros-worker-{index}",
            daemon=True,
        )
        proc.start()
        child_conn.close()
        w = _Launched(process=proc, conn=parent_conn, env_id=env_id)
        self._workers.add(w)
        loop = asyncio.get_running_loop()
        loop.add_reader(proc.sentinel, self._on_exit, w)
        logger.info("worker launcher: started %s (pid %d) for %s", env_id, proc.pid, peer)
        try:
            w.uri = await self._read_uri(w, timeout_s)
        except BaseException:
            await self._stop(w, grace_s=0.0)
            raise
        return w

    def _on_exit(self, w: _Launched) -> None:
        with contextlib.suppress(Exception):
            asyncio.get_running_loop().remove_reader(w.process.sentinel)
        w.process.join(0.5)  # reap
        w.exited.set()

    async def _read_uri(self, w: _Launched, timeout_s: float) -> str:
        async with asyncio.timeout(timeout_s):
            while not w.conn.poll():
                if w.exited.is_set():
                    raise RuntimeError(
                        f"the worker for {w.env_id} exited with code {w.process.exitcode} at start (see the launcher's "
                        "stderr)"
                    )
                await asyncio.sleep(0.02)
        try:
            return str(w.conn.recv())
        except EOFError:
            raise RuntimeError(f"the worker for {w.env_id} exited at start (see the launcher's stderr)") from None
        finally:
            w.conn.close()

    async def _supervise(self, w: _Launched, transport: Transport) -> None:
        """Until the worker exits (then report it) or the agent's launcher connection ends (then stop it)."""

        async def read_control() -> None:
            while True:
                msg = unpack(await transport.receive())
                op = msg.get("op")
                if op == "terminate" and not w.exited.is_set():
                    w.process.terminate()
                elif op == "kill" and not w.exited.is_set():
                    w.process.kill()

        reader = asyncio.get_running_loop().create_task(read_control())
        exited = asyncio.get_running_loop().create_task(w.exited.wait())
        try:
            await asyncio.wait({reader, exited}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for t in (reader, exited):
                t.cancel()
            await asyncio.gather(reader, exited, return_exceptions=True)
        if w.exited.is_set():
            async with asyncio.timeout(2.0):
                await transport.send(pack({"event": "exited", "pid": w.process.pid, "exitcode": w.process.exitcode}))

    async def _stop(self, w: _Launched, *, grace_s: float) -> None:
        """Give the worker ``grace_s`` to exit by itself, then terminate, then kill; reap it. Bounded."""
        try:
            for action, wait_s in ((None, grace_s), ("terminate", self.stop_timeout_s), ("kill", 1.0)):
                if w.exited.is_set():
                    break
                if action == "terminate":
                    w.process.terminate()
                elif action == "kill":
                    w.process.kill()
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(wait_s):
                        await w.exited.wait()
        finally:
            if not w.exited.is_set():
                self._on_exit(w)
            if not w.conn.closed:
                w.conn.close()
            self._workers.discard(w)


def _warm_registry() -> None:
    from uniros_async.tasks.registry import register_envs

    register_envs()


@contextlib.asynccontextmanager
async def serve_launcher(uri: str = "tcp://127.0.0.1:0", **kwargs: Any) -> AsyncIterator[Launcher]:
    """Run a ``Launcher`` (same arguments) on the running loop for the ``async with`` block; on exit every worker
    it started is stopped and reaped, and the port is free."""
    launcher = Launcher(uri, **kwargs)
    await launcher.start()
    task = asyncio.get_running_loop().create_task(launcher.serve())
    try:
        yield launcher
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        await launcher.aclose()


def run_launcher(
    uri: str = "tcp://0.0.0.0:7000",
    *,
    auth_key: bytes | str | None = None,
    max_workers: int | None = None,
    ready: Callable[[Launcher], None] | None = None,
) -> None:
    """Run a launcher until SIGTERM or SIGINT (``uniros worker serve``); ``ready`` is called once it listens."""

    async def main() -> None:
        cancel_on_signals(signal.SIGTERM, signal.SIGINT)
        launcher = Launcher(uri, auth_key=auth_key, max_workers=max_workers)
        await launcher.start()
        if ready is not None:
            ready(launcher)
        await launcher.serve()

    with contextlib.suppress(asyncio.CancelledError, KeyboardInterrupt):
        asyncio.run(main())
