"""Who held the cores when an env loop's tick came late: `python benchmarks/load_timeline.py [options]`.

Runs `uniros bench latency` under one load and scheduling class (by default `--load torch --sched rt
--duration 30`; the same scenario, table and JSON as the CLI) and records beside it:

- every env's tick stamps (CLOCK_MONOTONIC, from its timing records);
- the kernel's scheduler events (ftrace `sched_switch`, `sched_wakeup`, `sched_process_fork`, `sched_process_exec`
  on the `mono` trace clock, so that the trace and the stamps share one clock), when run as root with tracefs;
- the scheduling class of every thread of the run's processes, once in the middle of the phase.

Then, for each env's worst periods between ticks: when the late tick was due, when its thread was woken, and who
ran on each core in between (pid, real-time priority or nice, command, whether it belongs to this run), longest
first. Runs of several seconds of one task at a real-time priority equal to or above the loop's are what starves
it; a stretch in which no core reports any event while a wakeup is overdue is the hypervisor's (steal).

The tracing costs little (two events per context switch). The trace buffer is set to 40 MiB per core for the run
and put back after. Not a benchmark of record: the tool that finds the cause of a late tick. Recorded in
docs/reliability.md.
"""

from __future__ import annotations

import argparse
import bisect
import collections
import contextlib
import dataclasses
import json
import os
import re
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from uniros_async.bench import latency
from uniros_async.priority import thread_scheduling

TRACEFS = Path("/sys/kernel/tracing")
EVENTS = "sched:sched_switch sched:sched_wakeup sched:sched_process_fork sched:sched_process_exec"
SWITCH = re.compile(
    r"\[(\d+)\] \S+ +(\d+\.\d+): sched_switch: prev_comm=(.*?) prev_pid=(\d+) prev_prio=(\d+) prev_state=\S+ "
    r"==> next_comm=(.*?) next_pid=(\d+) next_prio=(\d+)"
)
WAKEUP = re.compile(r" (\d+\.\d+): sched_wakeup: comm=.*? pid=(\d+) prio=\d+ target_cpu=(\d+)")
STAMP = re.compile(r"\] \S+ +(\d+\.\d+): ")
FORK = re.compile(r" (\d+\.\d+): sched_process_fork: comm=.*? pid=(\d+) child_comm=.*? child_pid=(\d+)")


@dataclasses.dataclass
class Run:
    """What the run recorded: per env its label, worker pid and tick stamps; thread classes mid-phase."""

    labels: list[str] = dataclasses.field(default_factory=list)
    pids: list[int] = dataclasses.field(default_factory=list)
    ticks_ns: list[list[int]] = dataclasses.field(default_factory=list)
    periods_ms: list[float] = dataclasses.field(default_factory=list)
    classes: dict[int, dict[int, tuple[int, int]]] = dataclasses.field(default_factory=dict)


@contextlib.contextmanager
def ftrace(enabled: bool) -> Iterator[list[str] | None]:
    """Record the scheduler events for the block (root, tracefs mounted); yields the list that receives the trace's
    lines when the block ends, or None when not tracing. The tracing settings are put back."""
    if not enabled or os.geteuid() != 0 or not (TRACEFS / "trace").exists():
        if enabled:
            print("no scheduler trace (needs root and tracefs at /sys/kernel/tracing)", file=sys.stderr)
        yield None
        return
    keep = {f: (TRACEFS / f).read_text().strip() for f in ("trace_clock", "buffer_size_kb", "set_event", "tracing_on")}
    clock = re.search(r"\[(\w+)\]", keep["trace_clock"])
    size = re.findall(r"\d+", keep["buffer_size_kb"])  # "7 (expanded: 1408)": the size once in use is the last
    lines: list[str] = []
    try:
        (TRACEFS / "tracing_on").write_text("0")
        (TRACEFS / "trace").write_text("")
        (TRACEFS / "trace_clock").write_text("mono")  # CLOCK_MONOTONIC, as the env loops' stamps
        (TRACEFS / "buffer_size_kb").write_text("40960")
        (TRACEFS / "set_event").write_text(EVENTS)
        (TRACEFS / "tracing_on").write_text("1")
        yield lines
    finally:
        (TRACEFS / "tracing_on").write_text("0")
        lines += (TRACEFS / "trace").read_text().splitlines()
        (TRACEFS / "trace").write_text("")
        (TRACEFS / "set_event").write_text(keep["set_event"] + "\n")
        if clock:
            (TRACEFS / "trace_clock").write_text(clock[1])
        if size:
            (TRACEFS / "buffer_size_kb").write_text(size[-1])
        (TRACEFS / "tracing_on").write_text(keep["tracing_on"])


def run_bench(args: argparse.Namespace, run: Run) -> None:
    """``uniros bench latency`` as the CLI runs it, capturing the workers' pids and every env's tick stamps."""
    from uniros_async import runtime

    make_vec = runtime.make_vec
    original_metrics = latency.loop_metrics

    def spy_make_vec(*a: Any, **kw: Any) -> Any:
        vec = make_vec(*a, **kw)
        run.pids = list(vec._sup.pids())
        run.periods_ms = [1e3 / float(r) for r in vec.get_attr("env_loop_rate_hz")]
        sample = threading.Timer(args.duration / 2 + 15.0, lambda: run.classes.update(_classes(run.pids)))
        sample.daemon = True
        sample.start()
        return vec

    def spy_metrics(snap: Any, **kw: Any) -> Any:
        run.ticks_ns.append([int(t) for t in snap.get("tick_ns", [])])
        return original_metrics(snap, **kw)

    runtime.make_vec = spy_make_vec  # type: ignore[assignment]
    latency.loop_metrics = spy_metrics
    try:
        cfg = latency.LatencyBenchConfig(
            scenario="concurrent",
            duration_s=args.duration,
            loads=(args.load,),
            sched_classes=(args.sched,),
            json_path=args.json,
            progress=False,
        )
        run.labels = [f"{latency.ARM_OF_ENV_ID[e]} {r}" for e, r in latency.CONCURRENT_ENVS]
        latency.main(cfg)
    finally:
        runtime.make_vec = make_vec  # type: ignore[assignment]
        latency.loop_metrics = original_metrics


def _classes(pids: list[int]) -> dict[int, dict[int, tuple[int, int]]]:
    """Thread classes of the workers and of their children (the arms' processes)."""
    out: dict[int, dict[int, tuple[int, int]]] = {os.getpid(): thread_scheduling()}
    todo = list(pids)
    while todo:
        pid = todo.pop()
        with contextlib.suppress(ProcessLookupError, FileNotFoundError):
            out[pid] = thread_scheduling(pid)
            for tid in out[pid]:
                with contextlib.suppress(FileNotFoundError):
                    todo += [int(c) for c in Path(f"/proc/{pid}/task/{tid}/children").read_text().split()]
    return out


def _prio(kernel_prio: int) -> str:
    return f"rt {99 - kernel_prio}" if kernel_prio < 100 else f"nice {kernel_prio - 120}"


def analyse(trace: list[str], run: Run, worst: int) -> None:
    """Print, for each env's ``worst`` longest tick periods, the wakeup and who ran on each core meanwhile."""
    ours = {os.getpid(), *run.classes.get(os.getpid(), {})}  # forks name the forking thread
    for line in trace:
        m = FORK.search(line)
        if m and int(m[2]) in ours:
            ours.add(int(m[3]))
    switches = [m for line in trace if (m := SWITCH.search(line))]
    wakeups = [m for line in trace if (m := WAKEUP.search(line))]
    stamps = sorted(float(m[1]) for line in trace if (m := STAMP.search(line)))
    for label, pid, ticks, period in zip(run.labels, run.pids, run.ticks_ns, run.periods_ms, strict=False):
        gaps = sorted(((b - a) / 1e6, a / 1e9, b / 1e9) for a, b in zip(ticks, ticks[1:], strict=False))[-worst:]
        print(f"\n{label} (worker {pid}, period {period:g} ms): the {len(gaps)} longest periods between ticks")
        for gap, start, end in reversed(gaps):
            due = start + period / 1e3
            woken = [float(w[1]) for w in wakeups if int(w[2]) == pid and due - 0.001 <= float(w[1]) <= end]
            print(
                f"  {gap:7.2f} ms, tick {start:.4f} -> {end:.4f}: due {due:.4f}, woken "
                + (f"{woken[0]:.4f}" if woken else "(none recorded: its thread was running or runnable)")
                + f", ticked {end:.4f}"
            )
            held: collections.Counter[tuple[int, str, int, str]] = collections.Counter()
            current: dict[int, tuple[float, int, str, int]] = {}
            for m in switches:
                cpu, ts = int(m[1]), float(m[2])
                if ts > end:
                    break
                if cpu in current:
                    t0, p, comm, prio = current[cpu]
                    if (overlap := min(ts, end) - max(t0, due)) > 0 and p != 0:
                        held[(cpu, comm, p, _prio(prio))] += overlap
                current[cpu] = (ts, int(m[7]), m[6], int(m[8]))
            for cpu, (t0, p, comm, prio) in current.items():  # still running when the tick came
                if (overlap := end - max(t0, due)) > 0 and p != 0:
                    held[(cpu, comm, p, _prio(prio))] += overlap
            for (cpu, comm, p, prio), s in held.most_common(6):
                who = "the loop itself" if p == pid else "this run" if p in ours else "another"
                print(f"      cpu{cpu}: {s * 1e3:6.1f} ms  pid {p} {comm} ({prio}, {who})")
            lo = bisect.bisect_right(stamps, due) - 1  # the last event before the tick was due, and all up to it
            near = stamps[max(lo, 0) : bisect.bisect_right(stamps, end) + 1]
            a, b = max(zip(near, near[1:], strict=False), key=lambda ab: min(ab[1], end) - max(ab[0], due))
            if min(b, end) - max(a, due) > 0.002:
                print(
                    f"      no event on any core from {a:.4f} to {b:.4f} ({(b - a) * 1e3:.1f} ms; "
                    f"{(min(b, end) - max(a, due)) * 1e3:.1f} ms of it after the tick was due)"
                )


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    p.add_argument("--load", default="torch", choices=latency.LOADS)
    p.add_argument("--sched", default="rt", choices=latency.SCHED_CLASSES)
    p.add_argument("--duration", type=float, default=30.0, help="seconds of the loaded phase (default 30)")
    p.add_argument("--worst", type=int, default=3, help="periods to explain per env (default 3)")
    p.add_argument("--json", default=None, help="the bench's JSON records (as `uniros bench latency --json`)")
    p.add_argument("--save", default=None, metavar="DIR", help="keep the raw trace, stamps and classes there")
    p.add_argument("--no-trace", action="store_true", help="no scheduler trace, even as root")
    args = p.parse_args()
    run = Run()
    with ftrace(not args.no_trace) as trace:
        run_bench(args, run)
    print("\nthread classes mid-phase (pid: {policy/priority: threads}; 0 ordinary, 2 RR, + reset-on-fork):")
    for pid, threads in run.classes.items():
        kinds = collections.Counter(f"{pol & 0xFF}{'+' * bool(pol & ~0xFF)}/{prio}" for pol, prio in threads.values())
        print(f"  {pid}: {dict(kinds)}")
    if args.save:
        out = Path(args.save)
        out.mkdir(parents=True, exist_ok=True)
        (out / "ticks.json").write_text(json.dumps(dataclasses.asdict(run)))
        if trace:
            (out / "trace.txt").write_text("\n".join(trace))
    if trace:
        analyse(trace, run, args.worst)
    return 0


if __name__ == "__main__":
    sys.exit(main())
