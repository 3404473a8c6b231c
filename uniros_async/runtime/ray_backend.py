"""Workers placed by Ray: each env worker is started, on the node Ray's scheduler picks, by a small Ray actor.

This module gathers the Ray backend's public names; the backend is three modules: ``ray_placement`` (where: the
placement, the ``backend`` keyword, the cluster), ``ray_host`` (the actor on the worker's node) and
``ray_process`` (the agent's side of a worker an actor started).

A spec asks for Ray with the ``worker`` keyword (never passed to the env), or every spec at once with
``make_vec(..., backend="ray")`` / ``make(..., backend="ray")``::

    make_vec(["uniros/Ned2Reach-v0", ("uniros/Rx200Reach-v0", {"worker": {"ray": {"resources": {"rx200_arm": 1}}}})],
             backend="ray")

The placement (``RayPlacement``) holds what Ray schedules on: ``resources`` (a custom resource such as
``rx200_arm: 1`` that only the PC wired to that arm advertises), ``node_id`` (a hard node affinity), ``num_cpus``
(default 1: a worker steps its env on a core of its own) and the cluster ``address`` (default: the cluster this
process is connected to, else ``$RAY_ADDRESS``, else the one ``ray start`` started on this machine).

Ray only places and supervises; the step never goes through Ray. The actor (``ray_host.WorkerHost``, one per
worker process, ``max_restarts=0``) starts the worker process on its node exactly as the supervisor starts a local one
(``launch.start_worker``, its parent-pid watchdog then watching the actor), and answers with the worker's URI: shm
when the actor landed on the agent's own node, else ``tcp://<node ip>:0``. The agent connects to that URI directly
with a random key of its vector env (HMAC handshake, ``TransportOptions.auth_key``), and from then on the worker is
an ordinary one (``handle.WorkerHandle``); a step costs the transport's round trip, not a Ray call.

``ray_process.RayWorkerProcess`` stands for the worker process on the agent's side (``pid`` on its node, ``exitcode``,
``is_alive``), with the interface the supervisor uses for a worker it did not start itself: ``start``,
``lifeline_has_news`` (an attribute read: a completed ``wait_exit`` call of the actor, which returns the worker's
exit code when it ends, the node's loss when the actor sees its raylet end, and fails when the actor dies),
``poll_exit``, ``stop`` and ``aclose``.

Lifetime: a worker ends when its agent connection goes away (EOF, as for every worker), when its actor dies (the
parent-pid watchdog, at once), and on ``stop``: terminate, then kill, through the actor; then the actor is
killed (``ray.kill``). A node whose raylet ends (stopped, killed, the node going down) is lost: the actor watches
its raylet (``WorkerHost._watch_node``, a pidfd) and ends the worker at once, so its connection closes, and the
step in flight raises the worker's WorkerError within milliseconds, naming the node
(``StepExchange._take_replies`` watches the Ray-placed workers' tcp connections while it waits; docs/reliability.md).
A host that vanishes without closing its sockets is found by TCP keepalive (~5 s) or the call timeout.

Ray is imported only by these modules, and only when a Ray placement is used (``pip install 'uniros_async[ray]'``).
"""

from __future__ import annotations

from uniros_async.runtime.ray_placement import (
    BACKENDS,
    RayPlacement,
    apply_backend,
    check_placements,
    connect,
    parse_ray_placement,
)
from uniros_async.runtime.ray_process import RayWorkerProcess

__all__ = [
    "BACKENDS",
    "RayPlacement",
    "RayWorkerProcess",
    "apply_backend",
    "check_placements",
    "connect",
    "parse_ray_placement",
]
