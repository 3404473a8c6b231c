"""Env workers and the agent-side API over them: ``make`` (one env in a worker process) and ``make_vec`` (a
gymnasium VectorEnv, and through ``.as_sb3()`` an SB3 VecEnv, over one worker per env).

See docs/architecture.md: every env runs in a worker process of its own (``python -m uniros_async.runtime``) with
its own event loop; the agent side talks to it over ``shm://``; worker failures come back as WorkerError with the
worker's index and traceback.
A spec with a Ray placement (``worker="ray"``, ``{"ray": {...}}``, or ``backend="ray"``) runs on the node of a Ray
cluster that Ray's scheduler picks, and the agent steps it over tcp, or shm on its own node (runtime/ray_backend.py).

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
