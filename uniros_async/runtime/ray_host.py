"""The Ray actor that starts an env worker on the node Ray placed it on, and watches it (``WorkerHost``).

One actor per worker process (``max_restarts=0``): ``start`` starts the worker exactly as the supervisor starts a
local one (``launch.start_worker``; the worker's parent-pid watchdog then watches the actor) and answers with its
URIs: shm when the actor landed on the agent's own node, else ``tcp://<node ip>:0``. ``wait_exit`` blocks until
the worker ends (or the node is lost), ``terminate`` and ``kill`` stop it. A node whose raylet ends is lost: the
actor's node watch ends the worker at once, so its connections close and the agent's step in flight learns of it
(runtime/ray_backend.py).
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib.util
import os
import select
import socket
import threading
import time
from typing import Any

from uniros_async.errors import ConfigError
from uniros_async.runtime.worker import WorkerSpec

__all__ = ["WorkerHost", "host_class"]

_ACTOR_CONCURRENCY = 4
"""Threads of a host actor: ``wait_exit`` blocks in one while ``terminate`` / ``kill`` run in another."""
_NODE_LOST_GRACE_S = 0.5
"""How long a worker whose node's raylet ended may take to close its env after SIGTERM before it is killed."""


def _raylet_pid() -> int | None:
    """The pid of this Ray worker process's raylet (its parent, which started it), or None if the parent is not one."""
    ppid = os.getppid()
    try:
        with open(f"/proc/{ppid}/cmdline", "rb") as f:
            argv0 = f.read().split(b"\0", 1)[0]
    except OSError:
        return None
    return ppid if os.path.basename(argv0).startswith(b"raylet") else None


class WorkerHost:
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


def host_class(ray: Any) -> Any:
    global _HOST_CLASS
    if _HOST_CLASS is None:
        _HOST_CLASS = ray.remote(max_restarts=0, max_concurrency=_ACTOR_CONCURRENCY)(WorkerHost)
    return _HOST_CLASS
