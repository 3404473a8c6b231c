"""Env workers and the agent-side API over them: ``make`` (one env in a worker process) and ``make_vec`` (a
gymnasium VectorEnv, and through ``.as_sb3()`` an SB3 VecEnv, over one worker per env).

See docs/architecture.md: every env runs in a worker process of its own (``python -m uniros_async.runtime``) with
its own event loop; the agent side talks to it over ``shm://``; worker failures come back as WorkerError with the
worker's index and traceback.
A spec with ``worker="tcp://HOST:PORT"`` runs on a launcher on another host (``uniros worker serve``,
``serve_launcher``), over tcp (runtime/remote.py).
"""

from uniros_async.runtime.proxy import ProxyEnv, make
from uniros_async.runtime.remote import Launcher, RemoteWorker, serve_launcher
from uniros_async.runtime.supervisor import Supervisor
from uniros_async.runtime.vector import UnirosVectorEnv, make_vec

__all__ = [
    "Launcher",
    "ProxyEnv",
    "RemoteWorker",
    "Supervisor",
    "UnirosVectorEnv",
    "make",
    "make_vec",
    "serve_launcher",
]
