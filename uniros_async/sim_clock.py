"""SimClock: simulated time that every timer and sleep of the nodes using it follows.

The simulation is the time source. A SimClock keeps a heap of sleepers (``sleep_until`` deadlines) and time
only moves when its driver (``run()``, started by the servo sim node) advances it: a discrete-event scheduler.
Each round the driver

1. lets every runnable task of the event loop run until all of them wait again (in-process messages, timer
   callbacks, the servo's own tick: nothing is runnable any more);
2. takes the earliest pending deadline of *any* sleeper (the servo's next hardware tick, an env loop's timer, an
   action cycle, a modelled delay);
3. with ``time_scale=None`` jumps straight to it; with a finite ``time_scale`` first waits until wall time
   catches up (``time_scale=1.0``: real time, ``10.0``: ten times faster);
4. sets the time and wakes every sleeper whose deadline has come, in deadline order (ties: first come, first
   woken), and tells the listeners (the node publishing ``ClockTick`` on ``/clock``).

So with ``time_scale=None`` an env loop at 10 Hz beside a 10 Hz servo sim in the same process runs as fast as the
CPU allows, and every period, action repeat and action cycle keeps its meaning exactly: in-process timers fire at
their deadlines to the nanosecond of sim time.

Other processes follow with ``follow_clock(node, clock)``: a SimClock in follower mode takes its time from the
``ClockTick`` messages on ``/clock`` and wakes its own sleepers from them. The source does not know a follower's
deadlines, so a follower's timers fire at the first tick at or after their deadline (within one hardware period
of the source); with a finite ``time_scale`` the source's pacing bounds this, in unbounded mode there is no
lockstep across processes (that would need a barrier protocol): run cross-process sims with a time scale.

``pause()`` stops the driver from advancing (sleepers stay asleep; the world stands still while a turn-based agent
thinks, or while a synchronous ``step`` is not running); ``resume()`` goes on from the same sim time.

Everything an event wakes sees ``now_ns()`` equal to that event's time exactly (stamps are exact multiples of the
hardware period). With a finite time scale, code that runs *between* events (woken by I/O, e.g. an agent's
``step`` request) sees ``now_ns()`` interpolated with wall time (never past the next pending deadline), so a
sleep it computes from ``now_ns()`` means the same as in real time.
"""

from __future__ import annotations

import asyncio
import contextlib
import heapq
import itertools
import logging
import math
import time
import weakref
from collections.abc import Callable
from typing import Any

from uniros_async.clock import Clock, wall_clock
from uniros_async.errors import ConfigError

__all__ = ["SimClock", "follow_clock"]

logger = logging.getLogger(__name__)


class SimClock(Clock):
    """Simulated time in integer ns, driven by a simulation (see the module docstring).

    Args:
        time_scale: sim seconds per wall second (1.0: real time); None: unbounded, as fast as the CPU allows.
        start_ns: the time at start.
        follower: True for a clock that follows another process's ``/clock`` (``follow_clock``); it has no driver.
        max_lag_s: with a finite time scale, when the driver falls behind wall time by more than this (a busy
            machine), it re-anchors instead of replaying the backlog in a burst (counted in ``lag_resets``).

    Raises:
        ConfigError: ``time_scale`` is not None and not a finite value > 0.
    """

    def __init__(
        self,
        *,
        time_scale: float | None = None,
        start_ns: int = 0,
        follower: bool = False,
        max_lag_s: float = 0.25,
    ) -> None:
        _check_scale(time_scale)
        self._now = int(start_ns)
        self._scale = time_scale
        self.follower = follower
        self.max_lag_s = max_lag_s
        self._heap: list[tuple[int, int, asyncio.Future[None]]] = []
        self._seq = itertools.count()
        self._changed: asyncio.Event | None = None
        self._listeners: list[Callable[[int], Any]] = []
        self._driving = False
        self._paused = False
        self._between_events = False  # the driver waits for wall time: now_ns() interpolates
        self._wall0 = 0
        self._sim0 = 0
        self.advances = 0
        self.lag_resets = 0

    # ------------------------------------------------------------------------------------------- pausing

    @property
    def paused(self) -> bool:
        """True while time is frozen (``pause()``)."""
        return self._paused

    def pause(self) -> None:
        """Freeze time: the driver advances nothing until ``resume()``.

        A turn-based agent pauses the world while it thinks: an env in ``clock="sim"`` pauses when ``step``
        returns and resumes when the next ``step`` starts, so the sim does not run ahead of the agent.
        """
        self._paused = True
        if self._changed is not None:
            self._changed.set()  # a paced driver waiting for wall time re-plans at once

    def resume(self) -> None:
        """Let time move again (re-anchored to wall time, so a finite time scale does not catch up in a burst)."""
        if not self._paused:
            return
        self._paused = False
        self._anchor()
        if self._changed is not None:
            self._changed.set()

    # ------------------------------------------------------------------------------------------- Clock interface

    @property
    def time_scale(self) -> float | None:
        """Sim seconds per wall second; None: unbounded."""
        return self._scale

    @time_scale.setter
    def time_scale(self, value: float | None) -> None:
        _check_scale(value)
        self._scale = value
        self._anchor()
        if self._changed is not None:
            self._changed.set()

    @property
    def is_wall(self) -> bool:
        return self._scale == 1.0

    @property
    def running(self) -> bool:
        """True while a driver (``run()``) advances this clock."""
        return self._driving

    def now_ns(self) -> int:
        if self._scale is None or not self._between_events or self._paused:
            return self._now  # exact event time for everything the event woke
        interp = self._sim0 + int((time.monotonic_ns() - self._wall0) * self._scale)
        nxt = self.next_deadline_ns()
        if nxt is not None:
            interp = min(interp, nxt)
        return max(self._now, interp)

    async def sleep_until(self, deadline_ns: int, *, spin: bool = True) -> None:
        """Return once this clock reaches ``deadline_ns``; cancellation removes the sleeper (``spin``: ignored,
        a simulated deadline is exact)."""
        if deadline_ns <= self._now:
            await asyncio.sleep(0)
            return
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[None] = loop.create_future()
        heapq.heappush(self._heap, (deadline_ns, next(self._seq), fut))
        if self._changed is not None and self._heap[0][2] is fut:
            self._changed.set()  # an earlier deadline than the driver is waiting for
        await fut  # a cancelled future is dropped lazily from the heap

    # ------------------------------------------------------------------------------------------- advancing

    def next_deadline_ns(self) -> int | None:
        """The earliest deadline of a live sleeper, or None."""
        heap = self._heap
        while heap and heap[0][2].done():
            heapq.heappop(heap)
        return heap[0][0] if heap else None

    @property
    def pending(self) -> int:
        """Live sleepers (a count; cancelled ones are dropped first)."""
        return sum(1 for _, _, f in self._heap if not f.done())

    def add_listener(self, callback: Callable[[int], Any]) -> None:
        """Call ``callback(now_ns)`` after every advance (e.g. to publish ``ClockTick``)."""
        self._listeners.append(callback)

    def remove_listener(self, callback: Callable[[int], Any]) -> None:
        with contextlib.suppress(ValueError):
            self._listeners.remove(callback)

    def advance_to(self, t_ns: int) -> int:
        """Set the time to ``t_ns`` (never backwards) and wake every sleeper due by then.

        Returns:
            How many sleepers were woken.
        """
        if t_ns > self._now:
            self._now = t_ns
        now, heap, woken = self._now, self._heap, 0
        while heap and heap[0][0] <= now:
            _, _, fut = heapq.heappop(heap)
            if not fut.done():
                fut.set_result(None)
                woken += 1
        self.advances += 1
        for cb in self._listeners:
            cb(now)
        return woken

    def _anchor(self) -> None:
        self._wall0 = time.monotonic_ns()
        self._sim0 = self._now

    async def run(self) -> None:
        """Drive this clock until cancelled (the servo sim node runs this in its TaskGroup).

        Raises:
            ConfigError: the clock is a follower, or another driver already runs it.
        """
        if self.follower:
            raise ConfigError("this SimClock follows /clock (follower=True); it cannot be driven")
        if self._driving:
            raise ConfigError("this SimClock already has a driver")
        loop = asyncio.get_running_loop()
        settling = _settling(loop)
        self._changed = asyncio.Event()
        self._driving = True
        self._anchor()
        changed = self._changed
        try:
            while True:
                await _settle(loop, settling)
                if self._paused:
                    changed.clear()
                    await changed.wait()
                    continue
                nxt = self.next_deadline_ns()
                if nxt is None:
                    changed.clear()
                    await changed.wait()
                    continue
                scale = self._scale
                if scale is not None:
                    wall_due = self._wall0 + int((nxt - self._sim0) / scale)
                    late_ns = time.monotonic_ns() - wall_due
                    if late_ns > self.max_lag_s * 1e9:
                        self.lag_resets += 1
                        logger.debug("SimClock fell %.3f s behind wall time; re-anchoring", late_ns / 1e9)
                        self._anchor()
                        self._sim0 = nxt
                    elif late_ns < 0:
                        if not await self._wait_wall(wall_due, changed):
                            continue  # an earlier sleeper, a pause or a new time scale: plan again
                self.advance_to(nxt)
        finally:
            self._driving = False
            self._changed = None

    async def _wait_wall(self, wall_due_ns: int, changed: asyncio.Event) -> bool:
        """Wait until wall time ``wall_due_ns``; False if the plan changed first (``changed`` was set)."""
        changed.clear()
        self._between_events = True
        try:
            coarse_s = (wall_due_ns - time.monotonic_ns()) / 1e9 - 0.0015
            if coarse_s > 0:
                try:
                    async with asyncio.timeout(coarse_s):
                        await changed.wait()
                    return False
                except TimeoutError:
                    pass
            # the last stretch on the precise wall clock (asyncio rounds its timeouts to ~1 ms)
            await wall_clock().sleep_until(wall_due_ns)
            return not changed.is_set()
        finally:
            self._between_events = False


_SETTLING: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, list[int]] = weakref.WeakKeyDictionary()
"""Per loop, how many drivers are in ``_settle`` now (each has one yield in the ready queue while another runs)."""


def _settling(loop: asyncio.AbstractEventLoop) -> list[int]:
    """``loop``'s count of drivers in ``_settle`` (``_SETTLING``), looked up once per driver."""
    return _SETTLING.setdefault(loop, [0])


async def _settle(loop: asyncio.AbstractEventLoop, settling: list[int]) -> None:
    """Yield until no other callback of ``loop`` is runnable (every task waits again), the yields of other drivers
    settling on the same loop aside: two sims driven on one loop (a worker process hosting two envs) each see the
    other's yield in the ready queue, and without that count neither would settle before its 10,000th yield.

    The default loop exposes its ready queue; for others (uvloop) a fixed number of yields approximates it.
    """
    ready = getattr(loop, "_ready", None)
    if ready is None:
        for _ in range(16):
            await asyncio.sleep(0)
        return
    settling[0] += 1
    try:
        for _ in range(10_000):
            await asyncio.sleep(0)
            if len(ready) < settling[0]:
                return
    finally:
        settling[0] -= 1


def _check_scale(time_scale: float | None) -> None:
    if time_scale is not None and not (math.isfinite(time_scale) and time_scale > 0.0):
        raise ConfigError(f"SimClock.time_scale: expected None (unbounded) or a finite value > 0, got {time_scale}")


async def follow_clock(node: Any, clock: SimClock, topic: str = "/clock") -> Any:
    """Make ``clock`` (a follower SimClock) follow the ``ClockTick`` messages of ``topic`` seen by ``node``.

    Args:
        node: a bus Node of this process (any clock).
        clock: ``SimClock(follower=True)``; typically also the clock of the nodes that should follow.
        topic: where the source publishes.

    Returns:
        The Subscription (close it to stop following).

    Raises:
        ConfigError: ``clock`` is not a follower.
    """
    from uniros_async.bus.messages import ClockTick
    from uniros_async.bus.qos import latest

    if not clock.follower:
        raise ConfigError("follow_clock needs SimClock(follower=True)")

    def on_tick(msg: ClockTick) -> None:
        clock.advance_to(msg.sim_time_ns)

    return await node.create_subscription(ClockTick, topic, on_tick, qos=latest())
