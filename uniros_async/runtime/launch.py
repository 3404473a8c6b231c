"""Starting a local worker process: ``python -m uniros_async.runtime`` in a fresh interpreter.

A worker is a process of its own that talks to its supervisor over the project's transports, so it needs nothing of
the agent's ``__main__``. It is started as ``python -m uniros_async.runtime`` (``runtime/__main__.py``), not with
multiprocessing's spawn, which re-imports the parent's main module in every worker: then a script without
``if __name__ == "__main__":`` would start workers recursively, code piped to ``python -`` or typed into a notebook
could not be re-imported at all, and a main script that imports torch would make every worker import torch too.

The start-up handshake uses two pipes: the worker reads its ``WorkerSpec`` (and the parent's ``sys.path``, so a
``"module:Id"`` next to the agent's script is found) from its stdin, and writes its listen URI to an inherited
pipe end (``--uri-fd``), read here as a ``multiprocessing.connection.Connection``. The worker's output goes where
the agent's goes.

A worker can be started in two steps: ``start_interpreter`` starts the interpreter, which imports what every
worker needs (gymnasium, numpy, the protocol) and then waits for its spec on stdin; ``WorkerProcess.send_spec``
hands the spec over. The supervisor starts the interpreters first and checks the env ids and keyword arguments
meanwhile (for a uniros env that check imports the task's module, ~0.3 s on one core), so the two overlap; a
check that fails stops the interpreters before any has a spec (``WorkerProcess.discard``). ``start_worker`` does
both steps at once.

``WorkerProcess`` stands in for ``multiprocessing.Process`` (``pid``, ``exitcode``, ``is_alive``, ``join``,
``terminate``, ``kill``, ``sentinel``). Workers still running when the agent's interpreter exits are terminated
(the ``atexit`` hook below, what multiprocessing does for daemonic children); a SIGKILLed agent is noticed by each
worker's parent-pid watchdog (runtime/worker.py).
"""

from __future__ import annotations

import atexit
import contextlib
import multiprocessing.connection
import os
import pickle
import subprocess
import sys
import threading
import weakref
from typing import Any

import uniros_async
from uniros_async.runtime.worker import WorkerSpec

__all__ = ["WorkerProcess", "found_libraries", "live_workers", "start_interpreter", "start_worker"]

_PACKAGE_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(uniros_async.__file__)))
"""The directory that holds the ``uniros_async`` package: first on the worker's PYTHONPATH, so ``python -m`` finds
this very copy of it even when the agent put it on ``sys.path`` by hand."""

_LIVE: weakref.WeakSet[WorkerProcess] = weakref.WeakSet()
_LIVE_LOCK = threading.Lock()


class WorkerProcess:
    """A worker started by ``start_worker``, with the part of ``multiprocessing.Process``'s interface the
    supervisor uses."""

    def __init__(self, popen: subprocess.Popen[bytes], name: str, environ: dict[str, str] | None = None) -> None:
        self._popen = popen
        self.name = name
        self.pid: int = popen.pid
        self._sentinel = -1
        self._environ = environ  # the agent's environment when the interpreter started

    def environ_changes(self) -> dict[str, str]:
        """The variables of this process's environment set or changed since the interpreter started (by the
        checks that ran meanwhile: a module imported there may set one, ``MUJOCO_GL`` say), for its spec's
        ``environ``. A variable removed meanwhile stays in the worker's environment."""
        if self._environ is None:
            return {}
        return {k: v for k, v in os.environ.items() if self._environ.get(k) != v and k != "PYTHONPATH"}

    def send_spec(self, spec: WorkerSpec) -> None:
        """Hand the interpreter its spec (once; ``start_interpreter``): it then starts serving ``spec``'s env."""
        stdin = self._popen.stdin
        if stdin is None or stdin.closed:
            raise RuntimeError(f"{self.name} has had its spec already")
        self.name = f"uniros-worker-{spec.index}"
        # sys.path first, in a pickle of its own: the spec's kwargs may name things from modules found only
        # through it
        payload = pickle.dumps(list(sys.path)) + pickle.dumps(spec, protocol=pickle.HIGHEST_PROTOCOL)
        try:
            stdin.write(payload)
            stdin.close()
        except BrokenPipeError:  # it exited already: the start-up pipe's EOF says so
            with contextlib.suppress(BrokenPipeError):
                stdin.close()

    def withdraw(self) -> None:
        """Stop an interpreter that has not had its spec, without waiting: its stdin closes (once its imports are
        done it would exit by itself, quietly) and SIGTERM ends it at once (it holds nothing yet: no env, no
        shared memory; a worker handles SIGTERM only once it serves)."""
        stdin = self._popen.stdin
        if stdin is not None and not stdin.closed:
            with contextlib.suppress(BrokenPipeError):
                stdin.close()
        self.terminate()

    def discard(self, timeout_s: float = 2.0) -> None:
        """``withdraw``, then wait until it has exited (at most ``timeout_s``, then kill)."""
        self.withdraw()
        self.join(timeout_s)
        if self.is_alive():
            self.kill()
            self.join(timeout_s)
        self.close()

    @property
    def exitcode(self) -> int | None:
        """None while it runs; its exit status (``-signum`` if a signal ended it) once it exited (reaped here)."""
        return self._popen.poll()

    def is_alive(self) -> bool:
        return self._popen.poll() is None

    def join(self, timeout: float | None = None) -> None:
        """Wait until it exits, at most ``timeout`` seconds (None: no bound)."""
        with contextlib.suppress(subprocess.TimeoutExpired):
            self._popen.wait(timeout)

    def terminate(self) -> None:
        """SIGTERM (the worker cancels its root task and closes its env)."""
        if self._popen.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self._popen.terminate()

    def kill(self) -> None:
        if self._popen.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self._popen.kill()

    @property
    def sentinel(self) -> int:
        """A file descriptor that becomes readable when the process exits (a pidfd), for ``add_reader``."""
        if self._sentinel < 0:
            self._sentinel = os.pidfd_open(self.pid)
        return self._sentinel

    def close(self) -> None:
        """Release the sentinel (the process itself is left as it is)."""
        if self._sentinel >= 0:
            os.close(self._sentinel)
            self._sentinel = -1

    def __del__(self) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<WorkerProcess {self.name} pid={self.pid} exitcode={self.exitcode}>"


def start_interpreter() -> tuple[WorkerProcess, multiprocessing.connection.Connection]:
    """Start a worker's interpreter (``python -m uniros_async.runtime``), which imports what every worker needs and
    waits for its spec (``WorkerProcess.send_spec``); return it with the pipe end on which it will send its listen
    URI (``Connection.recv``; EOFError if it exits before).

    Raises:
        OSError: the interpreter could not be started.
    """
    read_fd, write_fd = os.pipe()
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (_PACKAGE_ROOT, env.get("PYTHONPATH", "")) if p)
    try:
        popen = subprocess.Popen(
            [sys.executable, "-m", "uniros_async.runtime", "--uri-fd", str(write_fd)],
            stdin=subprocess.PIPE,
            pass_fds=(write_fd,),
            env=env,
            close_fds=True,
        )
    except BaseException:
        os.close(read_fd)
        raise
    finally:
        os.close(write_fd)
    proc = WorkerProcess(popen, f"uniros-worker-{popen.pid}", dict(os.environ))
    with _LIVE_LOCK:
        _LIVE.add(proc)
    return proc, multiprocessing.connection.Connection(read_fd, writable=False)


def start_worker(spec: WorkerSpec) -> tuple[WorkerProcess, multiprocessing.connection.Connection]:
    """Start a worker for ``spec`` (``start_interpreter``, then ``send_spec``) and return it with the pipe end on
    which it sends its listen URI (``Connection.recv``; EOFError if it exits before).

    Raises:
        OSError: the interpreter could not be started.
    """
    proc, conn = start_interpreter()
    try:
        proc.send_spec(spec)
    except BaseException:
        conn.close()
        proc.discard()
        raise
    return proc, conn


def found_libraries() -> dict[str, str]:
    """Environment variables that hand a local worker the shared libraries this process's imports have found.

    ``import mujoco`` imports ``glfw`` (for ``mujoco.GLContext``), which looks for libglfw by loading each candidate
    in a Python subprocess of its own to read its version: a second interpreter and an ``ldconfig -p`` in every
    process that imports MuJoCo. Where this process has made that search already, the worker
    is given its result (``PYGLFW_LIBRARY``, glfw's own setting) and loads the same library at once; a variable set
    by the user is left as it is.
    """
    found: dict[str, str] = {}
    glfw_library = sys.modules.get("glfw.library")
    path = getattr(getattr(glfw_library, "glfw", None), "_name", None)
    if isinstance(path, str) and path and "PYGLFW_LIBRARY" not in os.environ:
        found["PYGLFW_LIBRARY"] = path
    return found


def live_workers() -> list[WorkerProcess]:
    """The workers started here that still run."""
    with _LIVE_LOCK:
        return [p for p in _LIVE if p.is_alive()]


def read_spec(stream: Any) -> WorkerSpec | None:
    """The worker's side of ``send_spec``: read the spec from ``stream`` and take the parent's ``sys.path``; None
    when ``stream`` ends before anything was written (``discard``: no worker is needed after all).

    Raises:
        RuntimeError: the payload is not what ``send_spec`` writes.
    """
    try:
        path = pickle.load(stream)
    except EOFError:
        return None
    if not isinstance(path, list):
        raise RuntimeError(f"expected the parent's sys.path on stdin, got {type(path).__name__}")
    for p in reversed(path):
        if isinstance(p, str) and p not in sys.path:
            sys.path.insert(0, p)
    spec = pickle.load(stream)
    if not isinstance(spec, WorkerSpec):
        raise RuntimeError(f"expected a WorkerSpec on stdin, got {type(spec).__name__}")
    return spec


@atexit.register
def _stop_live_workers() -> None:
    """What multiprocessing does for daemonic children at exit: terminate what still runs, then kill."""
    procs = live_workers()
    for p in procs:
        p.terminate()
    for p in procs:
        p.join(2.0)
        if p.is_alive():
            p.kill()
            p.join(1.0)
