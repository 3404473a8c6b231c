"""The agent's side of a worker that a Ray actor started: ``RayWorkerProcess``.

It stands for the worker process (``pid`` on its node, ``exitcode``, ``is_alive``), with the interface the
supervisor uses for a worker it did not start itself: ``start`` (have Ray place an actor, runtime/ray_host.py,
which starts the worker; returns its URI), ``lifeline_has_news`` (an attribute read: a completed ``wait_exit``
call of the actor, which returns the worker's exit code when it ends, the node's loss when the actor sees its
raylet end, and fails when the actor dies), ``poll_exit``, ``stop`` (terminate, then kill, through the actor; then
the actor is killed) and ``aclose``. Its coroutines run on the supervisor's loop; the step never goes through Ray.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import dataclasses
import os
from collections.abc import Sequence
from typing import Any

from uniros_async.errors import ConfigError, WorkerError
from uniros_async.runtime.ray_host import host_class
from uniros_async.runtime.ray_placement import RayPlacement, connect, node_summary
from uniros_async.runtime.worker import WorkerSpec

__all__ = ["RayWorkerProcess"]

_DEATH_REPORT_WAIT_S = 0.2
"""How long a broken connection waits for the actor's report of the worker's exit code before it is reported
without it (``poll_exit`` outside ``stop``): a living actor reports within milliseconds; a dead one (its node lost)
is reported by Ray only after ~0.5 s, which would hold the error past a 10 Hz env's next action cycle."""


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
        self._actor = host_class(ray).options(**options).remote()
        agent_node = ray.get_runtime_context().get_node_id()
        ref = self._actor.start.remote(spec, agent_node, timeout_s)
        try:
            async with asyncio.timeout(timeout_s):
                reply = await asyncio.wrap_future(ref.future())
        except TimeoutError:
            nodes = node_summary([n for n in ray.nodes() if n.get("Alive")])
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
