"""Workers placed by Ray: each env worker is started, on the node Ray's scheduler picks, by a small Ray actor.

A spec asks for Ray with the ``worker`` keyword (never passed to the env), or every spec at once with
``make_vec(..., backend="ray")`` / ``make(..., backend="ray")``::

    make_vec(["uniros/Ned2Reach-v0", ("uniros/Rx200Reach-v0", {"worker": {"ray": {"resources": {"rx200_arm": 1}}}})],
             backend="ray")

The placement (``RayPlacement``) holds what Ray schedules on: ``resources`` (a custom resource such as
``rx200_arm: 1`` that only the PC wired to that arm advertises), ``node_id`` (a hard node affinity), ``num_cpus``
(default 1: a worker steps its env on a core of its own) and the cluster ``address`` (default: the cluster this
process is connected to, else ``$RAY_ADDRESS``, else the one ``ray start`` started on this machine).

Ray only places and supervises; the step never goes through Ray. The actor (``_WorkerHost``, one per env worker,
``max_restarts=0``) starts the worker process on its node exactly as the supervisor starts a local one
(``launch.start_worker``, its parent-pid watchdog then watching the actor), and answers with the worker's URI: shm
when the actor landed on the agent's own node, else ``tcp://<node ip>:0``. The agent connects to that URI directly
with a random key of its vector env (HMAC handshake, ``TransportOptions.auth_key``), and from then on the worker is
an ordinary one (``supervisor.WorkerHandle``); a step costs the transport's round trip, not a Ray call.

``RayWorkerProcess`` stands for the worker process on the agent's side (``pid`` on its node, ``exitcode``,
``is_alive``), with the interface the supervisor uses for a worker it did not start itself: ``start``,
``lifeline_has_news`` (an attribute read: a completed ``wait_exit`` call of the actor, which returns the worker's
exit code when it ends, the node's loss when the actor sees its raylet end, and fails when the actor dies),
``poll_exit``, ``stop`` and ``aclose``.

Lifetime: a worker ends when its agent connection goes away (EOF, as for every worker), when its actor dies (the
parent-pid watchdog, at once), and on ``stop``: terminate, then kill, through the actor; then the actor is
killed (``ray.kill``). A node whose raylet ends (stopped, killed, the node going down) is lost: the actor watches
its raylet (``_WorkerHost._watch_node``, a pidfd) and ends the worker at once, so its connection closes, and the
step in flight raises the worker's WorkerError within milliseconds, naming the node
(``Supervisor._take_replies`` watches the Ray-placed workers' tcp connections while it waits; docs/reliability.md).
A host that vanishes without closing its sockets is found by TCP keepalive (~5 s) or the call timeout.

Ray is imported only here, and only when a Ray placement is used (``pip install 'uniros_async[ray]'``).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import dataclasses
import importlib.util
import os
import select
import socket
import threading
import time
from collections.abc import Sequence
from typing import Any

from uniros_async.errors import ConfigError, WorkerError
from uniros_async.runtime.worker import WorkerSpec

__all__ = [
    "RayPlacement",
    "BACKENDS",
    "RayWorkerProcess",
    "apply_backend",
    "check_placements",
    "connect",
    "parse_ray_placement",
]

_RAY_CURRENT_CLUSTER = "/tmp/ray/ray_current_cluster"
"""Where ``ray start --head`` writes the address of the cluster it started (Ray's own ``address="auto"``)."""
_ACTOR_CONCURRENCY = 4
"""Threads of a host actor: ``wait_exit`` blocks in one while ``terminate`` / ``kill`` run in another."""
_CONNECT_PROBE_S = 2.0
"""How long the tcp probe of a cluster's address may take before ``connect`` gives up on it."""
_DEATH_REPORT_WAIT_S = 0.2
"""How long a broken connection waits for the actor's report of the worker's exit code before it is reported
without it (``poll_exit`` outside ``stop``): a living actor reports within milliseconds; a dead one (its node lost)
is reported by Ray only after ~0.5 s, which would hold the error past a 10 Hz env's next action cycle."""
_NODE_LOST_GRACE_S = 0.5
"""How long a worker whose node's raylet ended may take to close its env after SIGTERM before it is killed."""
_PLACEMENT_KEYS = {"resources", "node_id", "num_cpus", "address"}
BACKENDS = ("local", "ray")
"""``make_vec`` / ``make``'s ``backend``: workers started here (``local``), or placed by Ray (``ray``)."""


@dataclasses.dataclass(frozen=True, eq=False)
class RayPlacement:
    """Where Ray may place a spec's worker.

    Attributes:
        resources: custom Ray resources the worker's node must have, e.g. ``{"rx200_arm": 1}``.
        node_id: a Ray node id (hex) the worker must run on; None: wherever the scheduler puts it.
        num_cpus: CPUs the worker takes from its node's Ray resources (it steps its env on one core).
        address: the Ray cluster (``HOST:PORT`` of its head); None: the connected one, else ``$RAY_ADDRESS``, else
            the one ``ray start --head`` started on this machine.
        auth_key: the key the agent and worker prove to each other (set by the supervisor, one per vector env).
    """

    resources: dict[str, float] = dataclasses.field(default_factory=dict)
    node_id: str | None = None
    num_cpus: float = 1.0
    address: str | None = None
    auth_key: bytes | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.resources, dict) or not all(
            isinstance(k, str) and isinstance(v, int | float) and not isinstance(v, bool) and v > 0
            for k, v in self.resources.items()
        ):
            raise ConfigError(
                f"ray resources must map names to amounts > 0, e.g. {{'rx200_arm': 1}}, got {self.resources!r:.80}"
            )
        if self.node_id is not None and not isinstance(self.node_id, str):
            raise ConfigError(f"ray node_id must be a node id string (hex), got {self.node_id!r:.80}")
        if isinstance(self.num_cpus, bool) or not isinstance(self.num_cpus, int | float) or self.num_cpus < 0:
            raise ConfigError(f"ray num_cpus must be a number >= 0, got {self.num_cpus!r}")
        if self.address is not None and not isinstance(self.address, str):
            raise ConfigError(f"ray address must be 'HOST:PORT' or 'auto', got {self.address!r:.80}")

    @property
    def uri(self) -> str:
        """The cluster, as error messages name it."""
        return f"the Ray cluster at {self.address or os.environ.get('RAY_ADDRESS') or 'auto'}"

    def keyed(self, key: bytes) -> RayPlacement:
        """This placement with ``key`` as the agent-worker key (unless it has one)."""
        return self if self.auth_key is not None else dataclasses.replace(self, auth_key=key)

    def __repr__(self) -> str:  # never print the key
        return f"RayPlacement(resources={self.resources}, node_id={self.node_id}, num_cpus={self.num_cpus})"


def parse_ray_placement(value: Any) -> RayPlacement | None:
    """The ``worker`` keyword of a spec as a Ray placement: ``"ray"``, ``{"ray": {resources, node_id, num_cpus,
    address}}`` (the YAML form), or a ``RayPlacement``; None for anything else (``envargs.split_placement`` judges it).

    Raises:
        ConfigError: a ``{"ray": ...}`` mapping with unknown keys or malformed values.
    """
    if isinstance(value, RayPlacement):
        return value
    if value == "ray":
        return RayPlacement()
    if isinstance(value, dict) and "ray" in value:
        if set(value) != {"ray"}:
            raise ConfigError(f"a Ray placement is {{'ray': {{...}}}} alone, got keys {sorted(value)}")
        fields = value["ray"] or {}
        if not isinstance(fields, dict) or set(fields) - _PLACEMENT_KEYS:
            got = sorted(fields) if isinstance(fields, dict) else fields
            raise ConfigError(f"a Ray placement takes {sorted(_PLACEMENT_KEYS)}, got {got!r:.80}")
        resources = fields.get("resources") or {}
        return RayPlacement(
            resources=dict(resources) if isinstance(resources, dict) else resources,
            node_id=fields.get("node_id"),
            num_cpus=fields.get("num_cpus", 1.0),
            address=fields.get("address"),
        )
    return None


def apply_backend(specs: list[tuple[str, dict[str, Any]]], backend: str) -> list[tuple[str, dict[str, Any]]]:
    """``specs`` with ``backend``'s default placement: ``ray`` gives every spec without a ``worker`` keyword
    ``worker="ray"`` (a spec's own placement wins, ``worker=None`` keeps it here); ``local`` changes nothing.

    Raises:
        ConfigError: an unknown backend.
    """
    if backend not in BACKENDS:
        raise ConfigError(f"backend must be one of {list(BACKENDS)}, got {backend!r}")
    if backend == "local":
        return specs
    return [(env_id, kwargs if "worker" in kwargs else {**kwargs, "worker": "ray"}) for env_id, kwargs in specs]


# ---------------------------------------------------------------- the cluster


def _import_ray() -> Any:
    try:
        import ray
    except ImportError as exc:
        raise ConfigError(f"backend 'ray' needs Ray: pip install 'uniros_async[ray]' ({exc})") from exc
    return ray


def _address(address: str | None) -> str:
    """The head's ``HOST:PORT`` to connect to.

    Raises:
        ConfigError: ``auto`` and no cluster was started on this machine.
    """
    addr = address or os.environ.get("RAY_ADDRESS") or "auto"
    if addr != "auto":
        return addr.removeprefix("ray://")
    try:
        with open(_RAY_CURRENT_CLUSTER) as f:
            return f.read().strip()
    except OSError:
        raise ConfigError(
            f"no Ray cluster to connect to: address 'auto' found no {_RAY_CURRENT_CLUSTER} (no `ray start --head` on "
            "this machine); start one, or give the head's HOST:PORT (placement address=, or $RAY_ADDRESS)"
        ) from None


def connect(address: str | None = None) -> Any:
    """The ``ray`` module, connected to the cluster (``ray.init`` unless this process is connected already).

    Fails fast: the head's address is probed with a tcp connect first (Ray's own connect retries for a minute).

    Raises:
        ConfigError: Ray is not installed, or no cluster answers at the address tried (named).
    """
    ray = _import_ray()
    if ray.is_initialized():
        return ray
    addr = _address(address)
    host, _, port = addr.rpartition(":")
    if not host or not port.isdigit():
        raise ConfigError(f"a Ray cluster address is HOST:PORT (the head's GCS port), got {addr!r}")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=_CONNECT_PROBE_S).close()
    except OSError as exc:
        raise ConfigError(f"no Ray cluster at {addr} ({type(exc).__name__}: {exc})") from None
    ray.init(address=addr, namespace="uniros", log_to_driver=True, configure_logging=False)
    return ray


def _node_summary(nodes: list[dict[str, Any]]) -> str:
    parts = []
    for n in nodes:
        res = {k: v for k, v in n["Resources"].items() if not k.startswith(("node:", "memory", "object_store"))}
        parts.append(f"{n['NodeID'][:12]} at {n['NodeManagerAddress']}: {res}")
    return "; ".join(parts) or "no alive node"


def check_placements(placements: list[RayPlacement]) -> None:
    """Check, before anything starts, that every placement can be met by some alive node of the cluster.

    Raises:
        ConfigError: no cluster at the address, or a placement asks for a resource (or node, or CPU count) that no
            alive node has: the message names what was asked and every node's resources.
    """
    if not placements:
        return
    ray = connect(placements[0].address)
    nodes = [n for n in ray.nodes() if n.get("Alive")]
    for p in placements:
        wanted = dict(p.resources)
        if p.num_cpus:
            wanted["CPU"] = p.num_cpus
        candidates = [n for n in nodes if p.node_id is None or n["NodeID"] == p.node_id]
        if p.node_id is not None and not candidates:
            raise ConfigError(f"no alive Ray node has id {p.node_id!r}; nodes: {_node_summary(nodes)}")
        if not any(all(n["Resources"].get(r, 0.0) >= a for r, a in wanted.items()) for n in candidates):
            missing = [r for r, a in wanted.items() if not any(n["Resources"].get(r, 0.0) >= a for n in candidates)]
            what = ", ".join(f"{r}: {wanted[r]}" for r in missing) or ", ".join(f"{r}: {a}" for r, a in wanted.items())
            raise ConfigError(
                f"no Ray node has the resources {what} (asked {wanted}"
                f"{f' on node {p.node_id}' if p.node_id else ''}); nodes: {_node_summary(nodes)}"
            )


# ---------------------------------------------------------------- the actor (runs on the worker's node)


def _raylet_pid() -> int | None:
    """The pid of this Ray worker process's raylet (its parent, which started it), or None if the parent is not one."""
    ppid = os.getppid()
    try:
        with open(f"/proc/{ppid}/cmdline", "rb") as f:
            argv0 = f.read().split(b"\0", 1)[0]
    except OSError:
        return None
    return ppid if os.path.basename(argv0).startswith(b"raylet") else None


class _WorkerHost:
    """Starts one env worker on its node and watches it (a Ray actor; see the module docstring)."""

    def __init__(self) -> None:
        self._proc: Any = None
        self._node_lost: str | None = None  # set by the node watch when the raylet ended
        self._lost_r, self._lost_w = os.pipe()  # the node watch's word to ``wait_exit`` that the node is lost

    def _watch_node(self, proc: Any) -> None:
        """Until the worker exits: if this node's raylet ends (the node is being lost), end the worker at once.

        Ray's own worker processes notice a dead raylet only at their next check (about once a second) and the
        worker's parent-pid watchdog follows only then; ended here, the worker's connections close at once and
        the agent's pending step learns of it within milliseconds (``Supervisor._take_replies`` watches them).
        SIGTERM first (the env closes, as on any stop), SIGKILL after ``_NODE_LOST_GRACE_S``.
        """
        raylet = _raylet_pid()
        if raylet is None or not hasattr(os, "pidfd_open"):
            return
        try:
            raylet_fd = os.pidfd_open(raylet)
            worker_fd = os.pidfd_open(proc.pid)
        except OSError:
            return
        try:
            poller = select.poll()
            poller.register(raylet_fd, select.POLLIN)
            poller.register(worker_fd, select.POLLIN)
            events = dict(poller.poll())
            if raylet_fd not in events or worker_fd in events:
                return
            self._node_lost = f"its Ray node's raylet (pid {raylet}) ended: the node is lost"
            os.write(self._lost_w, b"!")  # wait_exit's report leaves before the worker's connections close
            proc.terminate()
            if not select.select([worker_fd], [], [], _NODE_LOST_GRACE_S)[0]:
                proc.kill()
        finally:
            os.close(raylet_fd)
            os.close(worker_fd)

    def start(self, spec: WorkerSpec, agent_node_id: str, timeout_s: float) -> dict[str, Any]:
        """Start the worker (hosting ``spec``'s env and its ``mates``'); ``{"ok": True, "uris" (one per env, in
        that order), "pid", "node_id", "node_ip"}`` or ``{"ok": False, "type", "error"}`` (a bad request is
        answered, never raised)."""
        import ray

        from uniros_async.runtime.launch import start_worker

        node_id = ray.get_runtime_context().get_node_id()
        node_ip = ray.util.get_node_ip_address()  # type: ignore[no-untyped-call]
        where = f"Ray node {node_id[:12]} ({node_ip}, host {socket.gethostname()})"
        for hosted in (spec, *spec.mates):
            refused = _refusal(hosted, where)
            if refused is not None:
                return refused
        listen = "shm://" if node_id == agent_node_id else f"tcp://{node_ip}:0"
        here: dict[str, Any] = {"parent_pid": os.getpid(), "listen_uri": listen}
        mates = tuple(dataclasses.replace(m, **here) for m in spec.mates)
        spec = dataclasses.replace(spec, mates=mates, **here)
        proc, conn = start_worker(spec)
        self._proc = proc
        deadline = time.monotonic() + timeout_s
        try:
            while not conn.poll(0.05):
                if not proc.is_alive() or time.monotonic() > deadline:
                    proc.kill()
                    proc.join(1.0)
                    why = f"exited with code {proc.exitcode}" if proc.exitcode is not None else "did not start in time"
                    error = f"the worker {why} at start on {where} (its stderr is in the actor's log)"
                    return {"ok": False, "type": "WorkerError", "error": error}
            uris = [str(conn.recv()) for _ in range(1 + len(spec.mates))]
        except EOFError:
            proc.join(1.0)
            error = f"the worker exited with code {proc.exitcode} at start on {where}"
            return {"ok": False, "type": "WorkerError", "error": error}
        finally:
            conn.close()
        threading.Thread(target=self._watch_node, args=(proc,), name="uniros-node-watch", daemon=True).start()
        return {"ok": True, "uris": uris, "pid": proc.pid, "node_id": node_id, "node_ip": node_ip}

    def wait_exit(self) -> dict[str, Any]:
        """Block until the worker exits, or the node watch finds the node lost: ``{"code": its exit code (None
        when the node is lost before it exited), "node_lost": why the node watch ended it, or None}``.

        A lost node is reported as soon as the watch sees it, before the worker it ends closes its connections:
        the agent, woken by that close, waits only ``_DEATH_REPORT_WAIT_S`` for this report, and a worker that
        closes its env first (SIGTERM) could take longer than that on a loaded node."""
        if self._proc is None:
            return {"code": None, "node_lost": None}
        with contextlib.suppress(OSError, ValueError):  # no pidfd: join below
            select.select([self._proc.sentinel, self._lost_r], [], [])
        if self._node_lost is not None and self._proc.exitcode is None:
            return {"code": None, "node_lost": self._node_lost}
        self._proc.join(None)
        code = int(self._proc.exitcode) if self._proc.exitcode is not None else None
        return {"code": code, "node_lost": self._node_lost}

    def terminate(self) -> None:
        if self._proc is not None:
            self._proc.terminate()

    def kill(self) -> None:
        if self._proc is not None:
            self._proc.kill()


def _refusal(spec: WorkerSpec, where: str) -> dict[str, Any] | None:
    """The answer to a start request whose env this node cannot make (its module missing, or the id or kwargs
    judged by this node's registry), or None."""
    env_id = spec.env_id
    if ":" in env_id:
        module = env_id.partition(":")[0]
        try:
            found = importlib.util.find_spec(module) is not None
        except (ImportError, ValueError):
            found = False
        if not found:
            return {"ok": False, "type": "ConfigError", "error": f"{where} cannot import module {module!r} ({env_id})"}
    if spec.registration is None:  # "module:Id", or an id the agent does not know: this node's registry judges
        from uniros_async.runtime.envargs import check_env_args

        try:
            check_env_args(env_id, spec.kwargs)
        except ConfigError as exc:
            return {"ok": False, "type": "ConfigError", "error": f"on {where}: {exc}"}
    return None


_HOST_CLASS: Any = None


def _host_class(ray: Any) -> Any:
    global _HOST_CLASS
    if _HOST_CLASS is None:
        _HOST_CLASS = ray.remote(max_restarts=0, max_concurrency=_ACTOR_CONCURRENCY)(_WorkerHost)
    return _HOST_CLASS


# ---------------------------------------------------------------- the agent side


class RayWorkerProcess:
    """Stands in for the process of a worker that a Ray actor started (see the module docstring); the coroutines
    run on the supervisor's loop."""

    def __init__(self, placement: RayPlacement) -> None:
        self.placement = placement
        self.pid: int | None = None
        self.exitcode: int | None = None
        self.worker_uris: list[str] = []  # one per env the worker hosts
        self.node_id = ""
        self.node_ip = ""
        self.lost: str | None = None  # the node was lost (its raylet ended), or the actor ended without a report
        self._actor: Any = None
        self._exit: concurrent.futures.Future[Any] | None = None
        self._news = False
        self._stopping = False  # in ``stop``: wait for the exit as long as asked

    def where(self) -> str:
        return f"pid {self.pid} on Ray node {self.node_id[:12]} ({self.node_ip})"

    @property
    def worker_uri(self) -> str:
        """The URI of the worker's first env ("" before it started)."""
        return self.worker_uris[0] if self.worker_uris else ""

    def is_alive(self) -> bool:
        return self.pid is not None and self.exitcode is None and self.lost is None

    async def start(
        self,
        index: int,
        env_id: str,
        kwargs: dict[str, Any],
        timeout_s: float,
        mates: Sequence[tuple[int, str, dict[str, Any]]] = (),
    ) -> str:
        """Have Ray place an actor, which starts the worker; returns the worker's URI. ``mates``: ``(index, env_id,
        kwargs)`` of other envs the same worker process hosts (``make_vec(envs_per_worker=...)``); their URIs
        follow in ``worker_uris``.

        Raises:
            ConfigError: the worker's node cannot import the env's module, or judged the id or kwargs (named).
            WorkerError: the actor was not placed within ``timeout_s`` (the resources asked and the nodes' are
                named), or the worker did not start.
        """
        from uniros_async.runtime.envargs import registration

        p = self.placement

        def spec_of(index: int, env_id: str, kwargs: dict[str, Any]) -> WorkerSpec:
            return WorkerSpec(
                index=index,
                env_id=env_id,
                kwargs=dict(kwargs),
                accept_timeout_s=timeout_s,
                auth_key=p.auth_key,
                registration=registration(env_id) if ":" not in env_id else None,  # ConfigError: defined in __main__
                agent_pid=os.getpid(),
            )

        spec = dataclasses.replace(spec_of(index, env_id, kwargs), mates=tuple(spec_of(*m) for m in mates))
        ray = connect(p.address)
        options: dict[str, Any] = {"num_cpus": p.num_cpus, "resources": dict(p.resources)}
        if p.node_id is not None:
            from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

            options["scheduling_strategy"] = NodeAffinitySchedulingStrategy(p.node_id, soft=False)
        self._actor = _host_class(ray).options(**options).remote()
        agent_node = ray.get_runtime_context().get_node_id()
        ref = self._actor.start.remote(spec, agent_node, timeout_s)
        try:
            async with asyncio.timeout(timeout_s):
                reply = await asyncio.wrap_future(ref.future())
        except TimeoutError:
            nodes = _node_summary([n for n in ray.nodes() if n.get("Alive")])
            raise WorkerError(
                index,
                f"{env_id}: Ray did not place and start the worker within {timeout_s:.1f} s (it asks for "
                f"{p.num_cpus} CPU and {p.resources}{f' on node {p.node_id}' if p.node_id else ''}; nodes: {nodes})",
            ) from None
        except Exception as exc:  # noqa: BLE001 - RayActorError and the like: the actor died at start
            why = _first_line(exc)
            raise WorkerError(index, f"{env_id}: the Ray actor that starts the worker failed: {why}") from exc
        if not reply.get("ok"):
            if reply.get("type") == "ConfigError":
                raise ConfigError(f"worker {index}: {reply.get('error')}")
            raise WorkerError(index, f"{env_id}: {reply.get('error')}")
        self.pid = int(reply["pid"])
        self.node_id = str(reply["node_id"])
        self.node_ip = str(reply["node_ip"])
        self.worker_uris = [str(u) for u in reply["uris"]]
        self._exit = self._actor.wait_exit.remote().future()
        self._exit.add_done_callback(self._on_exit)
        return self.worker_uri

    def _on_exit(self, _: concurrent.futures.Future[Any]) -> None:  # a Ray thread
        self._news = True

    def lifeline_has_news(self) -> bool:
        """Whether the actor reported the worker's exit, or died (then the worker has ended or is about to): an
        attribute read, checked before every request."""
        return self._news

    async def poll_exit(self, timeout_s: float) -> int | None:
        """Wait at most ``timeout_s`` (outside ``stop``: at most ``_DEATH_REPORT_WAIT_S``) for the actor's report that
        the worker ended; its exit code, or None."""
        fut = self._exit
        if self.exitcode is not None or fut is None or self.lost is not None:
            return self.exitcode
        if not self._stopping:  # a broken connection's report: see _DEATH_REPORT_WAIT_S
            timeout_s = min(timeout_s, _DEATH_REPORT_WAIT_S)
        with contextlib.suppress(Exception):  # a timeout, or the actor's death: read from ``fut`` below
            async with asyncio.timeout(max(0.0, timeout_s)):
                await asyncio.shield(asyncio.wrap_future(fut))
        if fut.done():
            exc = fut.exception()
            if exc is None:
                report = fut.result()
                code = report.get("code")
                self.exitcode = int(code) if code is not None else -1
                if report.get("node_lost"):
                    self.lost = f"{report['node_lost']} (node {self.node_id[:12]}, {self.node_ip})"
            else:
                node = f"{self.node_id[:12]} ({self.node_ip})"
                self.lost = f"its Ray actor on node {node} is gone: {_first_line(exc)}"
        return self.exitcode

    async def stop(self, timeout_s: float, *, asked: bool) -> None:
        """Make sure the worker ends: wait ``timeout_s`` for it (if it was ``asked`` to close), else terminate it,
        then kill it, through its actor; then kill the actor. Bounded by about 2 x ``timeout_s`` + 1 s."""
        self._stopping = True
        try:
            if self._actor is None or self.pid is None:
                return
            if asked:
                await self.poll_exit(timeout_s)
            for op, wait_s in (("terminate", timeout_s), ("kill", 1.0)):
                if self.exitcode is not None or self.lost is not None:
                    break
                getattr(self._actor, op).remote()
                await self.poll_exit(wait_s)
        finally:
            await self.aclose()

    async def aclose(self) -> None:
        """Kill the actor (its worker, if still there, follows by its parent-pid watchdog)."""
        actor, self._actor = self._actor, None
        if actor is not None:
            import ray

            with contextlib.suppress(Exception):
                ray.kill(actor, no_restart=True)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}"
