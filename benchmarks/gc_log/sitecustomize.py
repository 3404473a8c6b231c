"""Log every full garbage collection of every Python process that starts with this folder on ``PYTHONPATH``
(workers and arm processes inherit it): one line per collection in ``$UNIROS_GC_LOG_DIR/<pid>.txt`` (default
``/tmp/uniros_gc_log``): wall time at its end, its duration in ms, the objects it freed, the objects frozen
(``gc.freeze``) at that moment.

    mkdir -p /tmp/uniros_gc_log
    PYTHONPATH=benchmarks/gc_log python benchmarks/gc_first_reset.py 120
    PYTHONPATH=benchmarks/gc_log uniros bench latency --scenario concurrent --duration 80 --load cpu gil torch gc

docs/reliability.md ("A full garbage collection on the loop's thread") has what it showed.
"""

from __future__ import annotations

import gc
import os
import time
from typing import Any

_DIR = os.environ.get("UNIROS_GC_LOG_DIR", "/tmp/uniros_gc_log")
_started: list[float] = [0.0]
try:
    _out = open(os.path.join(_DIR, f"{os.getpid()}.txt"), "a", buffering=1)  # noqa: SIM115 - for the process's life
except OSError:  # no such folder: log nothing
    _out = None


def _on_collect(phase: str, info: dict[str, Any]) -> None:
    if info.get("generation") != 2 or _out is None:
        return
    if phase == "start":
        _started[0] = time.perf_counter()
        return
    ms = (time.perf_counter() - _started[0]) * 1e3
    _out.write(f"{time.time():.3f} {ms:.2f} {info.get('collected')} frozen={gc.get_freeze_count()}\n")


gc.callbacks.append(_on_collect)
