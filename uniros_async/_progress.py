"""Progress bars that suit where they are written: tqdm on a terminal, plain periodic lines in a file.

tqdm redraws its bar with carriage returns. On a terminal that is one line updated in place; written to a file
(``uniros train ... 2> train.log``, a CI log) every redraw stays, and the log holds the bar dozens of times on one
line. So where the stream is not a terminal, ``progress_bar`` returns a ``LineProgress`` instead: the same calls,
one ordinary line at most every ``interval_s`` seconds, and one when it closes.
"""

from __future__ import annotations

import sys
import time
from typing import Any, TextIO

__all__ = ["LineProgress", "progress_bar"]

LINE_INTERVAL_S = 30.0


def progress_bar(
    *,
    total: float,
    desc: str,
    unit: str,
    initial: float = 0,
    file: TextIO | None = None,
    interval_s: float = LINE_INTERVAL_S,
    **tqdm_kwargs: Any,
) -> Any:
    """A tqdm bar on ``file`` (default stderr) if it is a terminal, else a ``LineProgress`` with the same calls.

    Args:
        total: the count at the end.
        desc: what is counted, printed first.
        unit: the unit of the count ("step", "ep", "s").
        initial: the count at the start (a resumed run).
        file: where to write; default ``sys.stderr``.
        interval_s: at most one line per this many seconds, when not a terminal.
        **tqdm_kwargs: passed to tqdm on a terminal (``mininterval``, ``bar_format``, ``leave``, ...).
    """
    stream = sys.stderr if file is None else file
    isatty = getattr(stream, "isatty", None)
    if isatty is not None and isatty():
        from tqdm import tqdm

        return tqdm(total=total, desc=desc, unit=unit, initial=initial, file=stream, **tqdm_kwargs)
    return LineProgress(total=total, desc=desc, unit=unit, initial=initial, file=stream, interval_s=interval_s)


class LineProgress:
    """tqdm's ``update``, ``n``, ``refresh``, ``set_postfix_str``, ``write`` and ``close``, as plain lines."""

    def __init__(
        self, *, total: float, desc: str, unit: str, initial: float = 0, file: TextIO, interval_s: float
    ) -> None:
        self.total, self.desc, self.unit, self.n = total, desc, unit, initial
        self._file, self._interval_s = file, interval_s
        self._postfix = ""
        self._t0 = time.monotonic()
        self._last = self._t0  # the first line comes after one interval, not at the start
        self._closed = False

    def update(self, n: float = 1) -> None:
        """Count ``n`` more; writes a line if the last one is ``interval_s`` old."""
        self.n += n
        self.refresh(force=False)

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        """Text written after the count (``success 80.0%``)."""
        self._postfix = s
        if refresh:
            self.refresh(force=False)

    def refresh(self, force: bool = False) -> None:
        """Write the current count if ``force`` or if the last line is ``interval_s`` old."""
        now = time.monotonic()
        if self._closed or not (force or now - self._last >= self._interval_s):
            return
        self._last = now
        self._file.write(self._line(now) + "\n")
        self._file.flush()

    def write(self, s: str, file: TextIO | None = None) -> None:
        """Write a message line (tqdm.write's place in a bar's output), to ``file`` if given, as tqdm's does."""
        out = self._file if file is None else file
        out.write(s.rstrip("\n") + "\n")
        out.flush()

    def close(self) -> None:
        """Write the final count once."""
        if not self._closed:
            self.refresh(force=True)
            self._closed = True

    def __enter__(self) -> LineProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _line(self, now: float) -> str:
        count = f"{self.n:.0f}/{self.total:.0f} {self.unit}"
        percent = f" ({100 * self.n / self.total:.0f} %)" if self.total else ""
        postfix = f", {self._postfix}" if self._postfix else ""
        return f"{self.desc}: {count}{percent}{postfix}, {now - self._t0:.0f} s"
