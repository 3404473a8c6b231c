"""The Ray rows of ``uniros bench throughput --backend ray``: workers placed by Ray against local ones and against a
plain Ray actor.

Rows (each a vector env of ``n`` sub-envs, stepped as the other rows are):

- ``uniros-ray``: ``make_vec(..., backend="ray")`` with every worker pinned to a node other than the agent's: Ray
  places and supervises, the step travels over our authenticated tcp;
- ``uniros-ray-local``: the same, pinned to the agent's own node: Ray places, the step travels over shm;
- ``uniros-tcp``: local workers over tcp on loopback (``transport="tcp"``), the figure ``uniros-ray`` is held to;
- ``ray-actor``: what a user would write first: the env inside a Ray actor on the other node, one actor method call
  (``ray.get(actor.step.remote(action))``) per sub-env per step, all sub-envs' calls in flight together.

The cluster: the one at ``--ray-address``, else a local one started here (a head, where the agent runs, and a
second node; ``ray.cluster_utils.Cluster``, small CPU counts, no dashboard, and without the background work of Ray's
daemons that the bench does not need: ``QUIET_SYSTEM_CONFIG``, ``QUIET_ENV``) and stopped at the end. On a shared
host, run the whole bench in a network namespace with only ``lo`` up, where Ray cannot bind the host's interfaces::

    unshare --net -- sh -c 'ip link set lo up && python -m uniros_async.cli bench throughput --backend ray'
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from uniros_async.bench._environ import environ_set
from uniros_async.errors import ConfigError

__all__ = ["QUIET_ENV", "QUIET_SYSTEM_CONFIG", "RAY_IMPLS", "RayRows", "local_cluster"]

RAY_IMPLS = ("uniros-ray", "uniros-ray-local", "uniros-tcp", "ray-actor")
_OBJECT_STORE_BYTES = 80 * 1024 * 1024
QUIET_SYSTEM_CONFIG: dict[str, Any] = {
    "enable_metrics_collection": False,  # no metrics recorded and exported by every process
    "memory_monitor_refresh_ms": 0,  # no reading of the node's memory use four times a second (Ray's OOM killer)
    "raylet_report_resources_period_milliseconds": 1000,  # each raylet's resource report: once a second, not ten
    "kill_idle_workers_interval_ms": 5000,  # each raylet's look for idle Ray workers to stop: every 5 s, not 0.2 s
    "task_events_report_interval_ms": 10000,  # the task events each process sends the GCS: every 10 s
    "prestart_worker_first_driver": False,  # no idle Ray workers started for the driver: its actors have their own
}
"""The Ray system config of the throughput bench's own cluster: what its daemons do on their own while the bench runs
takes the cores the physics bound assumes (``RayRows.start``; the CPU they take idle: docs/performance.md)."""
QUIET_ENV = {
    "RAY_USAGE_STATS_ENABLED": "0",
    "REPORTER_UPDATE_INTERVAL_MS": "60000",  # the dashboard agent's scan of the node's processes: once a minute
    "RAY_DASHBOARD_AGENT_CHECK_PARENT_INTERVAL_S": "2",  # its check that its raylet is alive: every 2 s, not 0.4 s
}
"""Environment of the throughput bench's cluster processes, read as they start (``QUIET_SYSTEM_CONFIG``)."""


@contextlib.contextmanager
def local_cluster(nodes: Sequence[dict[str, Any]], head_cpus: int = 2) -> Iterator[str]:
    """A local Ray cluster for the duration of the block: a head (where the agent runs) and one node per entry of
    ``nodes`` (``ray.cluster_utils.Cluster.add_node`` keywords, e.g. ``{"num_cpus": 2, "resources": {"rx200_pc":
    2}}``), no dashboard, small object stores; ``ray`` connected. Yields the head's address; stops every Ray process
    it started.

    Raises:
        ConfigError: Ray is not installed.
    """
    try:
        import ray
        from ray.cluster_utils import Cluster
    except ImportError as exc:
        raise ConfigError(f"--backend ray needs Ray: pip install 'uniros_async[ray]' ({exc})") from exc
    head = {"num_cpus": head_cpus, "include_dashboard": False, "object_store_memory": _OBJECT_STORE_BYTES}
    cluster = Cluster(initialize_head=True, head_node_args=head)
    try:
        for node in nodes:
            cluster.add_node(object_store_memory=_OBJECT_STORE_BYTES, **node)
        cluster.wait_for_nodes()
        from uniros_async.runtime.ray_backend import connect

        connect(cluster.address)
        yield str(cluster.address)
    finally:
        ray.shutdown()
        cluster.shutdown()  # type: ignore[no-untyped-call]


class _EnvActor:
    """An env inside a Ray actor (the ``ray-actor`` row)."""

    def __init__(self, env_id: str, kwargs: dict[str, Any]) -> None:
        from uniros_async.bench.envs import make_env

        self.env = make_env(env_id, kwargs)

    def reset(self, seed: int) -> Any:
        return self.env.reset(seed=seed)

    def step(self, action: Any) -> Any:
        return self.env.step(action)


class _ActorVec:
    """``n`` env actors stepped together: each step sends every sub-env's call, then waits for all."""

    def __init__(self, ray: Any, actors: list[Any]) -> None:
        self._ray = ray
        self.actors = actors

    def reset(self) -> Any:
        return self._ray.get([a.reset.remote(i) for i, a in enumerate(self.actors)])

    def step(self, actions: Any) -> Any:
        return self._ray.get([a.step.remote(actions[i]) for i, a in enumerate(self.actors)])

    def close(self) -> None:
        for a in self.actors:
            self._ray.kill(a, no_restart=True)


class RayRows:
    """The cluster the Ray rows run on, and their vector envs (``vector``); ``close`` stops what ``start`` started."""

    def __init__(self, address: str | None = None, *, quiet: bool = True) -> None:
        """``address``: a cluster to use, else ``start`` starts one, with ``QUIET_SYSTEM_CONFIG`` and ``QUIET_ENV``
        unless ``quiet`` is False (Ray's defaults: benchmarks/ray_idle_cpu.py compares the two)."""
        self.address = address
        self.quiet = quiet
        self._cluster: Any = None
        self._ray: Any = None
        self.agent_node = ""
        self.other_node = ""

    def start(self) -> None:
        """Connect to the cluster (or start a local one of two nodes) and pick a node other than the agent's.

        Raises:
            ConfigError: Ray is missing, no cluster answers at ``address``, or the cluster has one node only.
        """
        from uniros_async.runtime.ray_backend import connect

        if self.address is None:
            try:
                from ray.cluster_utils import Cluster
            except ImportError as exc:
                raise ConfigError(f"--backend ray needs Ray: pip install 'uniros_async[ray]' ({exc})") from exc
            head: dict[str, Any] = {
                "num_cpus": 2,
                "include_dashboard": False,
                "object_store_memory": _OBJECT_STORE_BYTES,
            }
            if self.quiet:
                head["include_log_monitor"] = False  # nothing here reads the workers' logs through the driver
                head["no_monitor"] = True  # no autoscaler: the cluster has the nodes it starts with
                head["_system_config"] = QUIET_SYSTEM_CONFIG
            with contextlib.ExitStack() as env:
                for name, value in QUIET_ENV.items() if self.quiet else ():
                    env.enter_context(environ_set(name, value))
                self._cluster = Cluster(initialize_head=True, head_node_args=head)
                self._cluster.add_node(num_cpus=2, object_store_memory=_OBJECT_STORE_BYTES)
                self._cluster.wait_for_nodes()
            self.address = self._cluster.address
        ray = self._ray = connect(self.address)
        self.agent_node = ray.get_runtime_context().get_node_id()
        others = [n["NodeID"] for n in ray.nodes() if n.get("Alive") and n["NodeID"] != self.agent_node]
        if not others:
            raise ConfigError(f"--backend ray needs a second node in the cluster at {self.address}; it has one")
        self.other_node = others[0]

    def describe(self) -> str:
        agent, other = self.agent_node[:12], self.other_node[:12]
        return f"Ray cluster at {self.address}: the agent on node {agent}, the remote rows' workers on node {other}"

    def vector(
        self, impl: str, n: int, env_id: str, kwargs: dict[str, Any], pad: bool, envs_per_worker: int = 1
    ) -> tuple[Any, Callable[[], Any], Callable[[Any], Any]]:
        """(vec env, reset(): seeds 0..n-1, step(actions)) for a Ray row; ``envs_per_worker``: make_vec's, for the
        rows of make_vec's Ray-placed workers."""
        from uniros_async.runtime import make_vec

        if impl == "uniros-tcp":
            venv = make_vec([env_id] * n, pad=pad, transport="tcp", **kwargs)
        elif impl in ("uniros-ray", "uniros-ray-local"):
            node = self.other_node if impl == "uniros-ray" else self.agent_node
            where = {"worker": {"ray": {"node_id": node, "num_cpus": 0}}}
            venv = make_vec([(env_id, where)] * n, pad=pad, backend="ray", envs_per_worker=envs_per_worker, **kwargs)
        elif impl == "ray-actor":
            from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

            cls = self._ray.remote(_EnvActor).options(
                num_cpus=0, scheduling_strategy=NodeAffinitySchedulingStrategy(self.other_node, soft=False)
            )
            vec = _ActorVec(self._ray, [cls.remote(env_id, kwargs) for _ in range(n)])
            return vec, vec.reset, vec.step
        else:
            raise ConfigError(f"unknown Ray row {impl!r}; expected one of {list(RAY_IMPLS)}")
        return venv, lambda: venv.reset(seed=0), venv.step

    def close(self) -> None:
        if self._ray is not None and self._cluster is not None:
            self._ray.shutdown()
        if self._cluster is not None:
            self._cluster.shutdown()
            self._cluster = None


def overhead_lines(records: list[dict[str, Any]], env_id: str) -> list[str]:
    """The goals of the Ray rows at one env: the Ray-placed worker's overhead against the local tcp worker's and
    against a Ray actor call per step (same run)."""
    rows = {r["impl"]: r for r in records if r["env"] == env_id and r["n_envs"] == 1 and not r.get("envs_in_turn")}
    if not all(k in rows for k in ("uniros-ray", "uniros-tcp", "ray-actor")):
        return []
    ray_us, tcp_us, actor_us = (float(rows[k]["overhead_us"]) for k in ("uniros-ray", "uniros-tcp", "ray-actor"))
    ratio_tcp = ray_us / tcp_us if tcp_us > 0 else float(np.inf)
    ratio_actor = ray_us / actor_us if actor_us > 0 else float(np.inf)
    return [
        f"{env_id}, N=1: Ray-placed worker over tcp {ray_us:.1f} us/step overhead = {ratio_tcp:.2f}x the local tcp"
        f" worker's ({tcp_us:.1f} us; goal <= 1.5x) and {ratio_actor:.3f}x a Ray actor call per step"
        f" ({actor_us:.1f} us; goal <= 0.2x)"
    ]
