"""Signals as cancellation: a long-running process's main task ends cleanly (its ``finally`` blocks and task
groups unwind) when asked to stop, instead of dying mid-write."""

from __future__ import annotations

import asyncio
import signal
from typing import Any

__all__ = ["cancel_on_signals"]


def cancel_on_signals(*signals: signal.Signals) -> asyncio.Task[Any]:
    """Cancel the calling task when any of ``signals`` arrives (a handler on the running loop); returns the task."""
    loop = asyncio.get_running_loop()
    task = asyncio.current_task()
    if task is None:
        raise RuntimeError("cancel_on_signals must be called from inside a task")
    for sig in signals:
        loop.add_signal_handler(sig, task.cancel)
    return task
