"""The bag's errors: BagError, and BagDamagedError for a file that reads only up to a byte offset (defined in
``uniros_async.errors`` with every other error)."""

from __future__ import annotations

from uniros_async.errors import BagDamagedError, BagError

__all__ = ["BagDamagedError", "BagError"]
