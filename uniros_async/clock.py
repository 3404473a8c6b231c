"""Clocks: every timer, sleep and stamp in uniros_async goes through one of these, never through ``time`` directly.

``WallClock`` follows ``time.monotonic_ns()``. asyncio's own timers cannot hit a deadline closer than about a
millisecond on Linux: the selector rounds its timeout up to whole milliseconds before ``epoll_wait``. The env loop
must fire within 0.1 ms of its period, so on Linux WallClock sleeps on a ``timerfd`` armed
with an absolute CLOCK_MONOTONIC deadline and registered in the event loop with ``add_reader``: the kernel wakes
the loop at the deadline, with nanosecond resolution, without busy waiting. Elsewhere it falls back to
``asyncio.sleep``.

``SimClock`` (in the robots issue) follows the simulation's published time; both share the ``Clock`` interface.
"""

from __future__ import annotations

import abc
import asyncio
import contextlib
import ctypes
import logging
import os
import sys
import time
import weakref

__all__ = ["Clock", "WallClock", "grid_after", "grid_before", "wall_clock"]

logger = logging.getLogger(__name__)


def grid_after(t_ns: int, period_ns: int, offset_ns: int = 0) -> int:
    """The first point of the grid ``offset_ns + k * period_ns`` (k any integer) at or after ``t_ns``.

    Loops that start on a common grid of the clock keep a common phase across processes and envs: every 10 Hz and
    25 Hz loop started this way ticks together at multiples of 200 ms, and action cycles that are multiples of both
    periods end together (the vector env's members return fresh observations at the same time).
    """
    if period_ns <= 0:
        raise ValueError(f"period_ns must be > 0, got {period_ns}")
    return offset_ns + -((offset_ns - t_ns) // period_ns) * period_ns


def grid_before(t_ns: int, period_ns: int, offset_ns: int = 0) -> int:
    """The last point of the grid ``offset_ns + k * period_ns`` at or before ``t_ns``."""
    if period_ns <= 0:
        raise ValueError(f"period_ns must be > 0, got {period_ns}")
    return offset_ns + ((t_ns - offset_ns) // period_ns) * period_ns


class Clock(abc.ABC):
    """A source of time and of sleeps until absolute deadlines, in integer nanoseconds."""

    @abc.abstractmethod
    def now_ns(self) -> int:
        """The current time of this clock in ns."""

    @abc.abstractmethod
    async def sleep_until(self, deadline_ns: int, *, spin: bool = True) -> None:
        """Return at (not before) ``deadline_ns`` of this clock. Cancellation leaves nothing behind.

        ``spin=False``: the caller needs no microsecond precision (a clock may then return a little later rather
        than hold a core to hit the deadline exactly; ``WallClock`` skips its bounded spin).
        """

    async def sleep(self, duration_s: float) -> None:
        """Sleep ``duration_s`` of this clock's time."""
        await self.sleep_until(self.now_ns() + int(duration_s * 1e9))

    @property
    def is_wall(self) -> bool:
        """True when this clock runs at wall-clock speed."""
        return False


class _LibcTimerFd:
    """ctypes access to timerfd_create / timerfd_settime (os.timerfd_* arrive only in Python 3.13)."""

    CLOCK_MONOTONIC = 1
    TFD_TIMER_ABSTIME = 1
    TFD_NONBLOCK = os.O_NONBLOCK
    TFD_CLOEXEC = os.O_CLOEXEC
    PR_SET_TIMERSLACK = 29

    class _Timespec(ctypes.Structure):
        _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]

    class _Itimerspec(ctypes.Structure):
        pass

    _Itimerspec._fields_ = [("it_interval", _Timespec), ("it_value", _Timespec)]

    def __init__(self) -> None:
        # the symbols already loaded into this process, libc's among them: ctypes.util.find_library("c") would run
        # ``ldconfig -p`` in a subprocess (a process start, in every process that makes a clock)
        libc = ctypes.CDLL(None, use_errno=True)
        self._create = libc.timerfd_create
        self._create.argtypes = [ctypes.c_int, ctypes.c_int]
        self._settime = libc.timerfd_settime
        self._settime.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p]
        # The default timer slack of 50 us would be most of our error budget; 1 us keeps wakeups on time.
        # It is a per-thread setting of the calling (event-loop) thread.
        try:
            libc.prctl(self.PR_SET_TIMERSLACK, ctypes.c_ulong(1000), 0, 0, 0)
        except (AttributeError, OSError):  # pragma: no cover - prctl always exists on Linux
            pass

    def create(self) -> int:
        fd = int(self._create(self.CLOCK_MONOTONIC, self.TFD_NONBLOCK | self.TFD_CLOEXEC))
        if fd < 0:
            err = ctypes.get_errno()
            raise OSError(err, os.strerror(err))
        return fd

    def arm_abs(self, fd: int, deadline_ns: int) -> None:
        spec = self._Itimerspec()
        spec.it_value.tv_sec, spec.it_value.tv_nsec = divmod(max(deadline_ns, 1), 1_000_000_000)
        if self._settime(fd, self.TFD_TIMER_ABSTIME, ctypes.byref(spec), None) != 0:
            err = ctypes.get_errno()
            raise OSError(err, os.strerror(err))


def _load_timerfd() -> _LibcTimerFd | None:
    if not sys.platform.startswith("linux") or os.environ.get("UNIROS_NO_TIMERFD"):
        return None
    try:
        return _LibcTimerFd()
    except (OSError, AttributeError):  # pragma: no cover - very old libc
        logger.warning("timerfd unavailable; WallClock falls back to asyncio.sleep (late by the loop's resolution)")
        return None


class WallClock(Clock):
    """Real time: ``time.monotonic_ns()`` and precise absolute sleeps (timerfd on Linux).

    One timerfd is kept per event loop and re-armed for each sleep; concurrent sleepers on the same loop each get
    their own (a pool), so a sleep costs one ``timerfd_settime`` and one wakeup, not an fd creation.

    Waking a halted core takes longer than the error a loop may have (docs/performance.md has the figures). So the
    timerfd is armed ``spin_lead_ns`` early and the last stretch is a bounded spin on ``monotonic_ns``, which
    costs that lead's CPU per sleep. The spin is bounded by
    the lead and waits on nobody, so it cannot stall behind a descheduled peer. ``spin_lead_ns=0`` disables it,
    ``sleep_until(..., spin=False)`` skips it for one sleep: a spinning real-time process holds its core, and
    with more processes than cores the lower-priority ones wait for it.
    """

    def __init__(self, *, spin_lead_ns: int = 500_000) -> None:
        self._tfd = _load_timerfd()
        # idle timer fds per event loop; a loop's fds are closed when the loop is collected (tests and
        # asyncio.run() make many short-lived loops)
        self._pools: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, list[int]] = weakref.WeakKeyDictionary()
        self.spin_lead_ns = spin_lead_ns

    def now_ns(self) -> int:
        return time.monotonic_ns()

    @property
    def is_wall(self) -> bool:
        return True

    async def sleep_until(self, deadline_ns: int, *, spin: bool = True) -> None:
        loop = asyncio.get_running_loop()
        if deadline_ns <= time.monotonic_ns():
            await asyncio.sleep(0)
            return
        if self._tfd is None:
            await asyncio.sleep((deadline_ns - time.monotonic_ns()) / 1e9)
            while time.monotonic_ns() < deadline_ns:  # noqa: ASYNC110 - a sleep, not a wait: asyncio may wake early
                await asyncio.sleep((deadline_ns - time.monotonic_ns()) / 1e9)
            return
        pool = self._pools.get(loop)
        if pool is None:
            pool = self._pools[loop] = []
            weakref.finalize(loop, _close_fds, pool)
        fd = pool.pop() if pool else self._tfd.create()
        fut: asyncio.Future[None] = loop.create_future()

        def _ready() -> None:
            try:
                os.read(fd, 8)
            except BlockingIOError:  # spurious wakeup: wait for the real expiry
                return
            if not fut.done():
                fut.set_result(None)

        wake_ns = deadline_ns - self.spin_lead_ns if spin else deadline_ns
        if wake_ns > time.monotonic_ns():
            self._tfd.arm_abs(fd, wake_ns)
            loop.add_reader(fd, _ready)
            try:
                await fut
            finally:
                loop.remove_reader(fd)
                if fut.done() and not fut.cancelled():
                    pool.append(fd)
                else:  # cancelled while armed: disarm by closing; a fresh fd next time
                    os.close(fd)
        else:
            pool.append(fd)
        while time.monotonic_ns() < deadline_ns:  # bounded by spin_lead_ns
            pass

    def close(self) -> None:
        """Close pooled timer fds now (otherwise they close with their event loop)."""
        for pool in self._pools.values():
            _close_fds(pool)


def _close_fds(fds: list[int]) -> None:
    while fds:
        with contextlib.suppress(OSError):
            os.close(fds.pop())


_WALL: WallClock | None = None


def wall_clock() -> WallClock:
    """The process-wide WallClock."""
    global _WALL
    if _WALL is None:
        _WALL = WallClock()
    return _WALL
