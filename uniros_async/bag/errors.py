"""The bag's errors: BagError, and BagDamagedError for a file that reads only up to a byte offset."""

from __future__ import annotations

from uniros_async.errors import UnirosError

__all__ = ["BagDamagedError", "BagError"]


class BagError(UnirosError):
    """A bag cannot be written or read as asked (names the file and what was wrong)."""


class BagDamagedError(BagError):
    """A bag is truncated or corrupt at byte ``offset``: everything before it was read."""

    def __init__(self, message: str, *, path: str, offset: int) -> None:
        super().__init__(message)
        self.path = path
        self.offset = offset
