"""Order statistics for benchmark samples (medians and percentiles, never means of latencies); the report; a
progress counter."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["progress_counter", "report", "summary"]


def summary(samples: Sequence[float]) -> dict[str, float]:
    """p50, p90, p99, IQR, min, max and count of ``samples`` (NaN when empty)."""
    if len(samples) == 0:
        nan = float("nan")
        return {"p50": nan, "p90": nan, "p99": nan, "iqr": nan, "min": nan, "max": nan, "count": 0}
    a = np.asarray(samples, dtype=np.float64)
    p25, p50, p75, p90, p99 = np.percentile(a, [25, 50, 75, 90, 99])
    return {
        "p50": float(p50),
        "p90": float(p90),
        "p99": float(p99),
        "iqr": float(p75 - p25),
        "min": float(a.min()),
        "max": float(a.max()),
        "count": int(a.size),
    }


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
    from tqdm import tqdm

    bar = tqdm(total=total, desc=desc, unit=unit, leave=False)

    def step(n: int, done: bool = False) -> None:
        if n:
            bar.update(n)
        if done:
            bar.close()

    return step
