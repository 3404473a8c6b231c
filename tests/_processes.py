"""Whether processes the tests started (workers, pollers, Ray's workers) are still there.

Imported as ``_processes``: tests/ is on ``sys.path`` (pytest's default import mode puts the folder of
tests/conftest.py there).
"""

from __future__ import annotations

import os
import time


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` runs; a zombie (exited, not yet reaped by its parent) counts as gone."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ", 1)[1][0] != "Z"
    except FileNotFoundError:
        return False


def wait_gone(pids: list[int], timeout_s: float) -> list[int]:
    """Wait up to ``timeout_s`` for every one of ``pids`` to be gone; those still alive then (none: all gone)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if not any(pid_alive(p) for p in pids):
            return []
        time.sleep(0.05)
    return [p for p in pids if pid_alive(p)]
