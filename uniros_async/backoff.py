"""Exponential backoff between retries: the one helper every reconnecting loop uses.

```python
backoff = Backoff(first_s=0.005, max_s=0.5)
while True:
    try:
        return await connect(...)
    except OSError:
        await backoff.sleep(limit_s=deadline - loop.time())
```

Delays double from ``first_s`` up to ``max_s``; ``reset()`` after a success starts again from ``first_s``. The sleep
is on the event loop's (wall) clock: retries are about sockets, not about a simulated domain clock.
"""

from __future__ import annotations

import asyncio
import math

from uniros_async.errors import ConfigError

__all__ = ["Backoff"]


class Backoff:
    """Delays that double from ``first_s`` to ``max_s``.

    Args:
        first_s: the first delay (and the one after ``reset``).
        max_s: the longest delay.
        factor: how much each delay grows over the previous one.
    """

    def __init__(self, *, first_s: float, max_s: float, factor: float = 2.0) -> None:
        if not 0 < first_s <= max_s or factor < 1:
            raise ConfigError(f"backoff needs 0 < first_s <= max_s and factor >= 1, got {first_s}, {max_s}, {factor}")
        self.first_s = first_s
        self.max_s = max_s
        self.factor = factor
        self._next_s = first_s

    @property
    def delay_s(self) -> float:
        """The delay the next ``sleep`` (or ``next_s``) will take."""
        return self._next_s

    @property
    def at_first(self) -> bool:
        """No retry has waited since the start or the last ``reset`` (a first failure may be worth logging louder)."""
        return self._next_s == self.first_s

    def next_s(self) -> float:
        """The current delay; the one after it grows."""
        delay = self._next_s
        self._next_s = min(delay * self.factor, self.max_s)
        return delay

    def reset(self) -> None:
        """Start again from ``first_s`` (call it after a success)."""
        self._next_s = self.first_s

    async def sleep(self, *, limit_s: float = math.inf) -> None:
        """Sleep for the current delay (at most ``limit_s``, never below 0), then grow it. Cancellable."""
        await asyncio.sleep(max(0.0, min(self.next_s(), limit_s)))
