"""The supervisor: starts env workers, connects to them, restarts and stops them (``Supervisor``).

The requests and replies themselves, the step's hot path among them, are the step exchange's
(runtime/exchange.py, ``StepExchange``, which ``Supervisor`` extends); one worker's connection is a
``handle.WorkerHandle``; which envs share a worker process is ``worker_groups``'s decision.

Start-up: the local workers' interpreters are started first (``launch.start_interpreter``: ``python -m
uniros_async.runtime``, which imports nothing of the agent's ``__main__``) and import what every worker needs while
the env ids and keyword arguments are checked here; once every check passed, each is sent its spec (a failed check
stops them before any has one); then each worker's listen URI (``shm://`` by default, ``tcp://127.0.0.1:0`` with
``transport="tcp"``) is read from its start-up pipe (the only use of a pipe), the supervisor connects to all of
them and asks each for its spaces, in parallel.
If any worker fails to start, all are closed and the error names the worker and why.

Workers placed by Ray: a spec whose ``worker`` is a Ray placement (``"ray"``, ``{"ray": {...}}``, a
``ray_placement.RayPlacement``) is started instead of ``_spawn`` by a Ray actor on the node Ray's scheduler picks
(runtime/ray_backend.py); the actor answers with the worker's URI and the supervisor connects to it directly, as to
a local one. Its ``process`` is a ``ray_process.RayWorkerProcess`` (pid and exit code as the actor reports them); a
broken connection is reported with the exit code the actor saw, ``restart`` starts the new worker through Ray with
the same placement, and ``close`` has the actor terminate and kill what does not exit by itself. The placements are
checked against the cluster's nodes before any worker starts, and the workers of one supervisor share a random key
(tcp or shm with HMAC). Local and Ray-placed workers mix freely.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import dataclasses
import functools
import logging
import multiprocessing.connection
import os
import secrets
import socket
import time
from collections.abc import Sequence
from typing import Any

import gymnasium as gym

from uniros_async.errors import ConfigError, TransportError, WorkerError
from uniros_async.priority import MAX_LOOP_RANK
from uniros_async.runtime.cores import cores_shared, shared_cores_mode
from uniros_async.runtime.envargs import check_env_args, registration, split_placement
from uniros_async.runtime.exchange import StepExchange, bounded
from uniros_async.runtime.handle import WorkerHandle
from uniros_async.runtime.launch import WorkerProcess, found_libraries, start_interpreter, start_worker
from uniros_async.runtime.ray_placement import RayPlacement, check_placements
from uniros_async.runtime.ray_process import RayWorkerProcess
from uniros_async.runtime.specs import AUTO, factory_of, plan_envs_per_worker
from uniros_async.runtime.worker import WorkerSpec

__all__ = ["Supervisor", "WorkerHandle", "worker_groups"]

logger = logging.getLogger(__name__)

Member = tuple[int, str, dict[str, Any], int]
"""One env of a worker process: ``(index, env_id, kwargs, rt_rank)``."""
REPLY_SPIN_NS = 200_000
"""How long the supervisor polls for a reply before it sleeps (``ShmTransport.spin_ns``): a worker takes longer to
unpack a request, step a trivial env and pack the reply than the transport's default window, so the agent would
sleep and pay a wake-up on every step. The agent's thread has nothing else to do meanwhile, and the
spin credit stops the polling when replies take longer (a 10 Hz env's step). Not for workers with a real-time env
loop: there the acting thread may run SCHED_RR above the workers, and its poll would keep a lower-ranked worker
from the very reply it waits for; their connections keep the transport's default. Nor when the workers outnumber
the cores (``cores.cores_shared``): the replies then come one core's share of the physics apart, a poll seldom
catches one, and while it polls a worker waiting for that core's turn does not run; that holds for workers that
a Ray node on the agent's own machine runs too (its address is one of this machine's: ``_local_address``)."""

# how the supervisor reaches its workers: shared memory on one machine (the default), or tcp on loopback
_LISTEN_URIS = {"shm": "shm://", "tcp": "tcp://127.0.0.1:0"}


class Supervisor(StepExchange):
    """Starts one worker per spec and runs requests on them; ``close()`` stops them all (idempotent, bounded).

    Args:
        specs: ``(env_id, kwargs)`` per worker, in index order (a factory's as ``specs.normalize_specs`` makes it).
        start_timeout_s: bound on starting every worker and building its env.
        call_timeout_s: bound on any one request (reset, step, ...).
        close_timeout_s: bound on ``close`` per stage (ask, join, terminate).
        transport: ``"shm"`` (same machine, the default) or ``"tcp"`` (loopback), for local workers; a spec with
            a Ray placement in its ``worker`` keyword runs where Ray places it (runtime/ray_backend.py).
        envs_per_worker: how many envs one worker process hosts (``worker_groups``): consecutive specs with the same
            placement, each with its own connection, stepped on the process's one event loop; ``"auto"``: as
            ``specs.plan_envs_per_worker`` decides.
        rt_rank_base: added to each worker's real-time rank (``WorkerSpec.rt_rank``: its loop's SCHED_RR priority
            above the base and, by default, its tick phase, ``worker.LOOP_PHASE_STEP_NS`` a rank), capped at
            ``MAX_LOOP_RANK``: a second vector env of real-time envs beside a first (``eval.alongside``) starts
            above the first's ranks, so their loops neither tick on the same instants nor tie for a core.
        loop_phase_base: the loop phase (``WorkerSpec.loop_phase``) of the lowest-ranked worker, the others' one
            step each above it in rank order; None: ``rt_rank_base`` (each loop's phase is its rank). Beside a
            second vector env, the one whose loops rank higher takes the lower phases (``alongside.phase_bases``).
    """

    def __init__(
        self,
        specs: Sequence[tuple[str, dict[str, Any]]],
        *,
        start_timeout_s: float = 60.0,
        call_timeout_s: float = 60.0,
        close_timeout_s: float = 3.0,
        transport: str = "shm",
        envs_per_worker: int | str = 1,
        rt_rank_base: int = 0,
        loop_phase_base: int | None = None,
    ) -> None:
        if not specs:
            raise ConfigError("expected at least one env spec, got none")
        if envs_per_worker != AUTO and (
            isinstance(envs_per_worker, bool) or not isinstance(envs_per_worker, int) or envs_per_worker < 1
        ):
            raise ConfigError(f"envs_per_worker must be an int >= 1 or 'auto', got {envs_per_worker!r}")
        self.envs_per_worker = envs_per_worker
        if isinstance(rt_rank_base, bool) or not isinstance(rt_rank_base, int) or rt_rank_base < 0:
            raise ConfigError(f"rt_rank_base must be an int >= 0, got {rt_rank_base!r}")
        self.rt_rank_base = rt_rank_base
        if loop_phase_base is not None and (
            isinstance(loop_phase_base, bool) or not isinstance(loop_phase_base, int) or loop_phase_base < 0
        ):
            raise ConfigError(f"loop_phase_base must be None or an int >= 0, got {loop_phase_base!r}")
        self.loop_phase_shift = 0 if loop_phase_base is None else loop_phase_base - rt_rank_base
        if transport not in _LISTEN_URIS:
            raise ConfigError(f"transport must be one of {sorted(_LISTEN_URIS)}, got {transport!r}")
        # The local workers' interpreters start now and import while the env arguments are checked here; none is
        # given its spec before every check passed (see launch.py).
        spares = _start_interpreters(specs, envs_per_worker)
        try:
            for env_id, kwargs in specs:
                if factory_of(kwargs) is None:
                    check_env_args(env_id, kwargs)
                elif split_placement(kwargs)[0] is not None:  # a factory is judged by the env it builds, here
                    raise ConfigError(
                        f"{env_id}: an env factory is built by a worker on this machine; workers placed by Ray are "
                        "built from env ids (their nodes are sent plain data, not pickles)"
                    )
        except BaseException:
            _discard_all(spares)
            raise
        self._spares = spares
        super().__init__(call_timeout_s)
        self.close_timeout_s = close_timeout_s
        self.listen_uri = _LISTEN_URIS[transport]
        # specs of different envs: every info says which env it came from (info["env_id"])
        self.tag_infos = len({env_id for env_id, _ in specs}) > 1
        self._closed = False
        self._ray_key = secrets.token_bytes(32)  # the key of this vector env's Ray-placed workers
        try:
            self._start(specs, start_timeout_s)
            _discard_all(self._spares)  # none is left unless "auto" judged a "module:Id" anew once it was imported
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
        for group in _groups(specs, placements, self.envs_per_worker):
            # the first worker the highest real-time priority: the order in which a step's requests are sent
            members = [
                (i, specs[i][0], split[i][1], min(self.rt_rank_base + len(specs) - 1 - i, MAX_LOOP_RANK)) for i in group
            ]
            self.workers += self._new_group(members, placements[group[0]], timeout_s)
        uris = self._launch(self.workers, deadline)
        remaining = max(0.1, deadline - time.monotonic())
        self.call(self._connect_all(self.workers, uris, remaining), remaining + 1.0)
        self._note_hangup_fds()

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
                loop_phase=max(rt_rank + self.loop_phase_shift, 0),
                registration=registration(env_id) if factory_of(kwargs) is None else None,
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
        ``cores.shared_cores_mode`` (the process pins itself to core ``slot`` modulo its cores when the envs
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
                acked = self._drive(bounded(self._close_all(t), t + 2.0), t + 2.0, finish_orphans=False)
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
                self._drive(bounded(stop_remote(), 2 * t + 3.0), 2 * t + 3.0, finish_orphans=False)
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


def worker_groups(
    placements: Sequence[RayPlacement | None], envs_per_worker: int, alone: Sequence[bool] = ()
) -> list[list[int]]:
    """The spec indices each worker process hosts: runs of consecutive specs with the same placement (here, or the
    same Ray resources, node, CPUs and cluster), at most ``envs_per_worker`` each; a spec marked in ``alone`` is
    hosted by itself. A Ray-placed process asks for that placement once (its actor's resources and CPUs), however
    many envs it hosts."""

    def where(p: RayPlacement | None) -> Any:
        return None if p is None else (sorted(p.resources.items()), p.node_id, p.num_cpus, p.address)

    alone = list(alone) or [False] * len(placements)
    groups: list[list[int]] = []
    for i, p in enumerate(placements):
        last = groups[-1] if groups else None
        if (
            last is not None
            and len(last) < envs_per_worker
            and not alone[i]
            and not alone[last[0]]
            and where(placements[last[0]]) == where(p)
        ):
            last.append(i)
        else:
            groups.append([i])
    return groups


def _groups(
    specs: Sequence[tuple[str, dict[str, Any]]], placements: Sequence[RayPlacement | None], envs_per_worker: int | str
) -> list[list[int]]:
    """``worker_groups`` for ``specs``, ``envs_per_worker`` a count or ``"auto"`` (``specs.plan_envs_per_worker``)."""
    most, alone = plan_envs_per_worker(specs, [p is not None for p in placements], envs_per_worker)
    return worker_groups(placements, most, alone)


def _start_interpreters(
    specs: Sequence[tuple[str, dict[str, Any]]], envs_per_worker: int | str = 1
) -> list[tuple[WorkerProcess, multiprocessing.connection.Connection]]:
    """One interpreter for each worker process that runs here (``launch.start_interpreter``; ``worker_groups``);
    none if any spec's placement is malformed or its env id unknown (``check_env_args`` then reports it, before any
    process starts). A ``"module:Id"`` counts as known: its module is imported by the check."""
    from uniros_async.tasks.registry import register_envs

    register_envs()
    if not all(
        isinstance(env_id, str) and (":" in env_id or env_id in gym.registry or factory_of(kwargs) is not None)
        for env_id, kwargs in specs
    ):
        return []
    try:
        placements = [split_placement(kwargs)[0] for _, kwargs in specs]
    except ConfigError:
        return []
    local = sum(placements[g[0]] is None for g in _groups(specs, placements, envs_per_worker))
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
