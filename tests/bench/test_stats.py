"""The benchmarks' order statistics."""

from __future__ import annotations

import math
import os
import subprocess
import sys

import numpy as np
import pytest

from uniros_async.stats import median_ci


@pytest.mark.parametrize(("n", "ranks"), [(6, (1, 6)), (10, (2, 9)), (29, (9, 21)), (100, (40, 61))])
def test_median_ci_takes_the_ranks_of_the_binomial_tables(n: int, ranks: tuple[int, int]) -> None:
    # 1-based ranks of the 95 % interval, as in the published tables of the sign test's interval
    samples = np.arange(1, n + 1, dtype=float)[::-1]  # unsorted on purpose
    assert median_ci(samples) == (float(ranks[0]), float(ranks[1]))


def test_median_ci_needs_six_samples_at_95_percent() -> None:
    assert all(math.isnan(v) for v in median_ci([1.0, 2.0, 3.0, 4.0, 5.0]))
    assert all(math.isnan(v) for v in median_ci([]))


def test_median_ci_holds_the_median_at_least_as_often_as_it_says() -> None:
    rng = np.random.default_rng(0)
    for n in (12, 60):
        hits = sum(lo <= 0.0 <= hi for lo, hi in (median_ci(rng.standard_cauchy(n)) for _ in range(2000)))
        assert hits / 2000 >= 0.94  # >= 95 % in expectation; 2,000 draws scatter by ~0.5 %


def test_real_time_threads_of_other_processes_are_counted_and_a_run_s_own_left_out() -> None:
    """A process in SCHED_RR that spins is listed with the CPU it used, but not when it is in the excluded tree;
    ordinary processes never are."""
    from uniros_async.bench.common import real_time_elsewhere, real_time_threads

    if os.geteuid() != 0:
        pytest.skip("SCHED_RR needs root or CAP_SYS_NICE; this machine's CI runs as root")
    code = (
        "import os, sys, time\n"
        "os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(1))\n"  # the lowest real-time priority
        "print('up', flush=True); sys.stdin.readline()\n"
        "t = time.monotonic()\n"
        "while time.monotonic() - t < 0.05: pass\n"  # 50 ms of CPU in the class
        "print('done', flush=True); sys.stdin.read()\n"
    )
    child = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    me = (child.pid, child.pid)
    try:
        assert child.stdin is not None and child.stdout is not None and child.stdout.readline() == "up\n"
        before = real_time_threads()
        child.stdin.write("go\n")
        child.stdin.flush()
        assert child.stdout.readline() == "done\n"
        after = real_time_threads()
        assert after[me] > before[me]  # clock ticks of 10 ms: 50 ms of spinning shows
        assert not [k for k in real_time_threads(exclude_tree_of=os.getpid()) if k[0] == child.pid]
        assert os.getpid() not in {p for p, _ in after}  # this process is ordinary
        line = real_time_elsewhere(before, after)
        assert line.startswith("real-time threads of other processes during the run: ") and "s of CPU" in line
        assert real_time_elsewhere({}, {}) == "real-time threads of other processes during the run: none"
    finally:
        child.communicate("", timeout=10)
