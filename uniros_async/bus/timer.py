"""Timers at absolute deadlines of a node's clock."""

from __future__ import annotations

import asyncio
import collections
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

from uniros_async.bus._local import (
    _maybe_await,
)
from uniros_async.errors import (
    ConfigError,
)

if TYPE_CHECKING:
    from uniros_async.bus.node import Node

logger = logging.getLogger(__name__)

M = TypeVar("M")
Req = TypeVar("Req")
Resp = TypeVar("Resp")


class Timer:
    """Calls ``callback`` every ``period_s`` of the node's clock, at absolute deadlines (``next += period``).

    ``fire_times_ns`` keeps the last ``history`` actual fire times; ``overruns`` counts deadlines missed because
    the previous callback (or the machine) ran late; missed deadlines are skipped, never fired in a burst.
    """

    def __init__(self, node: Node, period_s: float, callback: Callable[[], Any], history: int) -> None:
        if period_s <= 0:
            raise ConfigError(f"timer period_s must be > 0, got {period_s}")
        self.node = node
        self.period_ns = round(period_s * 1e9)
        self.callback = callback
        self.fire_times_ns: collections.deque[int] = collections.deque(maxlen=history)
        self.deadlines_ns: collections.deque[int] = collections.deque(maxlen=history)
        self.overruns = 0
        self.fired = 0
        self._task: asyncio.Task[None] | None = None

    @property
    def period_s(self) -> float:
        return self.period_ns / 1e9

    async def _run(self, start_ns: int | None) -> None:
        clock = self.node.clock
        nxt = start_ns if start_ns is not None else clock.now_ns() + self.period_ns
        cb = self.callback
        while True:
            await clock.sleep_until(nxt)
            now = clock.now_ns()
            self.fire_times_ns.append(now)
            self.deadlines_ns.append(nxt)
            self.fired += 1
            r = _maybe_await(cb())
            if r is not None:
                await r
            nxt += self.period_ns
            now = clock.now_ns()
            if now >= nxt:
                missed = (now - nxt) // self.period_ns + 1
                self.overruns += missed
                nxt += missed * self.period_ns

    def cancel(self) -> None:
        """Stop firing."""
        if self._task is not None:
            self._task.cancel()
