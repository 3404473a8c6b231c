"""Time to start vector envs: `python benchmarks/start_time.py [REPEATS]`.

Times `make_vec` (workers started, envs built, spaces exchanged; no reset) of four "uniros/Rx200Reach-v0" envs
(clock="sim") and of one "CartPole-v1", REPEATS times each (5 by default), each in a fresh process so no import is
cached, and prints the medians. Recorded in docs/performance.md.
"""

from __future__ import annotations

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


def main() -> None:
    repeats = int(sys.argv[1]) if len(sys.argv) > 1 else 5
    for name, call in CASES.items():
        times = []
        for _ in range(repeats):
            out = subprocess.run(
                [sys.executable, "-c", SNIPPET.format(call=call)], capture_output=True, text=True, check=True
            )
            times.append(float(out.stdout.strip().splitlines()[-1]))
        print(
            f"{name}: median {statistics.median(times):.3f} s over {repeats} ({', '.join(f'{t:.3f}' for t in times)})"
        )


if __name__ == "__main__":
    main()
