"""Where an env's world runs: an asyncio event loop in a background thread (``LoopThread``), or, attached, a task on
the caller's own running loop (``LoopTask``).

gymnasium's ``step`` is a blocking call; the env loop must not stop between calls (that is the whole point of a
real-time env). So for the synchronous API the env's bus nodes, the in-process servo sim and the env loop timer live
in a loop on a daemon thread, and ``step``/``reset`` hand coroutines to it and wait for the result under a timeout.

A caller that has an event loop of its own and keeps it running (the worker process of ``uniros_async.make_vec``)
makes the env inside ``deferred_start()`` and then runs it on that loop: ``await env.astart()``, ``await
env.astep(a)``, ``await env.areset()``, ``await env.aclose()``. No thread, no hand-over between loops: the
step's coroutine is awaited directly, and the env loop keeps ticking between calls because the caller's loop does.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import contextvars
import threading
from collections.abc import Awaitable, Callable, Coroutine, Iterator
from typing import Any, TypeVar

__all__ = ["LoopTask", "LoopThread", "deferred_start", "start_is_deferred"]

T = TypeVar("T")

_DEFERRED: contextvars.ContextVar[bool] = contextvars.ContextVar("uniros_deferred_start", default=False)


@contextlib.contextmanager
def deferred_start() -> Iterator[None]:
    """Envs made in this block (``gymnasium.make`` included) do not start a loop thread; the caller starts them on
    its own running event loop with ``await env.unwrapped.astart()`` and uses the async methods from then on."""
    token = _DEFERRED.set(True)
    try:
        yield
    finally:
        _DEFERRED.reset(token)


def start_is_deferred() -> bool:
    """True inside ``deferred_start()``."""
    return _DEFERRED.get()


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
                _cancel_leftovers(loop)  # calls whose caller left (interrupted), as asyncio.run cancels its tasks
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

        The result is handed over from inside the coroutine's last step, not from the task's done callbacks: those
        run only after everything the same event woke (in a sim, the servo tick's physics for the next period), so
        the caller would otherwise wait for work that does not belong to its call.

        Raises:
            TimeoutError: no result within ``timeout_s`` (the coroutine is cancelled).
            RuntimeError: the loop is not running (closed, or its main failed).
        """
        if self.loop is None or not self.alive:
            coro.close()
            raise RuntimeError(f"{self._thread.name} is not running")
        result: concurrent.futures.Future[T] = concurrent.futures.Future()
        task = asyncio.run_coroutine_threadsafe(_handing_over(coro, result), self.loop)
        try:
            return result.result(timeout_s)
        except concurrent.futures.TimeoutError:
            task.cancel()
            raise TimeoutError(f"no result within {timeout_s} s") from None
        except BaseException:  # the caller was interrupted (Ctrl-C, a signal): the call goes with it
            task.cancel()
            raise

    def close(self, timeout_s: float = 10.0) -> None:
        """Cancel ``main`` and join the thread; idempotent, bounded by ``timeout_s``."""
        if self._closed:
            return
        self._closed = True
        loop, task = self.loop, self._task
        if loop is not None and task is not None and not loop.is_closed():
            loop.call_soon_threadsafe(task.cancel)
        self._thread.join(timeout_s)


def _cancel_leftovers(loop: asyncio.AbstractEventLoop) -> None:
    """Cancel the tasks still pending on ``loop`` and let them finish (before it closes)."""
    pending = [t for t in asyncio.all_tasks(loop) if not t.done()]
    for t in pending:
        t.cancel()
    if pending:
        loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))


async def _handing_over(coro: Coroutine[Any, Any, T], out: concurrent.futures.Future[T]) -> None:
    try:
        value = await coro
    except asyncio.CancelledError:
        if not out.done():
            out.set_exception(RuntimeError("the call was cancelled: the loop is closing"))
        raise
    except BaseException as exc:  # noqa: BLE001 - handed to the caller
        if not out.done():
            out.set_exception(exc)
        if not isinstance(exc, Exception):
            raise
    else:
        if not out.done():
            out.set_result(value)


class LoopTask:
    """Runs ``main(started)`` as a task on the caller's running event loop (the attached mode; see the module
    docstring). Same contract for ``main`` as LoopThread."""

    def __init__(self, main: Callable[[Callable[[BaseException | None], None]], Awaitable[None]], name: str) -> None:
        self._main = main
        self.name = name
        self._task: asyncio.Task[None] | None = None
        self._callers: set[asyncio.Task[Any]] = set()

    async def start(self, timeout_s: float) -> None:
        """Start ``main`` on the running loop and wait until it reported ready.

        Raises:
            TimeoutError: not ready within ``timeout_s``.
            Exception: what ``main`` raised while starting.
        """
        loop = asyncio.get_running_loop()
        ready: asyncio.Future[None] = loop.create_future()

        def started(exc: BaseException | None) -> None:
            if not ready.done():
                ready.set_result(None) if exc is None else ready.set_exception(exc)

        async def run() -> None:
            await self._main(started)

        self._task = task = loop.create_task(run(), name=self.name)
        task.add_done_callback(self._on_main_done)

        def on_done(t: asyncio.Task[None]) -> None:
            if not ready.done():
                exc = None if t.cancelled() else t.exception()
                ready.set_exception(exc or RuntimeError(f"{self.name} stopped before it started"))

        task.add_done_callback(on_done)
        try:
            async with asyncio.timeout(timeout_s):
                await ready
        except TimeoutError:
            await self.aclose(5.0)
            raise TimeoutError(f"{self.name} did not start within {timeout_s} s") from None
        except BaseException:
            await self.aclose(5.0)
            raise

    def _on_main_done(self, task: asyncio.Task[None]) -> None:
        if not task.cancelled():
            task.exception()  # retrieved here; reported through failure()
        for caller in list(self._callers):
            caller.cancel()  # a call waiting on a world that stopped: failure() says why

    def failure(self) -> BaseException | None:
        """Why ``main`` stopped, once it has stopped (None while running or after a clean close)."""
        task = self._task
        if task is None or not task.done() or task.cancelled():
            return None
        return task.exception()

    @property
    def alive(self) -> bool:
        return self._task is not None and not self._task.done()

    async def call(self, coro: Coroutine[Any, Any, T], timeout_s: float) -> T:
        """Await ``coro`` under ``timeout_s``, in the caller's task (no hand-over).

        Raises:
            TimeoutError: no result within ``timeout_s``.
            RuntimeError: ``main`` is not running, or stopped during the call (then its failure is raised).
        """
        if not self.alive:
            coro.close()
            raise RuntimeError(f"{self.name} is not running")
        me = asyncio.current_task()
        assert me is not None
        self._callers.add(me)
        try:
            async with asyncio.timeout(timeout_s):
                return await coro
        except TimeoutError:
            raise TimeoutError(f"no result within {timeout_s} s") from None
        except asyncio.CancelledError:
            if not self.alive and me.uncancel() == 0:
                raise self.failure() or RuntimeError(f"{self.name} stopped") from None
            raise
        finally:
            self._callers.discard(me)

    async def aclose(self, timeout_s: float = 10.0) -> None:
        """Cancel ``main`` and wait (at most ``timeout_s``) until everything it opened is closed; idempotent."""
        task = self._task
        if task is None or task.done():
            return
        task.cancel()
        await asyncio.wait({task}, timeout=timeout_s)

    def close(self) -> None:
        """Cancel ``main`` without waiting (for a synchronous ``close`` or ``__del__``)."""
        task = self._task
        if task is not None and not task.done() and not task.get_loop().is_closed():
            task.get_loop().call_soon_threadsafe(task.cancel)
