"""An environment variable set for the length of a block: how a benchmark chooses what the workers it starts there
read when they start (``UNIROS_LOOP_PRIORITY``, ``UNIROS_SHARED_CORES``)."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

__all__ = ["environ_set"]


@contextlib.contextmanager
def environ_set(name: str, value: str | None) -> Iterator[None]:
    """``os.environ[name] = value`` for the block, then as it was before (unset if it was); ``value`` None leaves
    the variable as this process has it."""
    if value is None:
        yield
        return
    before = os.environ.get(name)
    os.environ[name] = value
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = before
