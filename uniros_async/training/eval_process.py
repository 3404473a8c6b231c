"""The evaluation process of ``eval.alongside``: the evaluation arms' vector env and a copy of the policy, in a
process of their own.

Why a process: an evaluation acts on real-time arms, so each of its actions must leave as soon as the arms' last
observations arrive. On a thread of the agent process it shares the GIL with the asynchronous learner
(async_td3.py), whose update steps run Python between torch's kernels: when the arms' observations arrive during
an update, the evaluation thread waits for the GIL whatever its OS priority (the real-time class decides who gets
a core, not who gets the GIL), and its arms' action cycles spread by up to a switch interval and more. The learner
yields to the acting thread of training (async_td3.py), whose cycle it can see; yielding to a second actor on a
cycle of its own as well would need the learner to keep clear of both. In a process of its own the evaluation has
its own interpreter and needs no such coordination: no learner step can hold its GIL. ``benchmarks/agent_realtime.py``
measures the process against the thread in one run (docs/performance.md, "The agent process in real time").

The process (``open_eval_process``) is a fresh interpreter, started as the env workers are (runtime/launch.py: not
multiprocessing's spawn, which would re-import the agent's main script), its spec and the agent's ``sys.path`` read from
its stdin. It ignores SIGINT (the agent's Ctrl-C is the agent's business, which closes it) and closes its envs on
SIGTERM; it opens the envs with ``open_concurrent_env`` (their workers are its children and stop when it exits), sets
torch to the agent's thread count, freezes its heap once set up (``priority.freeze_heap``) and then evaluates one
request at a time, on its main thread, in the real-time class when asked (``priority.real_time_thread``, as the agent's
acting thread). Its envs' loops rank below the training envs' or above them, as ``eval.alongside_rank`` says
(``make_vec``'s ``rt_rank_base``, ``alongside.rank_bases``), and tick in phases of their own (``loop_phase_base``,
``alongside.phase_bases``): with the same ranks, an evaluation arm's loop and a training arm's would tick and return on
the same instants at the same priority, and on a shared host one would wait for the other. A second thread only reads
the connection (blocked in ``recv`` without the GIL) and wakes only when the agent writes: a request, a stop or the
close. When the agent's end closes (the agent died), it stops the evaluation and closes the envs; if that has not ended
the process within ``ORPHAN_EXIT_S``, it exits anyway.

Messages (pickled tuples on one socket pair, ``multiprocessing.connection.Connection`` at both ends)::

    child:  ("ready", labels) | ("failed", error)                                   start-up
    agent:  ("evaluate", rid, EvalRequest) | ("stop", rid) | ("close",)
    child:  ("done", rid, results, timing window, real_time) | ("stopped", rid) | ("error", rid, error)

A request carries the policy's weights as numpy arrays (its actor's, for TD3's policies), the policy's class and
constructor arguments when the process has not seen that policy yet, and the observation statistics frozen at the
same step (``normalize_obs``). Progress is a step counter in shared memory (8 bytes of a memfd both map: no file
left behind), raised after every vector step and reset: every wait of the agent on the process ends when the process
exits, or when the counter has not moved for ``STALL_S``. An evaluation process still running when the agent's
interpreter exits is closed then (``atexit``).
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import logging
import mmap
import multiprocessing.connection
import os
import pickle
import queue
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
import traceback
import weakref
from collections.abc import Sequence
from typing import Any

import uniros_async
from uniros_async.errors import EvaluationStopped, UnirosError, WorkerError

__all__ = [
    "CLOSE_S",
    "ORPHAN_EXIT_S",
    "STALL_S",
    "EvalProcess",
    "EvalReply",
    "EvalRequest",
    "open_eval_process",
    "serve",
]

logger = logging.getLogger(__name__)

STALL_S = 60.0
"""How long the agent waits for an evaluation that makes no progress (no vector step, no reset) before it gives up:
longer than a reset of an emulated real arm or a worker's step deadline."""
CLOSE_S = 60.0
"""How long closing waits for the process to close its envs and exit, before it is terminated."""
ORPHAN_EXIT_S = 30.0
"""How long the process, once the agent is gone, gives its envs to close before it exits anyway."""
READY_MARGIN_S = 60.0
"""Added to the envs' start timeout for the process's own start-up (imports) when waiting for it to be ready."""

_PACKAGE_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(uniros_async.__file__)))
"""First on the process's PYTHONPATH, so that it imports this copy of ``uniros_async`` (as the workers do)."""
_LIVE: weakref.WeakSet[EvalProcess] = weakref.WeakSet()


@dataclasses.dataclass(frozen=True, kw_only=True)
class EvalRequest:
    """One evaluation: the policy at one step and what to evaluate it on."""

    weights: dict[str, Any]
    """The state dict (numpy arrays) of the policy's actor (``policy.actor``), or of the policy if it has none."""
    skeleton: tuple[type, dict[str, Any]] | None
    """The policy's class and constructor arguments, when the process has not built this policy yet."""
    obs_stats: Any
    """Frozen observation statistics (a VecNormalize without its env), or None."""
    episodes: int
    seed: int


@dataclasses.dataclass(frozen=True, kw_only=True)
class EvalReply:
    """The answer to one request: ``results`` (EvalResults, one per env) and the timing window of its steps, or
    ``error``; ``stopped`` when it was stopped before its end."""

    rid: int
    results: list[Any] = dataclasses.field(default_factory=list)
    window: dict[str, dict[str, list[float]]] = dataclasses.field(default_factory=dict)
    real_time: bool = False
    stopped: bool = False
    error: BaseException | None = None


@dataclasses.dataclass(frozen=True, kw_only=True)
class _Spec:
    specs: tuple[tuple[str, str, dict[str, Any]], ...]
    env_ids: tuple[str, ...]
    real_time: bool
    torch_threads: int
    start_timeout_s: float
    rt_rank_base: int
    loop_phase_base: int | None
    task_id: bool
    sys_path: tuple[str, ...]


class _Counter:
    """The progress counter: one signed 64-bit integer in a shared mapping of a memfd."""

    def __init__(self, fd: int) -> None:
        self._map = mmap.mmap(fd, 8)

    @property
    def value(self) -> int:
        return int(struct.unpack_from("q", self._map, 0)[0])

    @value.setter
    def value(self, n: int) -> None:
        struct.pack_into("q", self._map, 0, n)

    def close(self) -> None:
        self._map.close()


# ---------------------------------------------------------------- errors across the pipe


def _portable(exc: BaseException) -> tuple[Any, ...]:
    """``exc`` in a form the agent can rebuild: itself when it survives a pickle round trip, else its parts."""
    tb = "".join(traceback.format_exception(exc))
    try:
        pickle.loads(pickle.dumps(exc))
    except Exception:  # noqa: BLE001 - e.g. keyword-only constructor arguments
        if isinstance(exc, WorkerError):
            message = str(exc).removeprefix(f"worker {exc.index}: ")
            return ("worker", type(exc), exc.index, message, exc.remote_traceback or tb)
        return ("other", f"{type(exc).__name__}: {exc}", tb)
    return ("pickled", exc, tb)


def _rebuilt(parts: tuple[Any, ...]) -> BaseException:
    kind = parts[0]
    if kind == "pickled":
        exc: BaseException = parts[1]
    elif kind == "worker":
        _, cls, index, message, tb = parts
        return cls(index, f"{message} (in the evaluation process)", remote_traceback=tb)  # type: ignore[no-any-return]
    else:
        exc = UnirosError(f"the evaluation process failed: {parts[1]}")
    exc.add_note(f"in the evaluation process:\n{parts[2]}")
    return exc


# ---------------------------------------------------------------- the process


class _PolicyCopy:
    """What ``evaluate_vec_policy`` asks of a model: the process's policy and the request's statistics."""

    def __init__(self, policy: Any, stats: Any) -> None:
        self.policy = policy
        self.stats = stats

    def predict(self, observation: Any, deterministic: bool = True) -> tuple[Any, None]:
        actions, _ = self.policy.predict(observation, deterministic=deterministic)
        return actions, None

    def get_vec_normalize_env(self) -> Any:
        return self.stats


class _Commands:
    """The pipe's reader (a thread of the process): requests and the close go to ``queue``, a stop sets the event
    of the request it names (now or when that request begins); the agent gone counts as a close."""

    def __init__(self, conn: multiprocessing.connection.Connection) -> None:
        self.conn = conn
        self.queue: queue.SimpleQueue[tuple[Any, ...]] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._stopped_upto = -1
        self._current: tuple[int, threading.Event] | None = None

    def begin(self, rid: int) -> threading.Event:
        """The stop event of request ``rid``, now under way (set already if it was stopped before it began)."""
        event = threading.Event()
        with self._lock:
            self._current = (rid, event)
            if rid <= self._stopped_upto:
                event.set()
        return event

    def _stop(self, rid: int) -> None:
        with self._lock:
            self._stopped_upto = max(self._stopped_upto, rid)
            if self._current is not None and self._current[0] <= self._stopped_upto:
                self._current[1].set()

    def run(self) -> None:
        while True:
            try:
                msg = self.conn.recv()
            except (EOFError, OSError):  # the agent is gone
                self._stop(1 << 62)
                self.queue.put(("close",))
                time.sleep(ORPHAN_EXIT_S)
                os._exit(1)
            if msg[0] == "stop":
                self._stop(int(msg[1]))
                continue
            if msg[0] == "close":
                self._stop(1 << 62)
                self.queue.put(msg)
                return
            self.queue.put(msg)


def _load(policy: Any, request: EvalRequest) -> Any:
    """The process's policy with the request's weights (built first if the request brings a skeleton)."""
    import torch

    if request.skeleton is not None:
        cls, kwargs = request.skeleton
        policy = cls(**kwargs)
        policy.set_training_mode(False)
    if policy is None:
        raise UnirosError("an evaluation request without the policy's class, and no policy built before it")
    module = getattr(policy, "actor", policy)
    module.load_state_dict({k: torch.from_numpy(v) for k, v in request.weights.items()})
    return policy


def serve() -> None:
    """The process's entry point (``python -c``, argv: the connection's and the counter's descriptors): read the
    spec from stdin, then ``_child_main``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def on_term(signum: int, frame: Any) -> None:
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, on_term)
    spec = pickle.load(sys.stdin.buffer)
    if not isinstance(spec, _Spec):
        raise RuntimeError(f"expected the evaluation process's spec on stdin, got {type(spec).__name__}")
    for path in reversed(spec.sys_path):  # a "module:Id" env beside the agent's script is found
        if path not in sys.path:
            sys.path.insert(0, path)
    conn = multiprocessing.connection.Connection(int(sys.argv[1]))
    progress = _Counter(int(sys.argv[2]))
    try:
        _child_main(spec, conn, progress)
    finally:
        progress.close()


def _child_main(spec: _Spec, conn: multiprocessing.connection.Connection, progress: _Counter) -> None:
    """Open the envs, then evaluate requests until closed (see the module docstring)."""
    import torch
    from stable_baselines3.common.vec_env import VecEnvWrapper

    from uniros_async.priority import freeze_heap, real_time_thread
    from uniros_async.training.concurrent import open_concurrent_env
    from uniros_async.training.evaluate import evaluate_vec_policy

    torch.set_num_threads(spec.torch_threads)

    class Counted(VecEnvWrapper):
        def reset(self) -> Any:
            out = self.venv.reset()
            progress.value += 1
            return out

        def step_wait(self) -> Any:
            out = self.venv.step_wait()
            progress.value += 1
            return out

    try:
        venv = open_concurrent_env(
            spec.specs,
            start_timeout_s=spec.start_timeout_s,
            rt_rank_base=spec.rt_rank_base,
            loop_phase_base=spec.loop_phase_base,
            task_id=spec.task_id,
        )
    except BaseException as exc:  # noqa: BLE001 - reported to the agent
        with contextlib.suppress(OSError):
            conn.send(("failed", _portable(exc)))
        return
    try:
        counted = Counted(venv)
        commands = _Commands(conn)
        threading.Thread(target=commands.run, name="uniros-eval-commands", daemon=True).start()
        conn.send(("ready", list(venv.labels)))
        freeze_heap()
        policy: Any = None
        while True:
            msg = commands.queue.get()
            if msg[0] == "close":
                break
            _, rid, request = msg
            stop = commands.begin(rid)
            reply: tuple[Any, ...]
            try:
                policy = _load(policy, request)
                with real_time_thread() if spec.real_time else contextlib.nullcontext(False) as rt:
                    results = evaluate_vec_policy(
                        _PolicyCopy(policy, request.obs_stats),
                        counted,
                        request.episodes,
                        venv.labels,
                        seed=request.seed,
                        env_ids=spec.env_ids,
                        stop=stop,
                    )
                reply = ("done", rid, results, venv.timing_window(), rt)
            except EvaluationStopped:
                venv.restart_window()  # a stopped evaluation's timing is not kept
                reply = ("stopped", rid)
            except Exception as exc:  # noqa: BLE001 - reported to the agent, which raises it
                reply = ("error", rid, _portable(exc))
            try:
                conn.send(reply)
            except OSError:  # the agent is gone; the reader closes us
                continue
    finally:
        venv.close()
        conn.close()


# ---------------------------------------------------------------- the agent's side


class EvalProcess:
    """The agent's handle on an evaluation process (``open_eval_process``): one request at a time."""

    def __init__(
        self, process: subprocess.Popen[bytes], conn: multiprocessing.connection.Connection, progress: _Counter
    ) -> None:
        self.process = process
        self.labels: list[str] = []
        self._conn = conn
        self._progress = progress
        self._rid = 0
        self._seen = (-1, time.monotonic())  # the progress counter's last value and when it was first seen
        self._closed = False
        _LIVE.add(self)

    @property
    def pid(self) -> int:
        """The process's id."""
        return self.process.pid

    def submit(self, request: EvalRequest) -> int:
        """Send ``request``; returns its id (``poll``, ``wait`` and ``stop`` take it).

        Raises:
            UnirosError: the process has exited.
        """
        self._rid += 1
        try:
            self._conn.send(("evaluate", self._rid, request))
        except OSError as exc:
            raise self._gone() from exc
        self._seen = (int(self._progress.value), time.monotonic())
        return self._rid

    def poll(self, rid: int, timeout_s: float = 0.0) -> EvalReply | None:
        """The reply to request ``rid`` if it has come within ``timeout_s``, else None.

        Raises:
            UnirosError: the process exited, or made no progress for ``STALL_S``.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                ready = self._conn.poll(max(deadline - time.monotonic(), 0.0))
                msg = self._conn.recv() if ready else None
            except (EOFError, OSError) as exc:
                raise self._gone() from exc
            if msg is None:
                self._check_alive()
                return None
            if msg[1] != rid:  # the late answer to a request given up before
                continue
            if msg[0] == "done":
                return EvalReply(rid=rid, results=msg[2], window=msg[3], real_time=bool(msg[4]))
            if msg[0] == "stopped":
                return EvalReply(rid=rid, stopped=True)
            return EvalReply(rid=rid, error=_rebuilt(msg[2]))

    def wait(self, rid: int) -> EvalReply:
        """Block until the reply to request ``rid`` (see ``poll`` for the errors)."""
        while True:
            reply = self.poll(rid, timeout_s=1.0)
            if reply is not None:
                return reply

    def stop(self, rid: int) -> None:
        """Stop request ``rid`` (it ends before its next step) and wait for its end, at most ``CLOSE_S``."""
        try:
            self._conn.send(("stop", rid))
        except OSError as exc:
            raise self._gone() from exc
        deadline = time.monotonic() + CLOSE_S
        while self.poll(rid, timeout_s=1.0) is None:
            if time.monotonic() > deadline:
                raise UnirosError(f"the evaluation process did not stop its evaluation within {CLOSE_S:.0f} s")

    def close(self) -> None:
        """Ask the process to close its envs and exit; terminate it if it has not within ``CLOSE_S`` (then kill it
        if SIGTERM did not end it). Idempotent."""
        if self._closed:
            return
        self._closed = True
        _LIVE.discard(self)
        with contextlib.suppress(OSError):
            self._conn.send(("close",))
        for stop, wait_s in ((None, CLOSE_S), (self.process.terminate, 10.0), (self.process.kill, 5.0)):
            if stop is not None:
                logger.warning("the evaluation process did not exit; %s", stop.__name__)
                stop()
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.process.wait(wait_s)
                break
        self._conn.close()
        self._progress.close()

    def _check_alive(self) -> None:
        if self.process.poll() is not None:
            raise self._gone()
        value, since = self._seen
        now = time.monotonic()
        if int(self._progress.value) != value:
            self._seen = (int(self._progress.value), now)
        elif now - since > STALL_S:
            raise UnirosError(f"the evaluation process made no progress (no step, no reset) for {STALL_S:.0f} s")

    def _gone(self) -> UnirosError:
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.process.wait(1.0)
        return UnirosError(f"the evaluation process exited (exit code {self.process.returncode})")


@atexit.register
def _close_live() -> None:
    """Close the evaluation processes still running when the interpreter exits."""
    for handle in list(_LIVE):
        with contextlib.suppress(Exception):
            handle.close()


def open_eval_process(
    specs: Sequence[tuple[str, str, dict[str, Any]]],
    *,
    real_time: bool,
    torch_threads: int = 1,
    start_timeout_s: float = 120.0,
    rt_rank_base: int = 0,
    loop_phase_base: int | None = None,
    task_id: bool = False,
) -> EvalProcess:
    """Start an evaluation process over the envs ``specs`` ((label, id, kwargs), as ``open_concurrent_env``) and
    wait until its envs are up.

    Args:
        specs: the envs, as the training envs of the run.
        real_time: evaluate in the real-time class (``priority.real_time_thread``).
        torch_threads: torch's thread count in the process.
        start_timeout_s: the envs' start timeout (``make_vec``).
        rt_rank_base: the lowest real-time rank of the envs' loops (``make_vec``).
        loop_phase_base: the lowest tick phase of the envs' loops (``make_vec``).
        task_id: a one-hot env index in every observation, as the training envs have it (``task_id_in_obs``).

    Raises:
        ConfigError, WorkerError: what opening the envs raised in the process.
        UnirosError: the process exited, or was not ready within ``start_timeout_s`` + ``READY_MARGIN_S``.
    """
    spec = _Spec(
        specs=tuple((label, env_id, dict(kw)) for label, env_id, kw in specs),
        env_ids=tuple(env_id for _, env_id, _ in specs),
        real_time=real_time,
        torch_threads=torch_threads,
        start_timeout_s=start_timeout_s,
        rt_rank_base=rt_rank_base,
        loop_phase_base=loop_phase_base,
        task_id=task_id,
        sys_path=tuple(p for p in sys.path if isinstance(p, str)),
    )
    ours, theirs = socket.socketpair()
    counter_fd = os.memfd_create("uniros-eval-progress")
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (_PACKAGE_ROOT, env.get("PYTHONPATH", "")) if p)
    progress: _Counter | None = None
    try:
        os.ftruncate(counter_fd, 8)
        progress = _Counter(counter_fd)
        proc = subprocess.Popen(
            [
                sys.executable,
                "-c",
                "from uniros_async.training.eval_process import serve; serve()",
                str(theirs.fileno()),
                str(counter_fd),
            ],
            stdin=subprocess.PIPE,
            pass_fds=(theirs.fileno(), counter_fd),
            env=env,
        )
    except BaseException:
        ours.close()
        if progress is not None:
            progress.close()
        raise
    finally:
        theirs.close()
        os.close(counter_fd)
    handle = EvalProcess(proc, multiprocessing.connection.Connection(ours.detach()), progress)
    try:
        assert proc.stdin is not None
        with contextlib.suppress(BrokenPipeError):  # it exited at once: told below
            proc.stdin.write(pickle.dumps(spec))
        with contextlib.suppress(BrokenPipeError):
            proc.stdin.close()
        conn = handle._conn
        wait_s = start_timeout_s + READY_MARGIN_S
        if not conn.poll(wait_s):
            raise UnirosError(f"the evaluation process was not ready within {wait_s:.0f} s")
        try:
            msg = conn.recv()
        except (EOFError, OSError) as exc:
            raise handle._gone() from exc
        if msg[0] == "failed":
            raise _rebuilt(msg[1])
        handle.labels = list(msg[1])
    except BaseException:
        handle.close()
        raise
    return handle
