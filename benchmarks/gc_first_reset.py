"""Step a vector env of a real-time rx200 and ned2 (worker processes, random actions) for the seconds given, printing
the worker pids and when the first reset returned; with ``benchmarks/gc_log`` on ``PYTHONPATH`` every process logs
its full garbage collections, so the log says whether one ran on a worker's loop thread after its loop started.

    mkdir -p /tmp/uniros_gc_log
    PYTHONPATH=benchmarks/gc_log UNIROS_LOOP_PRIORITY=off python benchmarks/gc_first_reset.py 120
"""

from __future__ import annotations

import sys
import time

import numpy as np

from uniros_async.runtime import make_vec


def main(seconds: float) -> None:
    vec = make_vec([("uniros/Rx200Reach-v0", {}), ("uniros/Ned2Reach-v0", {})])
    try:
        print("worker pids", vec.pids, flush=True)
        vec.reset(seed=0)
        t0 = time.time()
        print(f"first reset returned at {t0:.3f}", flush=True)
        rng = np.random.default_rng(0)
        steps = 0
        while time.time() - t0 < seconds:
            vec.step(rng.uniform(-1, 1, (2, *vec.single_action_space.shape)).astype(np.float32))
            steps += 1
        print(f"{steps} steps, ended at {time.time():.3f}", flush=True)
    finally:
        vec.close()


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else 60.0)
