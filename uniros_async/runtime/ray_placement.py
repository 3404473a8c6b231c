"""Where Ray may place a worker: ``RayPlacement``, the ``worker`` keyword parsed into one, ``make_vec``'s
``backend``, and the cluster: ``connect`` (fails fast when no cluster answers) and ``check_placements`` (every
placement can be met by an alive node, checked before anything starts).

The placement holds what Ray schedules on: ``resources`` (a custom resource such as ``rx200_arm: 1`` that only the
PC wired to that arm advertises), ``node_id`` (a hard node affinity), ``num_cpus`` (default 1: a worker steps its
env on a core of its own) and the cluster ``address`` (default: the cluster this process is connected to, else
``$RAY_ADDRESS``, else the one ``ray start`` started on this machine). See runtime/ray_backend.py for the whole.

Ray is imported only when a Ray placement is used (``pip install 'uniros_async[ray]'``).
"""

from __future__ import annotations

import dataclasses
import os
import socket
from typing import Any

from uniros_async.errors import ConfigError

__all__ = [
    "BACKENDS",
    "RayPlacement",
    "apply_backend",
    "check_placements",
    "connect",
    "node_summary",
    "parse_ray_placement",
]

_RAY_CURRENT_CLUSTER = "/tmp/ray/ray_current_cluster"
"""Where ``ray start --head`` writes the address of the cluster it started (Ray's own ``address="auto"``)."""
_CONNECT_PROBE_S = 2.0
"""How long the tcp probe of a cluster's address may take before ``connect`` gives up on it."""
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


def node_summary(nodes: list[dict[str, Any]]) -> str:
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
            raise ConfigError(f"no alive Ray node has id {p.node_id!r}; nodes: {node_summary(nodes)}")
        if not any(all(n["Resources"].get(r, 0.0) >= a for r, a in wanted.items()) for n in candidates):
            missing = [r for r, a in wanted.items() if not any(n["Resources"].get(r, 0.0) >= a for n in candidates)]
            what = ", ".join(f"{r}: {wanted[r]}" for r in missing) or ", ".join(f"{r}: {a}" for r, a in wanted.items())
            raise ConfigError(
                f"no Ray node has the resources {what} (asked {wanted}"
                f"{f' on node {p.node_id}' if p.node_id else ''}); nodes: {node_summary(nodes)}"
            )
