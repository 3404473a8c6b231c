"""The supervisor: starts env workers, talks to them over shm, turns their failures into WorkerError.

The agent side is synchronous (gymnasium), the transports are asyncio: the supervisor has a private event loop
that the calling thread runs itself, only for the duration of each call (``loop.run_until_complete``): nothing on
the agent side needs to run between calls (replies wait in the shm rings, a dead worker's hang-up in its socket),
and a call then costs no hand-over to another thread (~16 us of loop start/stop instead of ~300 us of thread
wake-ups and GIL hand-offs). Calls from several threads are serialised by a lock. ``submit_steps`` sends requests
and returns at once; the replies are collected by ``_Pending.result``. A step does not run the loop at all: the
requests go out with the transport's ``try_send`` and the replies come in with its ``receive_blocking`` (shm and
tcp, local and Ray-placed workers), in the calling thread (``send_steps_now``, ``receive_steps_now`` and
``_take_replies``); whatever that cannot do (no room, a hang-up, a deadline, a Ray actor's news of its worker)
is left to the loop, which also reports it.
Every wait on a worker has a deadline; a worker that does not answer in time, whose connection breaks or whose
process died is marked broken and every later request to it raises WorkerError naming its index. A call
interrupted by Ctrl-C while the loop waits is finished (its replies consumed) before the next call; one
interrupted inside a request's own code marks that worker broken, since its next reply could no longer be matched
to a request.

Start-up: the local workers' interpreters are started first (``launch.start_interpreter``: ``python -m
uniros_async.runtime``, which imports nothing of the agent's ``__main__``) and import what every worker needs while
the env ids and keyword arguments are checked here; once every check passed, each is sent its spec (a failed check
stops them before any has one); then each worker's listen URI (``shm://`` by default, ``tcp://127.0.0.1:0`` with
``transport="tcp"``) is read from its start-up pipe (the only use of a pipe), the supervisor connects to all of
them and asks each for its spaces, in parallel.
If any worker fails to start, all are closed and the error names the worker and why.

Workers placed by Ray: a spec whose ``worker`` is a Ray placement (``"ray"``, ``{"ray": {...}}``, a
``ray_backend.RayPlacement``) is started instead of ``_spawn`` by a Ray actor on the node Ray's scheduler picks
(runtime/ray_backend.py); the actor answers with the worker's URI and the supervisor connects to it directly, as
to a local one. Its ``process`` is a ``RayWorkerProcess`` (pid and exit code as the actor reports them); a broken
connection is reported with the exit code the actor saw, ``restart`` starts the new worker through Ray with the
same placement, and ``close`` has the actor terminate and kill what does not exit by itself. The placements are
checked against the cluster's nodes before any worker starts, and the workers of one supervisor share a random key
(tcp or shm with HMAC). Local and Ray-placed workers mix freely.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import dataclasses
import functools
import logging
import multiprocessing.connection
import os
import secrets
import select
import socket
import threading
import time
from collections.abc import Callable, Coroutine, Sequence
from typing import Any, Generic, NoReturn, TypeVar

import gymnasium as gym

from uniros_async.errors import ConfigError, TransportError, WorkerError
from uniros_async.priority import MAX_LOOP_RANK
from uniros_async.runtime.envargs import check_env_args, registration, split_placement
from uniros_async.runtime.launch import WorkerProcess, found_libraries, start_interpreter, start_worker
from uniros_async.runtime.protocol import STEP_TAG, PackedRequest, pack, unpack
from uniros_async.runtime.ray_backend import RayPlacement, RayWorkerProcess, check_placements
from uniros_async.runtime.worker import WorkerSpec, cores_shared, shared_cores_mode

__all__ = ["Supervisor", "WorkerHandle"]

logger = logging.getLogger(__name__)

T = TypeVar("T")
Member = tuple[int, str, dict[str, Any], int]
"""One env of a worker process: ``(index, env_id, kwargs, rt_rank)``."""
_HANG_UP = getattr(select, "POLLRDHUP", 0x2000)  # poll(2): the peer closed its end (POLLHUP, POLLERR: always reported)
_HANG_UP_REPORT_S = 0.5
"""How long the report of a hung-up worker may take (its connection's end, then its actor's report of the exit,
``RayWorkerProcess.poll_exit``); a few milliseconds when its actor still answers."""
REPLY_SPIN_NS = 200_000
"""How long the supervisor polls for a reply before it sleeps (``ShmTransport.spin_ns``): a worker takes ~60 us to
unpack a request, step a trivial env and pack the reply, longer than the transport's default window, so the agent
would sleep and pay a wake-up (~30 us) on every step. The agent's thread has nothing else to do meanwhile, and the
spin credit stops the polling when replies take longer (a 10 Hz env's step). Not for workers with a real-time env
loop: there the acting thread may run SCHED_RR above the workers, and its poll would keep a lower-ranked worker
from the very reply it waits for; their connections keep the transport's default. Nor when the workers outnumber
the cores (``worker.cores_shared``): the replies then come one core's share of the physics apart, a poll seldom
catches one, and while it polls a worker waiting for that core's turn does not run; that holds for workers that
a Ray node on the agent's own machine runs too (its address is one of this machine's: ``_local_address``)."""
Request = dict[str, Any] | PackedRequest
"""A request to a worker: a message, or a step request already packed (``worker.pack_step_request``)."""
StepDecoder = Callable[[int, memoryview], Any]
"""``decode(worker index, step reply frame)``: what a step's reply becomes when taken in the calling thread (see
``WorkerHandle.receive_reply_blocking``); reads the frame before it returns (the ring reuses its bytes)."""
LATER: Any = object()
"""``WorkerHandle.receive_reply_blocking``: no reply this way; ``receive_reply`` must follow."""

# how the supervisor reaches its workers: shared memory on one machine (the default), or tcp on loopback
_LISTEN_URIS = {"shm": "shm://", "tcp": "tcp://127.0.0.1:0"}


@dataclasses.dataclass
class WorkerHandle:
    """The supervisor's side of one worker."""

    spec: WorkerSpec
    process: WorkerProcess | RayWorkerProcess
    conn: Any = None  # the start-up pipe end (None for a Ray-placed worker)
    transport: Any = None
    broken: str | None = None
    info: dict[str, Any] = dataclasses.field(default_factory=dict)
    in_flight: bool = False  # a request was sent and its reply not yet taken
    try_send: Any = None  # the transport's try_send and receive_blocking where it has them (shm, tcp), else None
    receive_blocking: Any = None
    hangup_fd: int = -1  # a Ray-placed worker's tcp socket, watched for a hang-up while another reply is awaited
    group: tuple[int, ...] = ()
    """The indices of the envs its process hosts, in the order they listen (``make_vec(envs_per_worker=...)``):
    stopped, restarted and pinned together."""

    def __post_init__(self) -> None:
        if not self.group:
            self.group = (self.spec.index,)

    def check_idle(self) -> None:
        """Raise AlreadyPendingCallError if a reply is still outstanding (one request at a time per connection:
        a second one would take the first one's reply)."""
        if self.in_flight and self.broken is None:
            raise gym.error.AlreadyPendingCallError(
                f"worker {self.index} still owes the reply to an earlier request (step_async without step_wait?)",
                "call",
            )

    @property
    def index(self) -> int:
        return self.spec.index

    @functools.cached_property
    def remote(self) -> RayWorkerProcess | None:
        """The handle of a worker started elsewhere (by a Ray actor), or None for a local one (read on every step; a
        handle keeps its process: a restart makes a new handle)."""
        return self.process if isinstance(self.process, RayWorkerProcess) else None

    async def request(self, message: dict[str, Any], timeout_s: float) -> Any:
        """Send ``message`` and wait for the reply's result.

        Raises:
            WorkerError: the worker raised (its traceback attached; the worker stays usable), or it did not answer
                within ``timeout_s``, its connection broke or its process died (the worker is then broken).
        """
        await self.send_request(message, timeout_s)
        return await self.receive_reply(message.get("op"), timeout_s)

    async def send_request(self, message: Request, timeout_s: float | None) -> None:
        """The first half of ``request``: send ``message`` (``receive_reply`` must follow). Raises as ``request``;
        ``timeout_s=None``: no deadline of its own (the caller's bounds the wait)."""
        if self.broken is not None:
            raise WorkerError(self.index, self.broken)
        self.check_idle()
        remote = self.remote
        if remote is not None and remote.lifeline_has_news():  # its actor reported the exit, or died
            self.broken = await self._death_reason()
            raise WorkerError(self.index, self.broken)
        op = message.get("op")
        frame = pack(message)
        try:
            if timeout_s is None:
                await self.transport.send(frame)
            else:
                async with asyncio.timeout(timeout_s):
                    await self.transport.send(frame)
        except TimeoutError:
            self.broken = f"could not send {op!r} within {timeout_s} s ({self.spec.env_id})"
            raise WorkerError(self.index, self.broken) from None
        except TransportError as exc:
            self.broken = await self._death_reason()
            raise WorkerError(self.index, self.broken) from exc
        except BaseException:  # cancelled, or Ctrl-C inside this frame: the connection is out of step
            self.broken = f"a {op!r} request was interrupted while being sent ({self.spec.env_id})"
            raise
        self.in_flight = True

    def try_send_request(self, frame: bytes) -> bool:
        """Send an already packed request at once, outside the event loop, when nothing stands in the way (not
        broken, no news from a Ray-placed worker's actor, room in the transport); True if sent (``receive_reply`` must
        follow). False: nothing was sent, ``send_request`` must do it (and raises what is wrong)."""
        try_send = self.try_send
        if self.broken is not None or self.in_flight or try_send is None:
            return False
        remote = self.remote
        if remote is not None and remote.lifeline_has_news():  # send_request reports the actor's news
            return False
        if not try_send(frame):
            return False
        self.in_flight = True
        return True

    async def receive_reply(self, op: Any, timeout_s: float | None) -> Any:
        """The second half of ``request``: wait for the reply to the request of ``op`` sent last, at most
        ``timeout_s`` (None: no deadline of its own; the caller's bounds the wait)."""
        if self.broken is not None:
            raise WorkerError(self.index, self.broken)
        try:
            if timeout_s is None:
                frame = await self.transport.receive()
            else:
                async with asyncio.timeout(timeout_s):
                    frame = await self.transport.receive()
            self.in_flight = False
            reply = unpack(frame)
        except TimeoutError:
            self.broken = f"no reply to {op!r} within {timeout_s} s ({self.spec.env_id})"
            raise WorkerError(self.index, self.broken) from None
        except TransportError as exc:
            self.broken = await self._death_reason()
            raise WorkerError(self.index, self.broken) from exc
        except BaseException:  # cancelled, Ctrl-C inside this frame, a malformed reply: replies out of step
            self.broken = f"waiting for the reply to {op!r} was interrupted ({self.spec.env_id})"
            raise
        return self._result(reply)

    def receive_reply_blocking(
        self, op: Any, timeout_s: float, decode: StepDecoder | None = None, watch: Sequence[int] = ()
    ) -> Any:
        """``receive_reply`` in this thread without the event loop (the transport's ``receive_blocking``), for a
        worker whose request is in flight: returns its result, or ``LATER`` when the reply cannot be had that way
        (not there within ``timeout_s``, the worker hung up, a transport without it, ...: nothing was consumed, and
        ``receive_reply`` must follow, which also reports what went wrong). ``decode``: what a step's reply frame
        becomes instead of its result, ``decode(index, frame)``, called while the frame is still in the ring (an
        error reply is not a step frame: it raises as usual). ``watch``: other workers' ``hangup_fd``; one of them
        hung up also returns ``LATER`` (the transport's ``receive_blocking``).

        Raises:
            WorkerError: the worker raised (its traceback attached; the worker stays usable).
        """
        receive_blocking = self.receive_blocking
        if self.broken is not None or not self.in_flight or receive_blocking is None:
            return LATER
        try:
            frame = receive_blocking(timeout_s, watch) if watch else receive_blocking(timeout_s)
            if frame is None:
                return LATER
            self.in_flight = False
            if decode is not None and frame[0] == STEP_TAG:
                return decode(self.index, frame)
            reply = unpack(frame)
        except BaseException:  # Ctrl-C in the wait, a malformed reply: replies out of step
            self.broken = f"waiting for the reply to {op!r} was interrupted ({self.spec.env_id})"
            raise
        return self._result(reply)

    def _result(self, reply: dict[str, Any]) -> Any:
        if not reply.get("ok"):
            raise WorkerError(
                self.index, f"{self.spec.env_id}: {reply.get('error')}", remote_traceback=reply.get("traceback", "")
            )
        return reply.get("result")

    async def _death_reason(self) -> str:
        remote = self.remote
        if remote is not None:
            code = await remote.poll_exit(0.5)  # the actor reports the exit a moment after the connection broke
            if remote.lost:
                return f"the remote worker ({self.spec.env_id}, {remote.where()}) is lost: {remote.lost}"
            if code is not None:
                return f"the remote worker process ({self.spec.env_id}, {remote.where()}) died with exit code {code}"
            return f"the connection to the remote worker ({self.spec.env_id}, {remote.where()}) broke"
        for _ in range(20):  # the connection usually breaks a moment before the process is reaped
            if self.process.exitcode is not None:
                break
            await asyncio.sleep(0.025)
        code = self.process.exitcode
        if code is None:
            return f"the connection to the worker ({self.spec.env_id}, pid {self.process.pid}) broke"
        return f"the worker process ({self.spec.env_id}, pid {self.process.pid}) died with exit code {code}"


class Supervisor:
    """Starts one worker per spec and runs requests on them; ``close()`` stops them all (idempotent, bounded).

    Args:
        specs: ``(env_id, kwargs)`` per worker, in index order.
        start_timeout_s: bound on starting every worker and building its env.
        call_timeout_s: bound on any one request (reset, step, ...).
        close_timeout_s: bound on ``close`` per stage (ask, join, terminate).
        transport: ``"shm"`` (same machine, the default) or ``"tcp"`` (loopback), for local workers; a spec with
            a Ray placement in its ``worker`` keyword runs where Ray places it (runtime/ray_backend.py).
        envs_per_worker: how many envs one worker process hosts (``worker_groups``): consecutive specs with the same
            placement, each with its own connection, stepped on the process's one event loop.
    """

    def __init__(
        self,
        specs: Sequence[tuple[str, dict[str, Any]]],
        *,
        start_timeout_s: float = 60.0,
        call_timeout_s: float = 60.0,
        close_timeout_s: float = 3.0,
        transport: str = "shm",
        envs_per_worker: int = 1,
    ) -> None:
        if not specs:
            raise ConfigError("expected at least one env spec, got none")
        if isinstance(envs_per_worker, bool) or not isinstance(envs_per_worker, int) or envs_per_worker < 1:
            raise ConfigError(f"envs_per_worker must be an int >= 1, got {envs_per_worker!r}")
        self.envs_per_worker = envs_per_worker
        if transport not in _LISTEN_URIS:
            raise ConfigError(f"transport must be one of {sorted(_LISTEN_URIS)}, got {transport!r}")
        # The local workers' interpreters start now and import while the env arguments are checked here; none is
        # given its spec before every check passed (see launch.py).
        spares = _start_interpreters(specs, envs_per_worker)
        try:
            for env_id, kwargs in specs:
                check_env_args(env_id, kwargs)
        except BaseException:
            _discard_all(spares)
            raise
        self._spares = spares
        self.call_timeout_s = call_timeout_s
        self.close_timeout_s = close_timeout_s
        self.listen_uri = _LISTEN_URIS[transport]
        # specs of different envs: every info says which env it came from (info["env_id"])
        self.tag_infos = len({env_id for env_id, _ in specs}) > 1
        self.workers: list[WorkerHandle] = []
        self._closed = False
        self._loop = asyncio.new_event_loop()
        self._lock = threading.Lock()
        self._orphans: list[asyncio.Task[Any]] = []  # calls interrupted inside the loop (see _drive)
        self._ray_key = secrets.token_bytes(32)  # the key of this vector env's Ray-placed workers
        self.fail_fast = False
        """A step raises a Ray-placed worker's hang-up at once, without the replies the others still owe (the vector
        env sets it unless it restarts failed workers, which needs every reply): ``_take_replies``."""
        self._hangup_fds: list[tuple[int, int]] = []  # (index, hangup_fd) of the workers that have one
        self._reply_rank: list[int] = []  # worker index -> its place in the order replies are taken (_take_replies)
        try:
            self._start(specs, start_timeout_s)
        except BaseException:
            _discard_all(self._spares)
            self.close()
            raise

    # ---- start-up

    def _start(self, specs: Sequence[tuple[str, dict[str, Any]]], timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        split = [split_placement(kwargs) for _, kwargs in specs]
        check_placements([p for p, _ in split if isinstance(p, RayPlacement)])  # before anything starts
        placements = [p for p, _ in split]
        for group in worker_groups(placements, self.envs_per_worker):
            # the first worker the highest real-time priority: the order in which a step's requests are sent
            members = [(i, specs[i][0], split[i][1], min(len(specs) - 1 - i, MAX_LOOP_RANK)) for i in group]
            self.workers += self._new_group(members, placements[group[0]], timeout_s)
        uris = self._launch(self.workers, deadline)
        remaining = max(0.1, deadline - time.monotonic())
        self.call(self._connect_all(self.workers, uris, remaining), remaining + 1.0)
        self._note_hangup_fds()

    def _note_hangup_fds(self) -> None:
        self._hangup_fds = [(w.index, w.hangup_fd) for w in self.workers if w.hangup_fd >= 0]
        n = len(self.workers)
        if any(w.info.get("cores_shared") for w in self.workers):  # see _take_replies: the last sent first
            self._reply_rank = [n - 1 - i for i in range(n)]
        else:
            self._reply_rank = list(range(n))

    def _new_group(self, members: list[Member], placement: RayPlacement | None, timeout_s: float) -> list[WorkerHandle]:
        """The handles of one worker process hosting ``members`` (``(index, env_id, kwargs, rt_rank)``): local,
        started now, or Ray-placed, to be started by ``_launch``."""
        if placement is None:
            return self._spawn(members, timeout_s, self.listen_uri)
        process = RayWorkerProcess(placement.keyed(self._ray_key))
        group = tuple(i for i, *_ in members)
        return [
            WorkerHandle(
                spec=WorkerSpec(index=i, env_id=env_id, kwargs=dict(kwargs), accept_timeout_s=timeout_s),
                process=process,
                group=group,
            )
            for i, env_id, kwargs, _ in members
        ]

    def _launch(self, workers: list[WorkerHandle], deadline: float) -> list[str]:
        """Ask the Ray actors of the Ray-placed ``workers`` to start them (in parallel, while the local ones start),
        then read the local ones' URIs; the workers' URIs in order."""
        remote = [w for w in workers if w.remote is not None and w.index == w.group[0]]  # one start per process
        if remote:
            remaining = max(0.1, deadline - time.monotonic())

            async def start_one(w: WorkerHandle) -> str:
                mates = [(v.index, v.spec.env_id, v.spec.kwargs) for v in (self.workers[i] for i in w.group[1:])]
                return await w.remote.start(w.index, w.spec.env_id, w.spec.kwargs, remaining, mates=mates)  # type: ignore[union-attr]

            async def start_all() -> None:
                results = await asyncio.gather(*(start_one(w) for w in remote), return_exceptions=True)
                for r in results:
                    if isinstance(r, BaseException):
                        raise r

            self.call(start_all(), remaining + 2.0)
        return [
            w.remote.worker_uris[w.group.index(w.index)] if w.remote is not None else self._wait_uri(w, deadline)
            for w in workers
        ]

    def _spawn(self, members: list[Member], timeout_s: float, listen_uri: str) -> list[WorkerHandle]:
        """Start a local worker process for ``members`` (``(index, env_id, kwargs, rt_rank)``; the first one's
        spec carries the others as ``mates``): their handles, sharing the process and its start-up pipe."""
        # a fresh interpreter (nothing of this process's __main__ is imported): one started at __init__, if any
        spare = self._spares.pop(0) if self._spares else None
        environ = {**(spare[0].environ_changes() if spare is not None else {}), **found_libraries()}
        specs = [
            WorkerSpec(
                index=index,
                env_id=env_id,
                kwargs=dict(kwargs),
                parent_pid=os.getpid(),
                accept_timeout_s=timeout_s,
                listen_uri=listen_uri,
                rt_rank=rt_rank,
                registration=registration(env_id),
                environ=environ,
            )
            for index, env_id, kwargs, rt_rank in members
        ]
        lead = dataclasses.replace(specs[0], mates=tuple(specs[1:]))
        if spare is None:
            proc, conn = start_worker(lead)
        else:
            proc, conn = spare
            try:
                proc.send_spec(lead)
            except BaseException:
                conn.close()
                proc.discard()
                raise
        group = tuple(spec.index for spec in specs)
        return [WorkerHandle(spec=spec, process=proc, conn=conn, group=group) for spec in specs]

    def restart(self, index: int, timeout_s: float = 60.0) -> WorkerHandle:
        """Stop worker ``index`` (whatever its state) and start a new one with the same spec; the other envs of
        its process (``group``) are stopped and started with it.

        The new workers' envs are built but not padded or reset; that is the caller's business.

        Raises:
            WorkerError: the new worker failed to start (it is stopped again).
        """
        old = self.workers[index]
        olds = [self.workers[i] for i in old.group]
        for w in olds:
            self._discard(w)
        old_remote = old.remote
        deadline = time.monotonic() + timeout_s
        members = [(w.index, w.spec.env_id, w.spec.kwargs, w.spec.rt_rank) for w in olds]
        if old_remote is None:
            news = self._spawn(members, timeout_s, old.spec.listen_uri)
        else:  # through Ray, with the same placement
            news = self._new_group(members, old_remote.placement, timeout_s)
        for w in news:
            self.workers[w.index] = w
        try:
            uris = self._launch(news, deadline)
            remaining = max(0.1, deadline - time.monotonic())
            self.call(self._connect_all(news, uris, remaining), remaining + 1.0)
            self._note_hangup_fds()
        except BaseException as exc:
            for w in news:
                w.broken = "restart failed"
                self._discard(w)
            if old_remote is not None and isinstance(exc, WorkerError | ConfigError):
                raise WorkerError(
                    index,
                    f"could not restart the remote worker through {old_remote.placement.uri}: {exc}",
                    remote_traceback=getattr(exc, "remote_traceback", ""),
                ) from exc
            raise
        return self.workers[index]

    def _discard(self, w: WorkerHandle) -> None:
        """Close ``w``'s connection and stop its process, whatever its state (bounded)."""
        with contextlib.suppress(Exception):
            self.call(_aclose(w.transport), 5.0)
        remote = w.remote
        if remote is None:
            _stop_process(w.process, self.close_timeout_s)  # type: ignore[arg-type]
        else:
            t = self.close_timeout_s
            with contextlib.suppress(Exception):
                self.call(remote.stop(t, asked=False), 2 * t + 4.0)

    @staticmethod
    def _wait_uri(w: WorkerHandle, deadline: float) -> str:
        hint = "see its stderr"
        while not w.conn.poll(0.05):
            if not w.process.is_alive():
                raise WorkerError(
                    w.index, f"{w.spec.env_id}: the worker exited with code {w.process.exitcode} at start; {hint}"
                )
            if time.monotonic() > deadline:
                raise WorkerError(w.index, f"{w.spec.env_id}: the worker did not start in time")
        try:
            uri = w.conn.recv()
        except EOFError:
            if isinstance(w.process, WorkerProcess):
                w.process.join(1.0)
            raise WorkerError(
                w.index, f"{w.spec.env_id}: the worker exited with code {w.process.exitcode} at start; {hint}"
            ) from None
        if w.index == w.group[-1]:  # the process's last URI (its envs' come in ``group`` order)
            w.conn.close()
        return str(uri)

    @staticmethod
    def _machine(w: WorkerHandle) -> str:
        """Which machine ``w`` runs on: "" for the agent's (a local worker, or a Ray-placed one over shm), else its
        Ray node."""
        remote = w.remote
        if remote is None or remote.worker_uri.startswith("shm://"):
            return ""
        return remote.node_id or f"worker {w.index}"

    def _core_shares(self) -> dict[int, list[Any]]:
        """``[slot, count, mode]`` per worker index, for its ``spaces`` request: the rank of its process among the
        worker processes of this vector env on its machine, how many envs they host, and
        ``worker.shared_cores_mode`` (the process pins itself to core ``slot`` modulo its cores when the envs
        outnumber them: ``_Server._share_cores``)."""
        mode = shared_cores_mode()
        machine = {w.index: self._machine(w) for w in self.workers}
        envs = collections.Counter(machine.values())
        processes: collections.Counter[str] = collections.Counter()
        slot: dict[int, int] = {}  # by the index of a process's first env
        for w in self.workers:
            if w.index == w.group[0]:
                slot[w.index] = processes[machine[w.index]]
                processes[machine[w.index]] += 1
        return {w.index: [slot[w.group[0]], envs[machine[w.index]], mode] for w in self.workers}

    async def _connect_all(self, workers: list[WorkerHandle], uris: list[str], timeout_s: float) -> None:
        from uniros_async.transports.base import TransportOptions, connect

        shares = self._core_shares()

        async def one(w: WorkerHandle, uri: str) -> None:
            key = w.remote.placement.auth_key if w.remote is not None else None
            try:
                w.transport = await connect(uri, TransportOptions(connect_timeout_s=timeout_s, auth_key=key))
            except (TransportError, OSError, TimeoutError) as exc:
                raise WorkerError(w.index, f"{w.spec.env_id}: could not connect to the worker at {uri}: {exc}") from exc
            share = shares[w.index]
            spaces = {"op": "spaces", "tag_infos": self.tag_infos, "share": share}
            w.info = await w.request(spaces, timeout_s)
            if hasattr(w.transport, "spin_ns") and not w.info.get("realtime"):  # shm, tcp: see REPLY_SPIN_NS
                here = w.remote is None or self._machine(w) == "" or _local_address(w.remote.node_ip)
                polls = share[2] == "off" or not here or not cores_shared(share[1])
                w.transport.spin_ns = REPLY_SPIN_NS if polls else 0
            w.try_send = getattr(w.transport, "try_send", None)  # shm, tcp (a Ray-placed worker too)
            w.receive_blocking = getattr(w.transport, "receive_blocking", None)
            if w.remote is not None and hasattr(w.transport, "fileno"):  # over tcp: another node, which may be lost
                w.hangup_fd = w.transport.fileno()

        results = await asyncio.gather(*(one(w, u) for w, u in zip(workers, uris, strict=True)), return_exceptions=True)
        for r in results:
            if isinstance(r, BaseException):
                raise r

    # ---- requests

    def call(self, coro: Coroutine[Any, Any, T], timeout_s: float | None = None) -> T:
        """Run ``coro`` on the supervisor's loop, in this thread, under ``timeout_s`` (default: the call timeout
        plus 5 s; the requests inside have their own deadlines).

        Raises:
            TimeoutError: no result within ``timeout_s``.
            RuntimeError: the supervisor is closed.
        """
        t = self.call_timeout_s + 5.0 if timeout_s is None else timeout_s
        return self._drive(_bounded(coro, t), t)

    def _drive(self, coro: Coroutine[Any, Any, T], timeout_s: float, *, finish_orphans: bool = True) -> T:
        """Run the loop in this thread until ``coro`` is done (one thread at a time).

        A call interrupted inside the loop (Ctrl-C: KeyboardInterrupt raised in this thread) leaves its task
        pending; the next call first lets it finish (under its own deadlines), so the replies it waited for are
        consumed and the workers stay usable, as when the loop ran on a thread of its own. ``close`` cancels such
        tasks instead (``finish_orphans=False``).
        """
        loop = self._loop
        if loop.is_closed():
            coro.close()
            raise RuntimeError("the supervisor is closed")
        if not self._lock.acquire(timeout=timeout_s):
            coro.close()
            raise TimeoutError(f"another thread kept the supervisor busy for {timeout_s} s")
        try:
            if self._orphans:
                self._settle_orphans(finish_orphans)
            task = loop.create_task(coro)
            try:
                return loop.run_until_complete(task)
            except BaseException:
                if not task.done():
                    self._orphans.append(task)
                raise
        finally:
            self._lock.release()

    def _settle_orphans(self, finish: bool) -> None:
        orphans, self._orphans = self._orphans, []
        pending = [t for t in orphans if not t.done()]
        if pending and not finish:
            for t in pending:
                t.cancel()
        if pending:
            try:
                self._loop.run_until_complete(asyncio.wait(pending))
            except BaseException:
                self._orphans = [t for t in orphans if not t.done()]
                raise
        for t in orphans:
            if not t.cancelled():
                t.exception()  # retrieved: the interrupted caller is gone

    def send_steps_now(self, messages: Sequence[PackedRequest]) -> int:
        """The first half of ``UnirosVectorEnv.step``: send one packed step request to every worker, in this thread
        (``WorkerHandle.try_send_request``), in index order until one cannot go; returns how many went. Its second
        half is ``receive_steps_now``; ``submit_steps`` (``step_async``) sends with it too. In as few lines of Python
        as it can: this runs on every step, and at one env the agent's share of a step's overhead is what its lines of
        Python cost (the goal: 50 us over the bare env step).

        Raises:
            gymnasium.error.AlreadyPendingCallError: a worker still owes a reply (nothing was sent).
        """
        if self._orphans:  # replies still owed by a call cut short: request_all collects them first (_drive)
            return 0
        workers = self.workers
        for w in workers:
            if w.in_flight:
                w.check_idle()  # raises unless it is broken (that one is reported by the request it is sent)
        lock = self._lock
        if not lock.acquire(blocking=False):
            return 0
        try:
            if self._loop.is_closed():
                return 0
            sent = 0
            for w, m in zip(workers, messages):  # noqa: B905  (one message per worker: _step_messages checks it)
                if not w.try_send_request(m.frame):
                    break
                sent += 1
            return sent
        finally:
            lock.release()

    def receive_steps_now(self, messages: Sequence[PackedRequest], sent: int, decode: StepDecoder) -> list[Any]:
        """The second half of ``UnirosVectorEnv.step``: the replies to ``messages``, of which ``send_steps_now``
        sent the first ``sent``, taken in this thread (``_take_replies``) while they can be had that way; from the
        first that cannot, the rest (requests not sent, replies not had) go through ``request_all`` on the loop, under
        the same deadline (``_SentPending``). Returns the results in index order (``decode``'s for the replies it
        took), a WorkerError in the slot of a worker that failed.

        Raises:
            Exception: any other error a reply raised (a malformed frame), once every reply is in, as ``request_all``.
        """
        n = len(messages)
        results: list[Any] = [None] * n
        deadline = time.monotonic() + self.call_timeout_s
        owing, unexpected, hung = self._take_replies(sent, deadline, results, decode)
        if hung is not None:
            self._report_hang_up(hung, owing, deadline)
        if not owing and sent == n:
            if unexpected is not None:
                raise unexpected
            return results
        pending = _SentPending(self, messages, sent, results, owing.union(range(sent, n)))
        pending.to_loop(deadline)
        return pending.result(decode=decode)

    def _take_replies(
        self, sent: int, deadline: float, results: list[Any], decode: StepDecoder | None
    ) -> tuple[set[int], Exception | None, int | None]:
        """Take the step replies of the first ``sent`` workers in this thread into ``results``, one after the other in
        the order of ``_reply_rank``, until one cannot be had that way (``WorkerHandle.receive_reply_blocking``, with
        ``decode``; nothing is consumed then). Returns the indices among the first ``sent`` whose replies were not
        taken, the first error other than a WorkerError that taking one raised (it is in that one's slot as well;
        ``request_all`` raises such an error once every reply is in), and, with ``fail_fast``, the index of a Ray-placed
        worker still owing its reply whose tcp connection ended while another reply was awaited (its node or process
        is gone: ``_report_hang_up``), else None.

        The order: index order, unless the workers outnumber their cores (``worker.cores_shared``), then the last sent
        first. Those run their steps one after the other on their core in the order their requests came, so the last
        one sent to each core replies last; waiting for it first, the agent sleeps until its core is done and then
        finds the replies before it waiting, instead of waking once per reply and taking a core from a worker in the
        middle of its step each time (the agent's wake-ups per vector step: docs/performance.md)."""
        if not sent or not self._lock.acquire(blocking=False):
            return set(range(sent)), None, None
        workers = self.workers
        rank = self._reply_rank
        order = range(sent - 1, -1, -1) if rank and rank[0] else range(sent)  # _reply_rank: reversed, or in order
        k = 0
        unexpected: Exception | None = None
        watched = self._hangup_fds if self.fail_fast and sent > 1 else ()
        try:
            if self._orphans or self._loop.is_closed():
                return set(range(sent)), None, None
            while k < sent:
                i = order[k]
                here = rank[i]
                watch = [fd for j, fd in watched if rank[j] > here] if watched else ()
                try:
                    r = workers[i].receive_reply_blocking("step", max(deadline - time.monotonic(), 0.0), decode, watch)
                except Exception as exc:  # noqa: BLE001 - in its slot, as request_all does
                    r = exc
                    if unexpected is None and not isinstance(exc, WorkerError):
                        unexpected = exc
                if r is LATER:
                    if watched:  # a hang-up, of one of them or of this one (then no need to wait for the others)?
                        hung, replied = _hung_up([(j, fd) for j, fd in watched if rank[j] >= here])
                        if hung is not None:
                            return set(order[k:]), unexpected, hung
                        if replied and deadline > time.monotonic():  # its reply came before it hung up: taken in
                            watched = [(j, fd) for j, fd in watched if fd not in replied]  # its turn
                            continue
                    break
                results[i] = r
                k += 1
            return set(order[k:]), unexpected, None
        except BaseException:  # Ctrl-C: the replies still owed can no longer be matched to requests
            for j in order[k:]:
                w = workers[j]
                if w.in_flight and w.broken is None:
                    w.broken = f"waiting for its reply was interrupted ({w.spec.env_id})"
            raise
        finally:
            self._lock.release()

    def _report_hang_up(self, hung: int, owing: set[int], deadline: float) -> NoReturn:
        """Raise the WorkerError of worker ``hung``, whose connection ended without the reply to its step request
        (``_take_replies``), now: what ``WorkerHandle.receive_reply`` makes of it (its Ray actor's report: exit code,
        or its node lost). The replies the workers in ``owing`` still owe are not waited for: a task on the loop
        collects them under ``deadline``; the next call lets it finish first and ``close`` cancels it (``_drive``)."""
        w = self.workers[hung]
        owed = [self.workers[i] for i in sorted(owing) if i != hung]

        async def collect() -> None:
            for other in owed:
                with contextlib.suppress(Exception):
                    await other.receive_reply("step", max(deadline - time.monotonic(), 0.0))

        async def report() -> tuple[WorkerError, asyncio.Task[None]]:
            task = asyncio.get_running_loop().create_task(collect())
            try:
                await w.receive_reply("step", _HANG_UP_REPORT_S)
            except WorkerError as exc:
                return exc, task
            return WorkerError(hung, f"the connection to the worker ({w.spec.env_id}) ended after its reply"), task

        error, task = self._drive(report(), _HANG_UP_REPORT_S + 2.0)
        if not task.done():
            self._orphans.append(task)
        raise error

    def submit(self, coro: Coroutine[Any, Any, T]) -> _Pending[T]:
        """Start ``coro`` on the supervisor's loop, run it until it waits, and return; ``.result()`` finishes it."""

        async def start() -> asyncio.Task[T]:
            task = asyncio.get_running_loop().create_task(coro)
            await asyncio.sleep(0)
            return task

        return _Pending(self, self._drive(start(), 5.0))

    def submit_steps(self, messages: Sequence[PackedRequest]) -> _Pending[list[Any]]:
        """``request_all(messages, return_exceptions=True)`` for one step request per worker, returning once every
        request is sent (``send_steps_now``); the replies are taken by ``.result()`` (``_take_replies``, then the
        loop for what is left). Raises as ``send_steps_now``."""
        sent = self.send_steps_now(messages)
        if sent == len(messages):  # all sent: nothing runs until the replies are due
            if self._loop.is_closed():
                raise RuntimeError("the supervisor is closed")
            return _SentPending(self, messages, sent)

        async def start() -> asyncio.Task[list[Any]]:
            done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
            task = asyncio.get_running_loop().create_task(
                self.request_all(messages, return_exceptions=True, sent=done, present=frozenset(range(sent)))
            )
            either: set[asyncio.Future[Any]] = {done, task}
            await asyncio.wait(either, return_when=asyncio.FIRST_COMPLETED)
            return task

        return _Pending(self, self._drive(start(), self.call_timeout_s + 5.0))

    async def request_all(
        self,
        messages: Sequence[Request | None],
        *,
        return_exceptions: bool = False,
        sent: asyncio.Future[None] | None = None,
        present: frozenset[int] = frozenset(),
        wait_s: float | None = None,
    ) -> list[Any]:
        """Send ``messages[i]`` to worker i (None: skip), all before waiting for any (then ``sent`` is set). Once
        every reply is in, raise the first failure (by index), or with ``return_exceptions`` put each WorkerError
        in its slot. ``present``: the workers whose request ``send_steps_now`` has sent already. ``wait_s``: how long
        to wait at most (default: the call timeout, which error messages name either way)."""
        for i, m in enumerate(messages):
            if m is not None and i not in present:
                self.workers[i].check_idle()  # before anything is sent
        t = self.call_timeout_s
        results: list[Any] = [None] * len(messages)
        waiting: list[int] = []
        current: tuple[int, str] | None = None  # the worker and phase a timeout interrupts
        # One deadline for the whole exchange (one timer, not two per worker). The replies are collected one after
        # the other (each waits in its ring meanwhile): no task per worker, so a step costs the fewest event-loop
        # rounds, and a hung worker is still found within the call timeout.
        try:
            async with asyncio.timeout(t if wait_s is None else wait_s):
                for i, m in enumerate(messages):
                    if m is None:
                        continue
                    if i in present:
                        waiting.append(i)
                        continue
                    current = (i, "send")
                    try:
                        await self.workers[i].send_request(m, None)
                    except WorkerError as exc:
                        results[i] = exc
                    else:
                        waiting.append(i)
                if sent is not None and not sent.done():
                    sent.set_result(None)
                while waiting:
                    i = waiting[0]
                    current = (i, "reply")
                    try:
                        results[i] = await self.workers[i].receive_reply(messages[i].get("op"), None)  # type: ignore[union-attr]
                    except Exception as exc:  # noqa: BLE001 - in its slot, raised below
                        results[i] = exc
                    waiting.pop(0)
                current = None
        except TimeoutError:
            assert current is not None
            i, phase = current
            w = self.workers[i]
            op = messages[i].get("op")  # type: ignore[union-attr]
            what = "could not send" if phase == "send" else "no reply to"
            w.broken = f"{what} {op!r} within {t} s ({w.spec.env_id})"
            results[i] = WorkerError(i, w.broken)
            if phase == "reply":
                waiting.pop(0)
            else:  # the requests after the one that could not be sent were not sent either
                for j in range(i + 1, len(messages)):
                    if messages[j] is not None:
                        results[j] = WorkerError(j, f"not sent: worker {i} did not take its request within {t} s")
            for j in waiting:  # same deadline, passed too: only a reply that is already there still counts
                try:
                    results[j] = await self.workers[j].receive_reply(messages[j].get("op"), 0.0)  # type: ignore[union-attr]
                except Exception as exc:  # noqa: BLE001
                    results[j] = exc
                    wj = self.workers[j]
                    if wj.broken is not None:
                        wj.broken = f"no reply to {messages[j].get('op')!r} within {t} s ({wj.spec.env_id})"  # type: ignore[union-attr]
                        results[j] = WorkerError(j, wj.broken)
            waiting.clear()
        finally:
            for j in waiting:  # interrupted: their replies can no longer be matched to requests
                w = self.workers[j]
                if w.broken is None:
                    w.broken = f"waiting for its reply was interrupted ({w.spec.env_id})"
        return _raise_unexpected(results, worker_errors=not return_exceptions)

    def pids(self) -> list[int | None]:
        """The worker process ids, in index order."""
        return [w.process.pid for w in self.workers]

    # ---- shutdown

    def close(self) -> None:
        """Ask every worker to close its env, then join, terminate, kill; idempotent, bounded in time.

        A worker that acknowledged gets ``close_timeout_s`` to exit; one that did not (dead, hung, broken) is
        terminated at once, and killed if it is still there ``close_timeout_s`` later (gymnasium close_extras).
        """
        if self._closed:
            return
        self._closed = True
        t = self.close_timeout_s
        acked = [False] * len(self.workers)
        if not self._loop.is_closed():
            try:
                acked = self._drive(_bounded(self._close_all(t), t + 2.0), t + 2.0, finish_orphans=False)
            except Exception:  # noqa: BLE001 - shutting down whatever state they are in
                logger.warning("asking the workers to close failed", exc_info=True)
        remote = [  # one stop per process, asked if every env of it closed
            (w.remote, all(acked[i] for i in w.group))
            for w in self.workers
            if w.remote is not None and w.index == w.group[0]
        ]
        if remote and not self._loop.is_closed():  # their actors join, terminate and kill them (bounded)

            async def stop_remote() -> None:
                await asyncio.gather(*(r.stop(t, asked=ok) for r, ok in remote), return_exceptions=True)

            try:
                self._drive(_bounded(stop_remote(), 2 * t + 3.0), 2 * t + 3.0, finish_orphans=False)
            except Exception:  # noqa: BLE001
                logger.warning("stopping the remote workers failed", exc_info=True)
        local = [
            (w, w.process, ok)
            for w, ok in zip(self.workers, acked, strict=True)
            if isinstance(w.process, WorkerProcess)
        ]
        deadline = time.monotonic() + t
        for _, p, ok in local:
            if ok:
                p.join(max(0.0, deadline - time.monotonic()))
        for _, p, _ in local:
            if p.is_alive():
                p.terminate()
        deadline = time.monotonic() + t
        for _, p, _ in local:
            p.join(max(0.0, deadline - time.monotonic()))
            if p.is_alive():
                p.kill()
                p.join(1.0)
        for w in self.workers:
            if w.conn is not None and not w.conn.closed:
                w.conn.close()
        self._close_loop()

    def _close_loop(self) -> None:
        loop = self._loop
        if loop.is_closed() or not self._lock.acquire(timeout=5.0):
            return
        try:
            pending = [task for task in asyncio.all_tasks(loop) if not task.done()]
            for task in pending:
                task.cancel()
            if pending:
                with contextlib.suppress(BaseException):
                    loop.run_until_complete(asyncio.wait(pending, timeout=2.0))
            with contextlib.suppress(BaseException):
                loop.run_until_complete(loop.shutdown_asyncgens())
            loop.close()
        finally:
            self._lock.release()

    async def _close_all(self, timeout_s: float) -> list[bool]:
        async def one(w: WorkerHandle) -> bool:
            try:
                if w.transport is not None and w.broken is None and w.process.is_alive():
                    await w.request({"op": "close"}, timeout_s)
                    return True
                return False
            except WorkerError:
                return w.broken is None  # the env's close raised, but the worker answered and is exiting
            finally:
                if w.transport is not None:
                    await w.transport.aclose()

        results = await asyncio.gather(*(one(w) for w in self.workers), return_exceptions=True)
        return [r is True for r in results]

    def __del__(self) -> None:
        if not getattr(self, "_closed", True):
            self.close()


@functools.cache
def _local_address(ip: str) -> bool:
    """Whether ``ip`` (a Ray node's address) is one of this machine's own: a node started on the agent's machine
    (``ray.cluster_utils.Cluster``, several ``ray start`` on one host), whose workers share the agent's cores."""
    if not ip:
        return False
    try:
        with socket.socket(socket.AF_INET6 if ":" in ip else socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind((ip, 0))  # only an address of one of this machine's interfaces can be bound
    except OSError:
        return False
    return True


def _hung_up(watched: list[tuple[int, int]]) -> tuple[int | None, set[int]]:
    """Which of ``watched`` ((index, socket descriptor), in the order their replies are taken) hung up or were
    reset: the index of the first one whose peer is gone with nothing left to read (its reply will never come), or
    None; and the descriptors of those hung up with data still to read (a reply sent before the hang-up)."""
    poller = select.poll()
    for _, fd in watched:
        poller.register(fd, _HANG_UP)
    fired = {fd for fd, _ in poller.poll(0)}
    replied: set[int] = set()
    for i, fd in watched:
        if fd not in fired:
            continue
        sock = socket.socket(fileno=fd)
        try:
            ended = sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
        except BlockingIOError:
            ended = False
        except OSError:  # reset
            ended = True
        finally:
            sock.detach()
        if ended:
            return i, replied
        replied.add(fd)
    return None, replied


def worker_groups(placements: Sequence[RayPlacement | None], envs_per_worker: int) -> list[list[int]]:
    """The spec indices each worker process hosts: runs of consecutive specs with the same placement (here, or the
    same Ray resources, node, CPUs and cluster), at most ``envs_per_worker`` each. A Ray-placed process asks for
    that placement once (its actor's resources and CPUs), however many envs it hosts."""

    def where(p: RayPlacement | None) -> Any:
        return None if p is None else (sorted(p.resources.items()), p.node_id, p.num_cpus, p.address)

    groups: list[list[int]] = []
    for i, p in enumerate(placements):
        if groups and len(groups[-1]) < envs_per_worker and where(placements[groups[-1][0]]) == where(p):
            groups[-1].append(i)
        else:
            groups.append([i])
    return groups


def _start_interpreters(
    specs: Sequence[tuple[str, dict[str, Any]]], envs_per_worker: int = 1
) -> list[tuple[WorkerProcess, multiprocessing.connection.Connection]]:
    """One interpreter for each worker process that runs here (``launch.start_interpreter``; ``worker_groups``);
    none if any spec's placement is malformed or its env id unknown (``check_env_args`` then reports it, before any
    process starts). A ``"module:Id"`` counts as known: its module is imported by the check."""
    from uniros_async.tasks.registry import register_envs

    register_envs()
    if not all(isinstance(env_id, str) and (":" in env_id or env_id in gym.registry) for env_id, _ in specs):
        return []
    try:
        placements = [split_placement(kwargs)[0] for _, kwargs in specs]
    except ConfigError:
        return []
    local = sum(placements[g[0]] is None for g in worker_groups(placements, envs_per_worker))
    spares: list[tuple[WorkerProcess, multiprocessing.connection.Connection]] = []
    try:
        for _ in range(local):
            spares.append(start_interpreter())
    except BaseException:
        _discard_all(spares)
        raise
    return spares


def _discard_all(spares: list[tuple[WorkerProcess, multiprocessing.connection.Connection]]) -> None:
    """Stop the interpreters that were not given a spec (``WorkerProcess.discard``), all at once."""
    for proc, conn in spares:
        conn.close()
        proc.withdraw()
    for proc, _ in spares:
        proc.discard()
    spares.clear()


def _raise_unexpected(results: list[Any], *, worker_errors: bool = False) -> list[Any]:
    """``results``, unless one of them is an exception other than a WorkerError (or is any, with
    ``worker_errors``): the first of those is raised, as ``request_all`` does once every reply is in."""
    for r in results:
        if isinstance(r, BaseException) and (worker_errors or not isinstance(r, WorkerError)):
            raise r
    return results


async def _aclose(transport: Any) -> None:
    if transport is not None:
        await transport.aclose()


def _stop_process(process: WorkerProcess, timeout_s: float) -> None:
    """join, terminate, kill: each bounded."""
    if process.is_alive():
        process.terminate()
        process.join(timeout_s)
    if process.is_alive():
        process.kill()
    process.join(1.0)


async def _bounded(coro: Coroutine[Any, Any, T], timeout_s: float) -> T:
    try:
        async with asyncio.timeout(timeout_s):
            return await coro
    except TimeoutError:
        raise TimeoutError(f"no result within {timeout_s} s") from None


class _Pending(Generic[T]):
    """Requests started by ``Supervisor.submit``/``submit_steps``; like a concurrent.futures.Future, but ``result``
    runs the supervisor's loop in the calling thread until they are done."""

    def __init__(self, supervisor: Supervisor, task: asyncio.Task[T]) -> None:
        self._sup = supervisor
        self._task = task

    def done(self) -> bool:
        return self._task.done()

    def result(self, timeout: float | None = None) -> T:
        """The result (or exception) of the requests.

        Raises:
            concurrent.futures.TimeoutError: not done within ``timeout`` (they stay pending: call again).
            concurrent.futures.CancelledError: the supervisor closed first.
        """
        task = self._task
        if not task.done():
            t = self._sup.call_timeout_s + 5.0 if timeout is None else timeout
            try:
                self._sup._drive(asyncio.wait({task}, timeout=t), t + 1.0)
            except RuntimeError:  # closed meanwhile
                pass
        if not task.done():
            raise concurrent.futures.TimeoutError()
        if task.cancelled():
            raise concurrent.futures.CancelledError()
        return task.result()


class _SentPending(_Pending[list[Any]]):
    """Step requests of which the first ``sent`` went already (``submit_steps``: every one; ``receive_steps_now``: as
    many as it could): ``result`` takes their replies in the calling thread (``Supervisor._take_replies``, no
    event-loop round) and leaves the rest, requests not sent and replies not had that way, to ``request_all`` on the
    supervisor's loop, under what is left of the same deadline. The call timeout starts at the first ``result``, as
    for a task."""

    def __init__(
        self,
        supervisor: Supervisor,
        messages: Sequence[PackedRequest],
        sent: int,
        results: list[Any] | None = None,
        rest: set[int] | None = None,
    ) -> None:
        """``results`` and ``rest``: what the calling thread took already and what it could not (given together,
        by ``receive_steps_now``, which then calls ``to_loop``)."""
        self._sup = supervisor
        self._messages = messages
        self._sent = sent
        self._results: list[Any] = [None] * len(messages) if results is None else results
        self._rest: set[int] | None = rest  # what the calling thread could not take (None: not tried yet)
        self._task: asyncio.Task[list[Any]] | None = None  # type: ignore[assignment]  # ... by request_all instead

    def done(self) -> bool:
        if self._task is not None:
            return self._task.done()
        return self._rest is not None and not self._rest

    def result(self, timeout: float | None = None, decode: StepDecoder | None = None) -> list[Any]:
        """As ``_Pending.result``; ``decode``: what a step reply taken in this thread becomes instead of its result
        (``WorkerHandle.receive_reply_blocking``; the replies taken by the event loop are results as usual)."""
        sup = self._sup
        now = time.monotonic()
        end = None if timeout is None else now + timeout
        if self._rest is None:
            deadline = now + sup.call_timeout_s
            until = deadline if end is None else min(deadline, end)
            owing, _, hung = sup._take_replies(self._sent, until, self._results, decode)  # raised below, with the rest
            if hung is not None:
                self._rest = set()
                sup._report_hang_up(hung, owing, deadline)
            self._rest = owing.union(range(self._sent, len(self._messages)))
            self.to_loop(deadline)
        if self._task is not None:
            more = super().result(None if end is None else max(end - time.monotonic(), 0.0))
            for i in self._rest or ():
                self._results[i] = more[i]
            self._rest = set()
            self._task = None
        return _raise_unexpected(self._results)

    def to_loop(self, deadline: float) -> None:
        """Start ``request_all`` on the supervisor's loop for what the calling thread could not collect (``rest``),
        with what is left until ``deadline``; ``result`` runs it.

        Raises:
            concurrent.futures.CancelledError: there is something left and the supervisor is closed.
        """
        sup = self._sup
        if self._rest:
            if sup._loop.is_closed():
                raise concurrent.futures.CancelledError()
            left = [m if i in self._rest else None for i, m in enumerate(self._messages)]
            present = frozenset(i for i in self._rest if i < self._sent)  # sent, their replies not taken
            wait_s = max(deadline - time.monotonic(), 0.0)
            coro = sup.request_all(left, return_exceptions=True, present=present, wait_s=wait_s)
            self._task = sup._loop.create_task(coro)
