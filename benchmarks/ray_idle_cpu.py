"""The CPU that the throughput bench's own Ray cluster takes while nothing runs on it.

Starts the cluster as ``uniros bench throughput --backend ray`` does without ``--ray-address`` (``RayRows.start``:
a head and a second node), lets it settle for 5 s, then sums the CPU time (user + system, ``/proc/<pid>/stat``) of
every process it started (the daemons, their agents, idle Ray workers) over a window, and prints it per process
and in all, as a % of one core. ``--as-before`` starts it with Ray's defaults instead (``RayRows(quiet=False)``: no
dashboard, the same CPU counts and object stores, nothing else set), for the comparison.

Run it in a network namespace (Ray binds the host's interfaces otherwise)::

    unshare --net -- sh -c 'ip link set lo up && python benchmarks/ray_idle_cpu.py --window 60'
"""

from __future__ import annotations

import argparse
import os
import time

from uniros_async.bench._ray_rows import RayRows


def _descendants(root: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        children.setdefault(ppid, []).append(int(entry))
    found, todo = [], [root]
    while todo:
        more = children.get(todo.pop(), [])
        found += more
        todo += more
    return found


def _cpu(pid: int) -> tuple[str, float] | None:
    """(name, user + system CPU seconds) of ``pid``, None once it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        with open(f"/proc/{pid}/comm") as f:
            name = f.read().strip()
    except OSError:
        return None
    return name, (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--window", type=float, default=60.0, help="seconds measured (default 60)")
    parser.add_argument("--as-before", action="store_true", help="Ray's defaults instead of the bench's quiet config")
    args = parser.parse_args()
    rows = RayRows(quiet=not args.as_before)
    rows.start()
    try:
        time.sleep(5.0)
        pids = _descendants(os.getpid())
        before = {p: _cpu(p) for p in pids}
        time.sleep(args.window)
        after = {p: _cpu(p) for p in pids}
    finally:
        rows.close()
    total = 0.0
    for p in pids:
        a, b = before[p], after[p]
        if a is None or b is None:
            continue
        total += b[1] - a[1]
        print(f"  {b[0]:<20} pid {p:<8} {b[1] - a[1]:.2f} s")
    label = "Ray's defaults" if args.as_before else "the bench's quiet config"
    print(
        f"{label}: {len(pids)} processes, {total:.2f} s of CPU over {args.window:.0f} s idle ="
        f" {100 * total / args.window:.2f} % of one core"
    )


if __name__ == "__main__":
    main()
