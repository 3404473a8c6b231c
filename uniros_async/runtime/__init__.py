"""Env workers and the agent-side API over them: ``make_vec`` (a gymnasium VectorEnv, and through ``.as_sb3()`` an
SB3 VecEnv, over worker processes) and ``make`` (one env in a worker process of its own).

``make`` is not ``gymnasium.make``: ``gymnasium.make(id)`` builds the env in the calling process, while
``uniros_async.make(id)`` starts a worker process, builds the env there and returns a ``ProxyEnv`` that forwards
``reset``, ``step`` and ``call`` to it (``make(id, in_process=True)`` returns ``gymnasium.make``'s env instead).

See docs/architecture.md: every env runs in a worker process (``python -m uniros_async.runtime``) with its own
event loop, one process per env or, where accelerated envs outnumber the cores, one per core hosting several
(``make_vec(envs_per_worker="auto")``, runtime/specs.py); the agent side talks to each env over ``shm://``; worker
failures come back as WorkerError with the worker's index and traceback, a request that gets no reply in time as
StepTimeoutError.
A spec with a Ray placement (``worker="ray"``, ``{"ray": {...}}``, or ``backend="ray"``) runs on the node of a Ray
cluster that Ray's scheduler picks, and the agent steps it over tcp, or shm on its own node (runtime/ray_backend.py).

The modules: ``vector`` and ``sb3`` (the vector envs), ``spaces`` (one space over the sub-envs'), ``proxy``
(``make``), ``specs`` (what ``make_vec`` is given, and which envs share a process), ``supervisor`` (starting,
restarting and stopping the workers), ``exchange`` and ``handle`` (requests out, replies in), ``hangup`` (a
Ray-placed worker's connection ending mid-step), ``worker``, ``cores``, ``protocol`` and ``launch`` (the worker
process), ``envargs`` (checks of ids and kwargs), and ``ray_placement``, ``ray_host`` and ``ray_process`` (workers
placed by Ray).

Names are imported lazily: a worker process, which runs ``python -m uniros_async.runtime`` and so imports this
package first, loads only its own modules (worker.py, protocol.py), not the agent side (supervisor, vector env).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from uniros_async._lazy import lazy_exports

if TYPE_CHECKING:
    from uniros_async.runtime.proxy import ProxyEnv, make
    from uniros_async.runtime.supervisor import Supervisor
    from uniros_async.runtime.vector import UnirosVectorEnv, make_vec

__all__ = [
    "ProxyEnv",
    "Supervisor",
    "UnirosVectorEnv",
    "make",
    "make_vec",
]

_WHERE = {
    "ProxyEnv": "proxy",
    "Supervisor": "supervisor",
    "UnirosVectorEnv": "vector",
    "make": "proxy",
    "make_vec": "vector",
}

__getattr__, __dir__ = lazy_exports(__name__, _WHERE)
