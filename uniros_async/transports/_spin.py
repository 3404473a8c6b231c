"""The polling rule the shm and tcp transports share: when a receive may poll for the next frame instead of
sleeping, for how long, and when it gives polling up.

Why poll: a receiver that sleeps in the event loop is woken by the kernel, and waking a halted core costs more than
the rest of a small round trip on the project's 2-core machines (docs/performance.md has the figures). In a
request/reply exchange the answer usually comes sooner than a sleeping process wakes up, and while both ends keep
polling neither core halts. So before it sleeps, a receive that may be waiting for an answer polls its medium (the
ring's write position, the socket) for up to a window, yielding the CPU between polls (``spin_yield``) so that a
peer waiting for this core runs at once.

The window is the transport's ``spin_ns`` plus, after a large send, the time the peer needs to read that frame
before it can answer (at most ``SPIN_EXTRA_NS`` more).

Credit (``SpinCredit``): a poll that finds nothing costs one credit; a connection without credit sleeps at once,
until a wait turns out shorter than its window plus ``SPIN_WAKEUP_NS`` (a poll would have caught that frame), which
earns one credit back; a poll that finds its frame restores the full credit. So an idle receiver polls a few times,
then sleeps; a slow peer (a 10 Hz arm's states) stops the polling at once.

A shared core: a poll only pays while the peer runs on another core. A woken process is often placed on its
waker's core (a socket's sync wake-up does that, more so in a VM whose other vCPU halted and looks busy to the
scheduler); the two ends then take turns on one core, each poll holding the core its peer needs, while the other
core idles, until the scheduler moves one of them. So a poll that has lasted ``SHARED_CORE_NS`` looks where the peer
runs: shm from the page both ends share (``R_CPU``), tcp from ``/proc/PID/stat`` (``peer_cpu``, at most once per
``LOOK_EVERY_NS``). An end that finds its peer on its own core stops polling, and, where it can, has itself moved
(``on_shared_core``: a worker moves itself, ``runtime.worker``).
"""

from __future__ import annotations

import os
import time

from uniros_async.transports.base import this_cpu

__all__ = [
    "LOOK_EVERY_NS",
    "SHARED_CORE_NS",
    "SPIN_CREDIT",
    "SPIN_EXTRA_NS",
    "SPIN_WAKEUP_NS",
    "SpinCredit",
    "now_ns",
    "peer_cpu",
    "spin_yield",
    "this_cpu",
]

SPIN_CREDIT = 4
"""Polls in a row that may find nothing before a connection stops polling."""
SPIN_WAKEUP_NS = 50_000
"""A wait this much longer than the window would still have been caught by a poll (it earns a credit back)."""
SPIN_EXTRA_NS = 150_000
"""At most this much longer a window after a large send."""
SHARED_CORE_NS = 50_000
"""A poll that lasts this long looks where the peer runs."""
LOOK_EVERY_NS = 1_000_000
"""tcp's look at the peer's core reads /proc: at most this often per connection."""

now_ns = time.perf_counter_ns
"""The clock a poll reads its window on (CLOCK_MONOTONIC on Linux, as the compiled ring end's)."""
spin_yield = getattr(os, "sched_yield", lambda: None)
"""What a poll does between two looks: lets whatever waits for this core run now (if the scheduler agrees: under
EEVDF a yield often returns at once, which is why a long poll looks where the peer is)."""


class SpinCredit:
    """A connection's credit for polling (module docstring), as a base of the transport, so that its hot paths read
    and write ``_spin_credit`` as a plain attribute: a poll that finds its frame sets it to ``SPIN_CREDIT``, one
    that finds nothing takes one off, and ``_waited`` gives one back after a wait a poll would have caught.
    ``_spin_allowed`` False: never polls (both ends in one process, where the peer likely runs on this very event
    loop and a poll cannot help). The transport sets both in its ``__init__``."""

    _spin_credit: int
    _spin_allowed: bool

    def _waited(self, t0_ns: int, window: int) -> None:
        """After a wait that began at ``t0_ns`` (on ``now_ns``) following a poll window of ``window`` ns: without
        credit, a wait a poll would have caught earns one back."""
        if self._spin_credit <= 0 and window and self._spin_allowed and now_ns() - t0_ns < window + SPIN_WAKEUP_NS:
            self._spin_credit = 1


def peer_cpu(pid: int) -> int | None:
    """The core process ``pid`` last ran on (``/proc/PID/stat``'s ``processor``), or None when it is gone or this
    host has no such file."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            return int(f.read().rpartition(b")")[2].split()[36])
    except (OSError, ValueError, IndexError):
        return None
