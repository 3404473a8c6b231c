"""Scheduling priority of real-time loops (env loops on the wall clock, servo sims, an agent's acting thread).

On a shared 2-core machine the env loop's timer fires on time only if its thread gets a core when it wakes; a
learner, a test suite or another env loop beside it delays that by a scheduler slice, even at
nice -10. As ros2_control does for its control loops, such a loop asks for a real-time scheduling class,
``SCHED_RR`` at a low priority (10): it then preempts every ordinary thread when its timer fires. These loops
sleep between ticks (a tick is well under a millisecond of work, physics included), and the kernel's real-time
throttling (``sched_rt_runtime_us``) keeps 5 % of every core for ordinary threads even if one misbehaved.
Accelerated (sim clock) workers, which compute flat out, and workers of envs without an env loop (a gymnasium
CartPole, stepped as fast as its agent asks) never ask; accelerated workers that outnumber the cores ask for the
opposite, ``SCHED_BATCH`` and a long slice (``run_steps_through``), so each runs its step in one go.

The class belongs to the thread that runs the loop, from the moment the loop is ready, and to nothing else:

- **Taken once start-up is done** (``raise_loop_priority`` is called by the worker after its env is built, by a
  servo sim once it serves): start-up is seconds of flat-out CPU (imports, the MuJoCo model, the arm's own
  process). In the real-time class it would run above every ordinary thread and, at the priority of an equal-rank
  loop, take turns with that loop in ``SCHED_RR``'s 100 ms slices: with the class taken at process start, four
  workers starting kept the lowest-ranked env loop of a running vector env off its core for tens of milliseconds
  (a kernel scheduler trace; docs/reliability.md).
- **Not inherited** (``SCHED_RESET_ON_FORK``): threads and processes a real-time thread starts (a learner thread,
  torch's intra-op pool, a servo sim process, a test's subprocess) begin in the ordinary class. Without the flag
  a thread pool that a real-time acting thread creates with its first parallel operation runs its workers at the
  acting thread's priority, above every env loop.
- **Per thread**: ``sched_setscheduler`` on Linux applies to one thread (``thread_id``; 0: the caller). Threads
  that the start-up itself started to deliver to the loop (a ROS 2 arm's cyclonedds receive threads) are named
  by id and get the loop's class too (``thread_ids`` before and after).

A loop's thread also runs its process's cyclic garbage collector whenever an allocation triggers it, and a full
collection walks every object the process holds (tens of thousands for a reach env's process): a tick due
meanwhile waits, whatever the class. Loop processes call ``freeze_heap`` once start-up is done, so that full
collections walk only what was made since.

The workers of one vector env get distinct priorities (``raise_loop_priority(rank)``: the first the highest, up to
``MAX_LOOP_RANK`` above the base), and an agent's acting thread (``real_time_thread``) one above them all. A step's
actions wake every worker at once; with fewer cores than workers they then run one after the other, and at equal
priority in whatever order the scheduler picks, so each env gets its action at a different point of each action
cycle. Ranked, they run in a fixed order and each env's action arrives at the same point every cycle (for the four
envs of ``uniros bench latency`` on 2 cores, git's docs/perf/history.md has the spread of when the action reached each
env loop, with and without ranks). The acting thread above them hands out all actions before the first woken
worker can take its core.

Both need root or CAP_SYS_NICE: without it the thread falls back to a lower nice value, and without that keeps
its priority (a debug log says so). ``UNIROS_LOOP_PRIORITY`` chooses: ``rt`` (default: SCHED_RR, else nice),
``nice`` (nice -10 only), ``off``. ``thread_scheduling`` reads back what every thread of a process has.
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import logging
import os
import platform
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence

__all__ = [
    "ACTOR_GIL_SWITCH_S",
    "ACTOR_RT_PRIORITY",
    "cores_kept_awake",
    "cores_kept_from_halting",
    "cores_kept_polling",
    "DEFAULT_LOOP_NICE",
    "environ_choice",
    "freeze_heap",
    "LOOP_RT_PRIORITY",
    "MAX_LOOP_RANK",
    "RESET_ON_FORK",
    "gil_switch_interval",
    "loop_nice",
    "loop_priority_mode",
    "raise_loop_priority",
    "real_time_thread",
    "reap",
    "run_steps_through",
    "STEP_SLICE_NS",
    "thread_ids",
    "thread_scheduling",
]

logger = logging.getLogger(__name__)

DEFAULT_LOOP_NICE = -10
ACTOR_GIL_SWITCH_S = 0.0005
"""The GIL switch interval while a real-time acting thread shares its process with a learner thread (Python's
default: 5 ms): a learner that holds the GIL when the acting thread wakes for the next step keeps it this long."""
LOOP_RT_PRIORITY = 10
MAX_LOOP_RANK = 15
"""Ranks above ``LOOP_RT_PRIORITY`` that loop processes may take (``raise_loop_priority(rank)``)."""
ACTOR_RT_PRIORITY = LOOP_RT_PRIORITY + MAX_LOOP_RANK + 1
"""The acting thread's SCHED_RR priority (``real_time_thread``): above every loop process."""
MODES = ("rt", "nice", "off")
STEP_SLICE_NS = 20_000_000
"""The scheduler slice ``run_steps_through`` asks for: longer than an accelerated rx200 or ned2 step, so a worker runs
its step in one go."""
_SCHED_SETATTR = {"x86_64": 314, "aarch64": 274}
"""``sched_setattr``'s syscall number (no Python wrapper); elsewhere only the policy is changed."""
RESET_ON_FORK: int = getattr(os, "SCHED_RESET_ON_FORK", 0)
"""``os.SCHED_RESET_ON_FORK`` (Linux), or'd into the policy: threads and processes the thread starts do not
inherit its real-time class or negative nice value."""


def environ_choice(name: str, choices: Sequence[str], default: str) -> str:
    """The environment variable ``name``, stripped and lower-cased, one of ``choices``; unset or empty: ``default``.

    Raises:
        ConfigError: another value (the message names the variable, the choices and the value).
    """
    from uniros_async.errors import ConfigError

    raw = os.environ.get(name, default).strip().lower() or default
    if raw not in choices:
        raise ConfigError(f"{name} must be one of {tuple(choices)}, got {raw!r}")
    return raw


def loop_priority_mode() -> str:
    """``UNIROS_LOOP_PRIORITY`` (default ``rt``).

    Raises:
        ConfigError: not one of ``rt``, ``nice``, ``off``.
    """
    return environ_choice("UNIROS_LOOP_PRIORITY", MODES, "rt")


def loop_nice() -> int | None:
    """The nice value asked for by ``UNIROS_LOOP_NICE`` (default -10), or None when disabled.

    Raises:
        ValueError: the variable is neither an integer in [-20, 19] nor ``off``.
    """
    raw = os.environ.get("UNIROS_LOOP_NICE", "").strip().lower()
    if raw in ("", "default"):
        return DEFAULT_LOOP_NICE
    if raw in ("off", "0", "none"):
        return None
    try:
        value = int(raw)
    except ValueError:
        raise ValueError(f"UNIROS_LOOP_NICE must be an integer in [-20, 19] or 'off', got {raw!r}") from None
    if not -20 <= value <= 19:
        raise ValueError(f"UNIROS_LOOP_NICE must be an integer in [-20, 19] or 'off', got {value}")
    return value


def freeze_heap() -> None:
    """Collect, then move everything this process holds out of the cyclic collector's reach (``gc.freeze``): its
    modules, its env, its MuJoCo model. Called once a loop process's start-up is done; later full collections walk
    only the objects made after it (see the module docstring)."""
    gc.collect()
    gc.freeze()


def raise_loop_priority(rank: int = 0, *, thread_id: int = 0) -> str | None:
    """Put one thread of a real-time loop in the real-time class (see the module docstring): SCHED_RR at
    ``LOOP_RT_PRIORITY + rank`` (``rank`` clipped to [0, ``MAX_LOOP_RANK``]; a nice value ignores it), with
    ``SCHED_RESET_ON_FORK``. Call it from the loop once its start-up is done.

    Args:
        rank: the loop's rank among the loops of one vector env (0: the lowest priority).
        thread_id: the native id of the thread (``threading.get_native_id()``, ``Thread.native_id``); 0: the
            calling thread.

    Returns:
        ``"rt"`` (SCHED_RR), ``"nice"`` (a lower nice value) or None (unchanged: disabled or not permitted).
    """
    mode = loop_priority_mode()
    if mode == "off":
        return None
    if mode == "rt" and hasattr(os, "sched_setscheduler"):
        prio = LOOP_RT_PRIORITY + min(max(rank, 0), MAX_LOOP_RANK)
        try:
            os.sched_setscheduler(thread_id, os.SCHED_RR | RESET_ON_FORK, os.sched_param(prio))
            return "rt"
        except PermissionError:
            logger.debug("not permitted to use SCHED_RR (needs root or CAP_SYS_NICE); trying nice")
    want = loop_nice()
    if want is None or not hasattr(os, "setpriority"):
        return None
    try:
        if os.getpriority(os.PRIO_PROCESS, thread_id) <= want:  # on Linux: that thread's nice value
            return None
        if hasattr(os, "sched_setscheduler") and os.sched_getscheduler(thread_id) == os.SCHED_OTHER:
            # what it starts begins at nice 0 (setting the flag needs no privilege)
            os.sched_setscheduler(thread_id, os.SCHED_OTHER | RESET_ON_FORK, os.sched_param(0))
        os.setpriority(os.PRIO_PROCESS, thread_id, want)
    except PermissionError:
        logger.debug("not permitted to set nice %d (needs root or CAP_SYS_NICE); the loop keeps its priority", want)
        return None
    return "nice"


class _SchedAttr(ctypes.Structure):
    _fields_ = [  # noqa: RUF012  (ctypes' own declaration)
        ("size", ctypes.c_uint32),
        ("sched_policy", ctypes.c_uint32),
        ("sched_flags", ctypes.c_uint64),
        ("sched_nice", ctypes.c_int32),
        ("sched_priority", ctypes.c_uint32),
        ("sched_runtime", ctypes.c_uint64),
        ("sched_deadline", ctypes.c_uint64),
        ("sched_period", ctypes.c_uint64),
    ]


def run_steps_through(slice_ns: int = STEP_SLICE_NS) -> str | None:
    """Let the calling thread run each of its bursts of work (an accelerated env's step) through to the end when it
    shares its core with others of its kind (the workers of a vector env with more workers than cores):
    ``SCHED_BATCH``, whose wake-ups do not preempt the thread that runs, and, on a kernel whose EEVDF scheduler takes
    a slice per thread (Linux 6.12 on), a slice of ``slice_ns``. Two workers on one core then run one after the
    other instead of in turns of a default slice (shorter than a step): fewer context switches, each of
    which costs the next one a cold cache, and a worker still waiting for its core has not run yet this step, so a
    core whose own workers are done can take it over (a worker that ran within the last half millisecond counts as
    cache-hot and stays where it is, and with turns every worker of a crowded core ran that recently). Keeps the
    nice value; needs no privilege.

    Returns:
        ``"batch+slice"`` (a kernel before 6.12 takes the policy and ignores the slice), ``"batch"`` (the slice was
        refused) or None (SCHED_BATCH not available or refused).
    """
    if not hasattr(os, "SCHED_BATCH"):
        return None
    nr = _SCHED_SETATTR.get(platform.machine())
    if nr is not None:
        attr = _SchedAttr(
            size=ctypes.sizeof(_SchedAttr),
            sched_policy=os.SCHED_BATCH,
            sched_nice=os.getpriority(os.PRIO_PROCESS, 0),
            sched_runtime=slice_ns,
        )
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.syscall(nr, 0, ctypes.byref(attr), 0) == 0:
            return "batch+slice"
        logger.debug("sched_setattr refused a %d ns slice (errno %d); SCHED_BATCH only", slice_ns, ctypes.get_errno())
    try:
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    except OSError as exc:
        logger.debug("could not switch to SCHED_BATCH: %s", exc)
        return None
    return "batch"


@contextlib.contextmanager
def real_time_thread() -> Iterator[bool]:
    """Run the calling thread (an agent's acting loop) under SCHED_RR at ``ACTOR_RT_PRIORITY`` (above every loop
    process) for the block, when permitted and ``UNIROS_LOOP_PRIORITY`` is ``rt``; restores its scheduling after.
    Yields whether it is real-time.

    Threads and processes started inside the block begin in the ordinary class (``SCHED_RESET_ON_FORK``): a
    learner thread, and torch's intra-op pool that the thread's first parallel operation creates, compute at
    normal priority.
    """
    if loop_priority_mode() != "rt" or not hasattr(os, "sched_setscheduler"):
        yield False
        return
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_RR | RESET_ON_FORK, os.sched_param(ACTOR_RT_PRIORITY))
    except PermissionError:
        yield False
        return
    try:
        yield True
    finally:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, policy, param)


def thread_ids() -> set[int]:
    """Native ids of this process's threads (empty where ``/proc`` is missing): a loop takes them before its
    start-up to tell, after it, which threads the start-up started (``raise_loop_priority(thread_id=...)``)."""
    try:
        return {int(t) for t in os.listdir(f"/proc/{os.getpid()}/task")}
    except OSError:
        return set()


def thread_scheduling(pid: int | None = None) -> dict[int, tuple[int, int]]:
    """Every thread of process ``pid`` (default: this one): native thread id -> (policy, real-time priority), the
    policy as ``os.SCHED_*`` with ``RESET_ON_FORK`` or'd in where set, the priority 0 outside the real-time
    classes. Threads that end while being read are left out.

    Raises:
        ProcessLookupError: no such process.
    """
    pid = os.getpid() if pid is None else pid
    try:
        tids = sorted(int(t) for t in os.listdir(f"/proc/{pid}/task"))
    except FileNotFoundError:
        raise ProcessLookupError(f"no process {pid}") from None
    out: dict[int, tuple[int, int]] = {}
    for tid in tids:
        try:
            out[tid] = (os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority)
        except ProcessLookupError:  # the thread ended meanwhile
            continue
    return out


@contextlib.contextmanager
def gil_switch_interval(seconds: float = ACTOR_GIL_SWITCH_S) -> Iterator[None]:
    """``sys.setswitchinterval(seconds)`` for the block (process-wide), restored after."""
    old = sys.getswitchinterval()
    sys.setswitchinterval(seconds)
    try:
        yield
    finally:
        sys.setswitchinterval(old)


_POLLER = """
import ctypes, os, signal, sys
parent, cpu = int(sys.argv[1]), int(sys.argv[2])
try:
    ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG: die with the parent
except (OSError, AttributeError):
    pass
os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
if cpu >= 0:
    os.sched_setaffinity(0, {cpu})
sys.stdout.write("up\\n"); sys.stdout.flush()
while os.getppid() == parent:
    for _ in range(100_000):
        pass
"""


PM_QOS_DEVICE = "/dev/cpu_dma_latency"


@contextlib.contextmanager
def cores_kept_polling(device: str = PM_QOS_DEVICE) -> Iterator[bool]:
    """Keep every core's idle loop polling instead of halting while the block runs, through the kernel's PM QoS:
    a CPU wake-up latency limit of 0 us written to ``/dev/cpu_dma_latency`` and held while its file stays open, as
    cyclictest does. Yields whether the limit is held (False where the device is missing or not writable: it
    needs root).

    Unlike ``cores_kept_awake``'s pollers, this adds no task to any run queue: a core's idle loop runs only when
    nothing else, kernel workers included, wants the core. A ``SCHED_IDLE`` poller is only a very light ordinary
    task, and the fair scheduler can pick it over a runnable kernel worker for a whole time slice; a task that waits
    for that worker (a pty's bytes are moved to the reader by one) then waits that long. Where the cpuidle driver
    has no polling state the limit still keeps the cores in their shallowest one.
    """
    try:
        fd = os.open(device, os.O_WRONLY | os.O_CLOEXEC)
    except OSError:
        yield False
        return
    try:
        os.write(fd, (0).to_bytes(4, sys.byteorder))
        yield True
    finally:
        os.close(fd)  # closing the file drops the limit


@contextlib.contextmanager
def cores_kept_awake(cpus: set[int] | None = None) -> Iterator[list[int]]:
    """Keep the machine's cores from halting while the block runs: one busy-polling process per core, in the
    ``SCHED_IDLE`` class, so it runs only when nothing else wants that core. Yields the pollers' pids (empty where
    ``SCHED_IDLE`` does not exist).

    What ``idle=poll`` (or cyclictest's hold on ``/dev/cpu_dma_latency``) does for real-time Linux, without a reboot
    or privileges. On a virtual machine a halted core is handed back to the host, and waking it again for a timer
    or a message costs the hypervisor's scheduling delay, seen as CPU steal and late ticks in the latency benchmark
    (git's docs/perf/history.md has both, with and without pollers). Any ordinary or real-time thread preempts a poller
    at once; the cost is power (the cores stay at 100 %) and, on SMT siblings, some of the sibling's throughput.
    The pollers die with this process (parent-death signal, and they check their parent), so none outlives even a
    SIGKILL.
    """
    if not hasattr(os, "SCHED_IDLE") or not hasattr(os, "sched_getaffinity"):
        yield []
        return
    targets = sorted(os.sched_getaffinity(0) if cpus is None else cpus)
    procs: list[subprocess.Popen[bytes]] = []
    try:
        for cpu in targets:
            procs.append(
                subprocess.Popen(
                    [sys.executable, "-c", _POLLER, str(os.getpid()), str(cpu)],
                    stdin=subprocess.DEVNULL,
                    stdout=subprocess.PIPE,
                    stderr=subprocess.DEVNULL,
                )
            )
        deadline = time.monotonic() + 10.0
        for p in procs:  # each has lowered itself before the block starts
            assert p.stdout is not None
            ready = _readline_until(p, deadline)
            if ready != b"up\n":
                raise RuntimeError(f"a core poller (pid {p.pid}) did not start: exit code {p.poll()}")
        yield [p.pid for p in procs]
    finally:
        reap(procs)


@contextlib.contextmanager
def cores_kept_from_halting() -> Iterator[str]:
    """Keep idle cores from halting while the block runs, by the PM QoS limit where this process may set it
    (``cores_kept_polling``), else by idle-class pollers (``cores_kept_awake``). Yields which: ``"pm_qos"`` or
    ``"pollers"`` (``"no"`` where neither exists)."""
    with cores_kept_polling() as held:
        if held:
            yield "pm_qos"
            return
        with cores_kept_awake() as pids:
            yield "pollers" if pids else "no"


def reap(procs: Sequence[subprocess.Popen[bytes]], timeout_s: float = 5.0) -> None:
    """End helper processes of ours that hold no state (core pollers, load spinners): kill those still running,
    wait up to ``timeout_s`` for each to exit, and close their stdout pipes."""
    for p in procs:
        if p.poll() is None:
            p.kill()
    for p in procs:
        with contextlib.suppress(subprocess.TimeoutExpired):
            p.wait(timeout=timeout_s)
        if p.stdout is not None:
            p.stdout.close()


def _readline_until(p: subprocess.Popen[bytes], deadline: float) -> bytes:
    """The poller's first line, or b"" if it exits or stays silent until ``deadline``."""
    import selectors

    assert p.stdout is not None
    with selectors.DefaultSelector() as sel:
        sel.register(p.stdout, selectors.EVENT_READ)
        if not sel.select(max(0.0, deadline - time.monotonic())):
            return b""
    return p.stdout.readline()
