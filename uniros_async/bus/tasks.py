"""A TaskGroup for objects that live across an ``async with`` body (nodes, domains)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator

__all__ = ["unwrap_task_group"]


@contextlib.asynccontextmanager
async def unwrap_task_group() -> AsyncIterator[asyncio.TaskGroup]:
    """``asyncio.TaskGroup`` whose body's own exception comes out as itself, not inside an ExceptionGroup.

    A node's tasks belong to a TaskGroup held open across the user's ``async with open_node(...)`` block. When
    that block raises (a ConfigError, a failed assertion), the user should see that error, not an
    ExceptionGroup wrapping it; errors of the node's own tasks still come out as the ExceptionGroup they are
    (several may fail at once).
    """
    body_error: BaseException | None = None
    try:
        async with asyncio.TaskGroup() as tg:
            try:
                yield tg
            except BaseException as exc:
                body_error = exc
                raise
    except BaseExceptionGroup as eg:
        if body_error is not None and len(eg.exceptions) == 1 and eg.exceptions[0] is body_error:
            raise body_error from body_error.__cause__  # keep its own cause, drop the group context
        raise
