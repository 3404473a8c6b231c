"""What every ``uniros bench`` shares: the report, a progress counter, and what else on the host competed with a
run (hypervisor steal, other processes' real-time threads). The statistics are ``uniros_async.stats``."""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = [
    "cpu_times",
    "progress_counter",
    "real_time_elsewhere",
    "real_time_threads",
    "report",
    "steal_percent",
]


def report(table: str, records: list[dict[str, Any]], json_path: str | None, log: Callable[[str], None]) -> None:
    """Print a benchmark's table and, when asked, write its records as JSON (every ``uniros bench`` ends so)."""
    log(table)
    if json_path:
        Path(json_path).write_text(json.dumps(records, indent=2) + "\n")
        log(f"wrote {json_path}")


def progress_counter(total: int, enabled: bool, desc: str, unit: str) -> Callable[..., None]:
    """A tqdm bar of ``total`` ``unit``s on stderr, gone when done: ``step(n)`` counts ``n`` more, ``step(0,
    done=True)`` closes it. Without ``enabled``, a function that does nothing."""
    if not enabled:
        return lambda n, done=False: None
    from uniros_async._progress import progress_bar

    bar = progress_bar(total=total, desc=desc, unit=unit, leave=False)

    def step(n: int, done: bool = False) -> None:
        if n:
            bar.update(n)
        if done:
            bar.close()

    return step


def cpu_times() -> list[int] | None:
    """The aggregate ``cpu`` line of /proc/stat (jiffies: user nice system idle iowait irq softirq steal), or None."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
    except OSError:
        return None
    return [int(x) for x in fields[1:9]] if fields and fields[0] == "cpu" and len(fields) >= 9 else None


def steal_percent(before: list[int] | None, after: list[int] | None) -> float | None:
    """Share of CPU time the hypervisor stole between two ``cpu_times`` readings, in %."""
    if before is None or after is None:
        return None
    delta = [b - a for a, b in zip(before, after, strict=True)]
    total = sum(delta)
    return 100.0 * delta[7] / total if total > 0 else None


def real_time_threads(exclude_tree_of: int | None = None) -> dict[tuple[int, int], int]:
    """Threads of user processes in a real-time class (SCHED_FIFO, SCHED_RR) and the CPU time each has used
    (utime + stime, in clock ticks): ``(pid, tid) -> ticks``, leaving out kernel threads and the process tree of
    ``exclude_tree_of`` (a benchmark's own). Empty where ``/proc`` is missing; processes and threads that end while
    being read are left out.

    Two readings around a run tell what real-time work of other processes competed with its loops: at their
    priorities they preempt or take turns with them, which no setting of the run prevents.
    """
    stats: dict[int, list[str]] = {}
    try:
        pids = [int(d) for d in os.listdir("/proc") if d.isdigit()]
    except OSError:
        return {}
    for pid in pids:
        with contextlib.suppress(OSError, IndexError):
            with open(f"/proc/{pid}/stat") as f:
                stats[pid] = f.read().rsplit(")", 1)[1].split()
    parent = {pid: int(f[1]) for pid, f in stats.items()}
    excluded: set[int] = set()
    if exclude_tree_of is not None:
        excluded.add(exclude_tree_of)
        grew = True
        while grew:
            more = {pid for pid, pp in parent.items() if pp in excluded and pid not in excluded}
            excluded |= more
            grew = bool(more)
    out: dict[tuple[int, int], int] = {}
    for pid, pp in parent.items():
        if pid in excluded or pid == 2 or pp == 2:  # kthreadd and its children: kernel threads
            continue
        try:
            tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
        except OSError:
            continue
        for tid in tids:
            with contextlib.suppress(OSError, IndexError):
                with open(f"/proc/{pid}/task/{tid}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
                if int(fields[38]) in (1, 2):  # policy: SCHED_FIFO, SCHED_RR
                    out[(pid, tid)] = int(fields[11]) + int(fields[12])
    return out


def real_time_elsewhere(before: dict[tuple[int, int], int], after: dict[tuple[int, int], int]) -> str:
    """One line on the real-time threads of other processes between two ``real_time_threads`` readings: how many,
    in how many processes, and the CPU time they used meanwhile (a thread that started meanwhile counts whole)."""
    if not after and not before:
        return "real-time threads of other processes during the run: none"
    ticks = sum(t - before.get(k, 0) for k, t in after.items())
    seconds = ticks / (os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100)
    return (
        f"real-time threads of other processes during the run: {len(after)} in {len(set(p for p, _ in after))} "
        f"process(es) at its end, {seconds:.1f} s of CPU meanwhile (at their priorities they delay this run's loops)"
    )
