"""Time to start vector envs: ``python benchmarks/start_time.py [REPEATS] [--against TREE]``.

Times ``make_vec`` (workers started, envs built, spaces exchanged; no reset) of four "uniros/Rx200Reach-v0" envs
(clock="sim") and of one "CartPole-v1", REPEATS times each (5 by default), each in a fresh process so no import is
cached, and prints the medians. Recorded in docs/performance.md.

``--against TREE`` also times the checkout at ``TREE`` (a git worktree with its compiled ring end: ``python
setup.py build_ext --inplace``), each process with ``PYTHONPATH`` set to its tree, in ABBA order (this tree, the
other, the other, this tree, ... REPEATS rounds of each case), so that a load that rises or falls over the run
weighs on both alike; it prints both medians and their ratio (this tree / the other: below 1 is faster here).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys

CASES = {
    "4 x uniros/Rx200Reach-v0 (sim clock)": 'make_vec(["uniros/Rx200Reach-v0"] * 4, clock="sim")',
    "1 x CartPole-v1": 'make_vec(["CartPole-v1"], pad=False)',
}
SNIPPET = """
import time
from uniros_async.runtime import make_vec
t0 = time.perf_counter()
venv = {call}
print(time.perf_counter() - t0)
venv.close()
"""
HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
"""The tree this script belongs to."""


def time_once(call: str, tree: str) -> float:
    """Seconds that ``call`` took in a fresh interpreter importing ``uniros_async`` from ``tree``."""
    env = {**os.environ, "PYTHONPATH": tree}
    out = subprocess.run(
        [sys.executable, "-c", SNIPPET.format(call=call)], capture_output=True, text=True, check=True, env=env
    )
    return float(out.stdout.strip().splitlines()[-1])


def _runs(times: list[float]) -> str:
    return ", ".join(f"{t:.3f}" for t in times)


def main() -> None:
    """Parse the arguments, time each case (against the other tree if given), print the medians."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("repeats", nargs="?", type=int, default=5, help="runs of each case (and tree); default 5")
    parser.add_argument("--against", metavar="TREE", help="another checkout to time alongside, in ABBA order")
    args = parser.parse_args()
    for name, call in CASES.items():
        if args.against is None:
            times = [time_once(call, HERE) for _ in range(args.repeats)]
            print(f"{name}: median {statistics.median(times):.3f} s over {args.repeats} ({_runs(times)})")
            continue
        here: list[float] = []
        other: list[float] = []
        for i in range(args.repeats):
            order = [(here, HERE), (other, args.against)]
            for times, tree in order if i % 2 == 0 else order[::-1]:
                times.append(time_once(call, tree))
        h, o = statistics.median(here), statistics.median(other)
        print(f"{name}: this tree median {h:.3f} s ({_runs(here)})")
        print(f"{name}: {args.against} median {o:.3f} s ({_runs(other)})")
        print(f"{name}: ratio this / other {h / o:.3f}")


if __name__ == "__main__":
    main()
