"""Time to start vector envs: ``python benchmarks/start_time.py [REPEATS] [--against TREE] [--only TEXT]``.

Times ``make_vec`` (workers started, envs built, spaces exchanged; no reset) of four "uniros/Rx200Reach-v0" envs
(clock="sim") and of one "CartPole-v1", REPEATS times each (5 by default), each in a fresh process so no import is
cached, and prints the medians.

``--against TREE`` also times the checkout at ``TREE`` (a git worktree with its compiled ring end: ``python
setup.py build_ext --inplace``), each process with ``PYTHONPATH`` set to its tree, in ABBA order (this tree, the
other, the other, this tree, ... REPEATS rounds of each case), so that a load that rises or falls over the run
weighs on both alike; it prints both medians and their ratio (this tree / the other: below 1 is faster here), and
the median of each round's own ratio (its two runs are next to each other in time, so a load that comes and goes
between rounds cancels out).

Each tree's package is byte-compiled first (``compileall``), as an installed package is: otherwise, where
``PYTHONDONTWRITEBYTECODE`` is set or the tree is read-only, every process would compile the package's modules
from source again, and the figures would be the compiler's.

Besides the wall-clock time it prints the CPU time spent (the caller's during ``make_vec``, and its children's:
the workers, reaped at ``close``, so their shutdown counts too): on a host whose other load varies, that is the
steadier figure, and on 2 cores four workers' start is mostly CPU-bound.
"""

from __future__ import annotations

import argparse
import compileall
import os
import statistics
import subprocess
import sys

CASES = {
    "4 x uniros/Rx200Reach-v0 (sim clock)": 'make_vec(["uniros/Rx200Reach-v0"] * 4, clock="sim")',
    "1 x CartPole-v1": 'make_vec(["CartPole-v1"], pad=False)',
}
SNIPPET = """
import resource, time
from uniros_async.runtime import make_vec
def cpu(who):
    r = resource.getrusage(who)
    return r.ru_utime + r.ru_stime
t0, c0 = time.perf_counter(), cpu(resource.RUSAGE_SELF)
venv = {call}
wall, own = time.perf_counter() - t0, cpu(resource.RUSAGE_SELF) - c0
venv.close()
print(wall, own + cpu(resource.RUSAGE_CHILDREN))
"""
HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
"""The tree this script belongs to."""


def time_once(call: str, tree: str) -> tuple[float, float]:
    """Seconds that ``call`` took in a fresh interpreter importing ``uniros_async`` from ``tree``: wall-clock, and
    CPU (the caller's during the call and its children's whole lives: the workers, reaped at ``close``)."""
    env = {**os.environ, "PYTHONPATH": tree}
    out = subprocess.run(
        [sys.executable, "-c", SNIPPET.format(call=call)], capture_output=True, text=True, check=True, env=env
    )
    wall, cpu = out.stdout.strip().splitlines()[-1].split()
    return float(wall), float(cpu)


def _runs(times: list[float]) -> str:
    return ", ".join(f"{t:.3f}" for t in times)


def _line(name: str, runs: list[tuple[float, float]]) -> str:
    walls, cpus = [w for w, _ in runs], [c for _, c in runs]
    return (
        f"{name} median {statistics.median(walls):.3f} s ({_runs(walls)}); CPU median {statistics.median(cpus):.3f} s"
        f" ({_runs(cpus)})"
    )


def main() -> None:
    """Parse the arguments, time each case (against the other tree if given), print the medians."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("repeats", nargs="?", type=int, default=5, help="runs of each case (and tree); default 5")
    parser.add_argument("--against", metavar="TREE", help="another checkout to time alongside, in ABBA order")
    parser.add_argument("--only", metavar="TEXT", help="time only the cases whose name contains TEXT (CartPole)")
    args = parser.parse_args()
    for tree in [HERE] if args.against is None else [HERE, args.against]:
        compileall.compile_dir(os.path.join(tree, "uniros_async"), quiet=1)
    for name, call in CASES.items():
        if args.only is not None and args.only.lower() not in name.lower():
            continue
        if args.against is None:
            print(_line(f"{name}:", [time_once(call, HERE) for _ in range(args.repeats)]))
            continue
        here: list[tuple[float, float]] = []
        other: list[tuple[float, float]] = []
        for i in range(args.repeats):
            order = [(here, HERE), (other, args.against)]
            for runs, tree in order if i % 2 == 0 else order[::-1]:
                runs.append(time_once(call, tree))
        print(_line(f"{name}: this tree", here))
        print(_line(f"{name}: {args.against}", other))
        wall = statistics.median(w for w, _ in here) / statistics.median(w for w, _ in other)
        cpu = statistics.median(c for _, c in here) / statistics.median(c for _, c in other)
        paired = statistics.median(h[0] / o[0] for h, o in zip(here, other, strict=True))
        print(f"{name}: ratio this / other: wall {wall:.3f} (median of each round's {paired:.3f}), CPU {cpu:.3f}")


if __name__ == "__main__":
    main()
