"""The worker processes this test process started and that still run: local workers (``launch.live_workers``,
started as ``python -m uniros_async.runtime``) and anything multiprocessing started (servo
processes)."""

from __future__ import annotations

import multiprocessing
from typing import Any

from uniros_async.runtime.launch import live_workers


def children() -> list[Any]:
    """Every child this process started that still runs."""
    return [*multiprocessing.active_children(), *live_workers()]
