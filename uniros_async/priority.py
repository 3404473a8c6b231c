"""Scheduling priority of real-time loop processes (env workers on the wall clock, servo sim processes).

On a shared 2-core machine the env loop's timer fires on time only if its process gets a core when it wakes; a
learner, a test suite or another env loop beside it delays that by a scheduler slice (milliseconds). A lower nice
value gives a process more of the CPU and makes the kernel preempt ordinary processes when it wakes, the cheap,
unprivileged-safe cousin of the real-time scheduling classes that ros2_control uses for its control loops.
(SCHED_FIFO is not used: a bug that kept such a loop runnable would freeze the machine.)

Lowering nice needs root or CAP_SYS_NICE; without it the process keeps its priority and says so in a debug log.
``UNIROS_LOOP_NICE`` sets the value (default -10; ``0`` or ``off`` leaves priorities alone).
"""

from __future__ import annotations

import logging
import os

__all__ = ["DEFAULT_LOOP_NICE", "loop_nice", "raise_loop_priority"]

logger = logging.getLogger(__name__)

DEFAULT_LOOP_NICE = -10


def loop_nice() -> int | None:
    """The nice value asked for by ``UNIROS_LOOP_NICE`` (default -10), or None when disabled.

    Raises:
        ValueError: the variable is neither an integer in [-20, 19] nor ``off``.
    """
    raw = os.environ.get("UNIROS_LOOP_NICE", "").strip().lower()
    if raw in ("", "default"):
        return DEFAULT_LOOP_NICE
    if raw in ("off", "0", "none"):
        return None
    try:
        value = int(raw)
    except ValueError:
        raise ValueError(f"UNIROS_LOOP_NICE must be an integer in [-20, 19] or 'off', got {raw!r}") from None
    if not -20 <= value <= 19:
        raise ValueError(f"UNIROS_LOOP_NICE must be an integer in [-20, 19] or 'off', got {value}")
    return value


def raise_loop_priority() -> bool:
    """Set this process's nice value to ``loop_nice()`` if that is lower than its own. True if it was set."""
    want = loop_nice()
    if want is None or not hasattr(os, "setpriority"):
        return False
    try:
        if os.getpriority(os.PRIO_PROCESS, 0) <= want:
            return False
        os.setpriority(os.PRIO_PROCESS, 0, want)
    except PermissionError:
        logger.debug("not permitted to set nice %d (needs root or CAP_SYS_NICE); the loop keeps its priority", want)
        return False
    return True
