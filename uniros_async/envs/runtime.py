"""An asyncio event loop in a background thread, so the env loop keeps running while the agent computes.

gymnasium's ``step`` is a blocking call; the env loop must not stop between calls (that is the whole point of a
real-time env). So the env's bus nodes, the in-process servo sim and the env loop timer live in a loop on a
daemon thread, and ``step``/``reset`` hand coroutines to it and wait for the result under a timeout.
(Worker processes, the runtime issue, take the GIL out of the picture as well.)
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import threading
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any, TypeVar

__all__ = ["LoopThread"]

T = TypeVar("T")


class LoopThread:
    """Runs ``main(started)`` on a private event loop in a daemon thread until ``close()``.

    ``main`` receives a callback to call once it is ready (or with an exception if it failed to start) and must
    return when cancelled; everything it opens it closes in its own ``finally``/``async with``.
    """

    def __init__(self, main: Callable[[Callable[[BaseException | None], None]], Awaitable[None]], name: str) -> None:
        self._main = main
        self._ready: concurrent.futures.Future[None] = concurrent.futures.Future()
        self._done: concurrent.futures.Future[None] = concurrent.futures.Future()
        self.loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task[None] | None = None
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._closed = False

    def start(self, timeout_s: float) -> None:
        """Start the thread and wait until ``main`` reported ready.

        Raises:
            TimeoutError: not ready within ``timeout_s``.
            Exception: what ``main`` raised while starting.
        """
        self._thread.start()
        try:
            self._ready.result(timeout_s)
        except concurrent.futures.TimeoutError:
            self.close(5.0)
            raise TimeoutError(f"{self._thread.name} did not start within {timeout_s} s") from None
        except BaseException:
            self.close(5.0)
            raise

    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        self.loop = loop
        try:
            self._task = loop.create_task(self._wrapped())
            loop.run_until_complete(self._task)
        except BaseException as exc:  # noqa: BLE001 - reported through the futures
            if not self._ready.done():
                self._ready.set_exception(exc)
            if not self._done.done():
                self._done.set_exception(exc)
        finally:
            try:
                loop.run_until_complete(loop.shutdown_asyncgens())
            finally:
                loop.close()
            if not self._done.done():
                self._done.set_result(None)

    async def _wrapped(self) -> None:
        def started(exc: BaseException | None) -> None:
            if self._ready.done():
                return
            if exc is None:
                self._ready.set_result(None)
            else:
                self._ready.set_exception(exc)

        try:
            await self._main(started)
        except asyncio.CancelledError:
            if not self._ready.done():
                self._ready.set_exception(RuntimeError("closed before it started"))

    def failure(self) -> BaseException | None:
        """Why ``main`` stopped, once it has stopped (None while running or after a clean close)."""
        if not self._done.done():
            return None
        return self._done.exception()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive() and not self._done.done()

    def call(self, coro: Coroutine[Any, Any, T], timeout_s: float) -> T:
        """Run ``coro`` on the loop and wait for its result.

        Raises:
            TimeoutError: no result within ``timeout_s`` (the coroutine is cancelled).
            RuntimeError: the loop is not running (closed, or its main failed).
        """
        if self.loop is None or not self.alive:
            coro.close()
            raise RuntimeError(f"{self._thread.name} is not running")
        fut = asyncio.run_coroutine_threadsafe(coro, self.loop)
        try:
            return fut.result(timeout_s)
        except concurrent.futures.TimeoutError:
            fut.cancel()
            raise TimeoutError(f"no result within {timeout_s} s") from None

    def close(self, timeout_s: float = 10.0) -> None:
        """Cancel ``main`` and join the thread; idempotent, bounded by ``timeout_s``."""
        if self._closed:
            return
        self._closed = True
        loop, task = self.loop, self._task
        if loop is not None and task is not None and not loop.is_closed():
            loop.call_soon_threadsafe(task.cancel)
        self._thread.join(timeout_s)
