"""The loads ``uniros bench latency --loads`` runs beside its learners, to show what the real-time class keeps off
the env loops: ``cpu`` (one spinning process per core), ``gil`` (a thread of the agent's process that holds the
GIL in long C calls), ``gc`` (a thread that makes garbage cycles and collects them), ``torch`` (the learner's own
intra-op threads, one per core); and the table of the loops' cycles under them."""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence

from uniros_async.bench.looptiming import Series
from uniros_async.errors import ConfigError
from uniros_async.priority import reap
from uniros_async.stats import summary

__all__ = ["GC_OBJECTS", "GIL_STRETCH_N", "LOADS", "LoadStats", "format_load_table", "open_load"]

LOADS = ("cpu", "gil", "torch", "gc")
LOAD_P99_GOAL_MS = 2.0
LOAD_MAX_GOAL_MS = 10.0
GIL_STRETCH_N = 1_500_000
"""``sum(range(GIL_STRETCH_N))``: one C call that holds the GIL throughout (tens of ms)."""
GC_OBJECTS = 300_000
"""Objects each of the ``gc`` load's rounds makes before it collects them."""

_SPINNER = """
import ctypes, os, signal, sys
parent = int(sys.argv[1])
try:
    ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG: die with the parent
except (OSError, AttributeError):
    pass
try:
    os.setpriority(os.PRIO_PROCESS, 0, 0)  # normal priority, also when the bench runs under nice
except OSError:
    pass
sys.stdout.write("up\\n"); sys.stdout.flush()
while os.getppid() == parent:
    for _ in range(100_000):
        pass
"""


@dataclasses.dataclass
class LoadStats:
    """What a load did while it ran: GIL stretches held (ms), collections run, the spinning processes' pids."""

    stretches_ms: list[float] = dataclasses.field(default_factory=list)
    collections: int = 0
    spinners: list[int] = dataclasses.field(default_factory=list)


@contextlib.contextmanager
def open_load(kind: str) -> Iterator[LoadStats]:
    """Run load ``kind`` (``cpu``, ``gil`` or ``gc``; ``torch`` is the learner's own threads) for the block; every
    process and thread it started has ended when the block is left.

    Raises:
        ConfigError: an unknown kind.
    """
    stats = LoadStats()
    if kind == "torch":
        yield stats
        return
    if kind == "cpu":
        n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
        procs = []
        try:
            for _ in range(n):
                procs.append(
                    subprocess.Popen(
                        [sys.executable, "-c", _SPINNER, str(os.getpid())],
                        stdin=subprocess.DEVNULL,
                        stdout=subprocess.PIPE,
                        stderr=subprocess.DEVNULL,
                    )
                )
            for p in procs:
                assert p.stdout is not None
                if p.stdout.readline() != b"up\n":
                    raise RuntimeError(f"a cpu load process (pid {p.pid}) did not start: exit code {p.poll()}")
            stats.spinners = [p.pid for p in procs]
            yield stats
        finally:
            reap(procs)
        return
    if kind not in ("gil", "gc"):
        raise ConfigError(f"unknown load {kind!r}; choose from {list(LOADS)}")
    stop = threading.Event()

    def hold_gil() -> None:
        while not stop.is_set():
            t0 = time.perf_counter()
            sum(range(GIL_STRETCH_N))  # one C call: the GIL is not released until it returns
            stats.stretches_ms.append((time.perf_counter() - t0) * 1e3)

    def churn() -> None:
        while not stop.is_set():
            junk = [{"i": i, "t": (i, str(i))} for i in range(GC_OBJECTS)]
            junk.append({"self": junk})  # a cycle: only the collector frees it
            del junk
            t0 = time.perf_counter()
            gc.collect()
            stats.stretches_ms.append((time.perf_counter() - t0) * 1e3)
            stats.collections += 1

    thread = threading.Thread(target=hold_gil if kind == "gil" else churn, name=f"{kind} load", daemon=True)
    thread.start()
    try:
        yield stats
    finally:
        stop.set()
        thread.join(10.0)


def format_load_table(series: Sequence[Series]) -> str:
    """Per load, class and env: actuator cycle median, p99 and max, action cycle median and IQR (ms), and whether
    the real-time class met the goal under load (p99 within ``LOAD_P99_GOAL_MS`` and max within
    ``LOAD_MAX_GOAL_MS`` of the period)."""
    head = (
        f"{'env':<20} {'learner, load, class':<24} {'act. med':>9} {'act. p99':>9} {'act. max':>9} "
        f"{'cycle med':>10} {'cycle IQR':>10}  goal (rt: p99 <= period + {LOAD_P99_GOAL_MS:g}, max <= period + "
        f"{LOAD_MAX_GOAL_MS:g})"
    )
    lines = ["actuator cycle (act.) and action cycle, ms, under load", head, "-" * len(head)]
    for s in series:
        a, c = summary(s.samples.get("actuator_cycle", [])), summary(s.samples.get("action_cycle", []))
        verdict = ""
        if s.learner.endswith(" rt") and s.period_ms is not None and a["count"]:
            ok = a["p99"] <= s.period_ms + LOAD_P99_GOAL_MS and a["max"] <= s.period_ms + LOAD_MAX_GOAL_MS
            verdict = "met" if ok else "MISSED"
        lines.append(
            f"{s.env:<20} {s.learner:<24} {a['p50']:>9.2f} {a['p99']:>9.2f} {a['max']:>9.2f} "
            f"{c['p50']:>10.2f} {c['iqr']:>10.2f}  {verdict}".rstrip()
        )
    return "\n".join(lines)
