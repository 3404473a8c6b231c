"""What the env loop and ``step`` record, so benchmarks can read the paper's timing figures."""

from __future__ import annotations

import collections
import collections.abc
import dataclasses

__all__ = ["Timing"]


@dataclasses.dataclass
class Timing:
    """Time stamps (ns of the env's clock) of the env loop and the agent's steps; bounded histories.

    - ``tick_ns``: every env-loop tick; ``tick_deadline_ns``: the deadline each tick was scheduled for (the loop's
      absolute grid); ``command_ns``: ticks that sent a command (the actuator cycle is their
      difference);
    - ``step_ns``: when each ``step`` returned (the action cycle is their difference); ``step_deadline_ns``: the
      deadline each ``step`` returned at (a point of the action-cycle grid);
    - ``action_ns``: when each action reached the loop (with ``clock="sim"`` and a modelled agent latency, that
      latency after the previous ``step`` returned);
    - ``observation_age_ns``: how old the returned observation was when ``step`` returned;
    - ``action_latency_ns``: from an action reaching the loop to the first command sent with it;
    - ``stale_ticks``: ticks that found the newest joint state older than ``robot_timeout_s`` (nothing built or sent).
    """

    history: int = 100_000
    tick_ns: collections.deque[int] = dataclasses.field(default_factory=collections.deque)
    tick_deadline_ns: collections.deque[int] = dataclasses.field(default_factory=collections.deque)
    command_ns: collections.deque[int] = dataclasses.field(default_factory=collections.deque)
    step_ns: collections.deque[int] = dataclasses.field(default_factory=collections.deque)
    step_deadline_ns: collections.deque[int] = dataclasses.field(default_factory=collections.deque)
    action_ns: collections.deque[int] = dataclasses.field(default_factory=collections.deque)
    observation_age_ns: collections.deque[int] = dataclasses.field(default_factory=collections.deque)
    action_latency_ns: collections.deque[int] = dataclasses.field(default_factory=collections.deque)
    step_overruns: int = 0
    stale_ticks: int = 0
    _SERIES = (
        "tick_ns",
        "tick_deadline_ns",
        "command_ns",
        "step_ns",
        "step_deadline_ns",
        "action_ns",
        "observation_age_ns",
        "action_latency_ns",
    )

    def __post_init__(self) -> None:
        for f in self._SERIES:
            setattr(self, f, collections.deque(maxlen=self.history))

    def clear(self) -> None:
        for f in self._SERIES:
            getattr(self, f).clear()
        self.step_overruns = 0
        self.stale_ticks = 0

    def snapshot(self) -> dict[str, list[int] | int]:
        """Plain copies of every series (lists of ints) and ``step_overruns``: msgpack-able, so a benchmark can
        fetch it from a worker process with ``env.call("timing_snapshot")``."""
        out: dict[str, list[int] | int] = {f: list(getattr(self, f)) for f in self._SERIES}  # list(deque) holds the GIL
        out["step_overruns"] = self.step_overruns
        out["stale_ticks"] = self.stale_ticks
        return out

    @staticmethod
    def periods_ms(stamps: collections.abc.Iterable[int]) -> list[float]:
        """Differences of consecutive stamps, in ms."""
        s = list(stamps)
        return [(b - a) / 1e6 for a, b in zip(s, s[1:], strict=False)]
