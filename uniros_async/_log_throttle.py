"""Rate-limited warnings for what peers can trigger at will (malformed requests, refused connections).

A stranger who sends a million bad frames must not write a million log lines: ``LogThrottle`` lets one line through
per ``period_s`` and adds to the next one how many it held back.
"""

from __future__ import annotations

import logging
import time

__all__ = ["LogThrottle"]


class LogThrottle:
    """At most one record per ``period_s``; the next one says how many similar ones were not logged.

    Args:
        logger: where records go.
        period_s: the shortest time between two records.
    """

    def __init__(self, logger: logging.Logger, period_s: float = 1.0) -> None:
        self._logger = logger
        self._period_s = period_s
        self._next_s = 0.0
        self.suppressed = 0
        """Records held back since the last one logged."""

    def log(self, level: int, msg: str, *args: object) -> None:
        now = time.monotonic()
        if now < self._next_s:
            self.suppressed += 1
            return
        self._next_s = now + self._period_s
        if self.suppressed:
            msg += " (%d similar messages suppressed)"
            args = (*args, self.suppressed)
            self.suppressed = 0
        self._logger.log(level, msg, *args)

    def warning(self, msg: str, *args: object) -> None:
        self.log(logging.WARNING, msg, *args)
