"""Memory-bandwidth load for latency runs: `python benchmarks/memory_hog.py SECONDS`.

Copies two 128 MB arrays back and forth at nice 19 for SECONDS, so that whatever core the real-time processes of
`uniros bench latency` leave free streams through memory and shares the caches and memory bus with them (a proxy
for a busier host; it takes no CPU time from SCHED_RR processes):

    python benchmarks/memory_hog.py 130 & uniros bench latency; wait
"""

import os
import sys
import time

import numpy as np

os.nice(19)
a = np.ones(16_000_000, dtype=np.float64)
b = np.empty_like(a)
end = time.monotonic() + float(sys.argv[1])
while time.monotonic() < end:
    np.copyto(b, a)
    np.copyto(a, b)
