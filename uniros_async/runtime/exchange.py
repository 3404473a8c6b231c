"""The step exchange: requests out to every worker, replies in, on the agent's side (``StepExchange``).

The agent side is synchronous (gymnasium), the transports are asyncio: the supervisor has a private event loop
that the calling thread runs itself, only for the duration of each call (``loop.run_until_complete``): nothing on
the agent side needs to run between calls (replies wait in the shm rings, a dead worker's hang-up in its socket),
and a call then costs no hand-over to another thread (a loop's start and stop cost far less than a thread's
wake-ups and GIL hand-offs). Calls from several threads are serialised by a lock. ``submit_steps`` sends requests
and returns at once; the replies are collected by ``_Pending.result``. A step does not run the loop at all: the
requests go out with the transport's ``try_send`` and the replies come in with its ``receive_blocking`` (shm and
tcp, local and Ray-placed workers), in the calling thread (``send_steps_now``, ``receive_steps_now`` and
``_take_replies``); whatever that cannot do (no room, a hang-up, a deadline, a Ray actor's news of its worker)
is left to the loop, which also reports it.
Every wait on a worker has a deadline; a worker that does not answer in time raises StepTimeoutError (naming its
index, the operation and the timeout), one whose connection breaks or whose process died raises WorkerError; either
is marked broken and every later request to it raises WorkerError naming its index. A call interrupted by Ctrl-C
while the loop waits is finished (its replies consumed) before the next call; one interrupted inside a request's own
code marks that worker broken, since its next reply could no longer be matched to a request.

``Supervisor`` (runtime/supervisor.py) adds the workers' lifecycle to this: start, connect, restart, close.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import threading
import time
from collections.abc import Callable, Coroutine, Sequence
from typing import Any, Generic, NoReturn, TypeVar

from uniros_async.errors import StepTimeoutError, WorkerError
from uniros_async.runtime.handle import Request, WorkerHandle
from uniros_async.runtime.hangup import HANG_UP_REPORT_S, hang_up_report, hung_up
from uniros_async.runtime.protocol import STEP_TAG, PackedRequest, unpack

__all__ = ["StepExchange", "bounded"]

T = TypeVar("T")

StepDecoder = Callable[[int, memoryview], Any]
"""``decode(worker index, step reply frame)``: what a step's reply becomes when taken in the calling thread
(``StepExchange._take_replies``); reads the frame before it returns (the ring reuses its bytes)."""
LATER: Any = object()
"""``StepExchange._take_replies``: no reply this way (the loop's ``request_all`` must take it)."""


class StepExchange:
    """Requests to a supervisor's workers and their replies, on a private event loop run by the calling thread.

    Args:
        call_timeout_s: bound on any one request (reset, step, ...).
    """

    def __init__(self, call_timeout_s: float) -> None:
        self.call_timeout_s = call_timeout_s
        self.workers: list[WorkerHandle] = []
        self._loop = asyncio.new_event_loop()
        self._lock = threading.Lock()
        self._orphans: list[asyncio.Task[Any]] = []  # calls interrupted inside the loop (see _drive)
        self.fail_fast = False
        """A step raises a Ray-placed worker's hang-up at once, without the replies the others still owe (the vector
        env sets it unless it restarts failed workers, which needs every reply): ``_take_replies``."""
        self._hangup_fds: list[tuple[int, int]] = []  # (index, hangup_fd) of the workers that have one
        self._reply_rank: list[int] = []  # worker index -> its place in the order replies are taken (_take_replies)

    def _note_hangup_fds(self) -> None:
        self._hangup_fds = [(w.index, w.hangup_fd) for w in self.workers if w.hangup_fd >= 0]
        n = len(self.workers)
        if any(w.info.get("cores_shared") for w in self.workers):  # see _take_replies: the last sent first
            self._reply_rank = [n - 1 - i for i in range(n)]
        else:
            self._reply_rank = list(range(n))

    def call(self, coro: Coroutine[Any, Any, T], timeout_s: float | None = None) -> T:
        """Run ``coro`` on the supervisor's loop, in this thread, under ``timeout_s`` (default: the call timeout
        plus 5 s; the requests inside have their own deadlines).

        Raises:
            TimeoutError: no result within ``timeout_s``.
            RuntimeError: the supervisor is closed.
        """
        t = self.call_timeout_s + 5.0 if timeout_s is None else timeout_s
        return self._drive(bounded(coro, t), t)

    def _drive(self, coro: Coroutine[Any, Any, T], timeout_s: float, *, finish_orphans: bool = True) -> T:
        """Run the loop in this thread until ``coro`` is done (one thread at a time).

        A call interrupted inside the loop (Ctrl-C: KeyboardInterrupt raised in this thread) leaves its task
        pending; the next call first lets it finish (under its own deadlines), so the replies it waited for are
        consumed and the workers stay usable, as when the loop ran on a thread of its own. ``close`` cancels such
        tasks instead (``finish_orphans=False``).
        """
        loop = self._loop
        if loop.is_closed():
            coro.close()
            raise RuntimeError("the supervisor is closed")
        if not self._lock.acquire(timeout=timeout_s):
            coro.close()
            raise TimeoutError(f"another thread kept the supervisor busy for {timeout_s} s")
        try:
            if self._orphans:
                self._settle_orphans(finish_orphans)
            task = loop.create_task(coro)
            try:
                return loop.run_until_complete(task)
            except BaseException:
                if not task.done():
                    self._orphans.append(task)
                raise
        finally:
            self._lock.release()

    def _settle_orphans(self, finish: bool) -> None:
        orphans, self._orphans = self._orphans, []
        pending = [t for t in orphans if not t.done()]
        if pending and not finish:
            for t in pending:
                t.cancel()
        if pending:
            try:
                self._loop.run_until_complete(asyncio.wait(pending))
            except BaseException:
                self._orphans = [t for t in orphans if not t.done()]
                raise
        for t in orphans:
            if not t.cancelled():
                t.exception()  # retrieved: the interrupted caller is gone

    def send_steps_now(self, messages: Sequence[PackedRequest]) -> int:
        """The first half of ``UnirosVectorEnv.step``: send one packed step request to every worker, in this thread
        with the transport's ``try_send`` (shm and tcp: no event-loop round), in index order until one cannot go
        that way; returns how many went. A worker that cannot take its request so is left, with the rest, to the
        loop (``receive_steps_now``: ``request_all``, which also reports what stood in the way): one that is broken,
        a transport without ``try_send``, no room in its ring, or a Ray-placed worker whose actor has news. Its
        second half is ``receive_steps_now``; ``submit_steps`` (``step_async``) sends with it too. Flat, in as few
        lines of Python as it can: this runs on every step, and at one env the agent's share of a step's overhead is
        what its lines of Python cost (its goal over the bare env step: docs/performance.md).

        Raises:
            gymnasium.error.AlreadyPendingCallError: a worker still owes a reply (nothing was sent).
        """
        if self._orphans:  # replies still owed by a call cut short: request_all collects them first (_drive)
            return 0
        workers = self.workers
        for w in workers:
            if w.in_flight:
                w.check_idle()  # raises unless it is broken (that one is reported by the request it is sent)
        lock = self._lock
        if not lock.acquire(blocking=False):
            return 0
        try:
            if self._loop.is_closed():
                return 0
            sent = 0
            for w, m in zip(workers, messages):  # noqa: B905  (one message per worker: _step_messages checks it)
                try_send = w.try_send
                if w.broken is not None or try_send is None:
                    break
                remote = w.remote
                if remote is not None and remote.lifeline_has_news():  # send_request reports the actor's news
                    break
                if not try_send(m.frame):
                    break
                w.in_flight = True
                sent += 1
            return sent
        finally:
            lock.release()

    def receive_steps_now(self, messages: Sequence[PackedRequest], sent: int, decode: StepDecoder) -> list[Any]:
        """The second half of ``UnirosVectorEnv.step``: the replies to ``messages``, of which ``send_steps_now``
        sent the first ``sent``, taken in this thread (``_take_replies``) while they can be had that way; from the
        first that cannot, the rest (requests not sent, replies not had) go through ``request_all`` on the loop, under
        the same deadline (``_SentPending``). Returns the results in index order (``decode``'s for the replies it
        took), a WorkerError in the slot of a worker that failed.

        Raises:
            Exception: any other error a reply raised (a malformed frame), once every reply is in, as ``request_all``.
        """
        n = len(messages)
        results: list[Any] = [None] * n
        deadline = time.monotonic() + self.call_timeout_s
        owing, unexpected, hung = self._take_replies(sent, deadline, results, decode)
        if hung is not None:
            self._report_hang_up(hung, owing, deadline)
        if not owing and sent == n:
            if unexpected is not None:
                raise unexpected
            return results
        pending = _SentPending(self, messages, sent, results, owing.union(range(sent, n)))
        pending.to_loop(deadline)
        return pending.result(decode=decode)

    def _take_replies(
        self, sent: int, deadline: float, results: list[Any], decode: StepDecoder | None
    ) -> tuple[set[int], Exception | None, int | None]:
        """Take the step replies of the first ``sent`` workers in this thread into ``results``, one after the other in
        the order of ``_reply_rank``, until one cannot be had that way (the transport's ``receive_blocking``:
        nothing is consumed then). ``decode(index, frame)``: what a step's reply frame becomes, read while it is
        still in the ring (an error reply is no step frame: its WorkerError goes in its slot). Returns the indices
        among the first ``sent`` whose replies were not taken, the first error other than a WorkerError that taking
        one raised (it is in that one's slot as well; ``request_all`` raises such an error once every reply is
        in), and, with ``fail_fast``, the index of a Ray-placed worker still owing its reply whose tcp connection
        ended while another reply was awaited (its node or process is gone: ``_report_hang_up``), else None.

        The order: index order, unless the workers outnumber their cores (``cores.cores_shared``), then the last sent
        first. Those run their steps one after the other on their core in the order their requests came, so the last
        one sent to each core replies last; waiting for it first, the agent sleeps until its core is done and then
        finds the replies before it waiting, instead of waking once per reply and taking a core from a worker in the
        middle of its step each time (the agent's wake-ups per vector step: docs/performance.md)."""
        if not sent or not self._lock.acquire(blocking=False):
            return set(range(sent)), None, None
        workers = self.workers
        rank = self._reply_rank
        order = range(sent - 1, -1, -1) if rank and rank[0] else range(sent)  # _reply_rank: reversed, or in order
        k = 0
        unexpected: Exception | None = None
        watched = self._hangup_fds if self.fail_fast and sent > 1 else ()
        monotonic = time.monotonic
        try:
            if self._orphans or self._loop.is_closed():
                return set(range(sent)), None, None
            while k < sent:
                i = order[k]
                w = workers[i]
                receive_blocking = w.receive_blocking
                if w.broken is not None or not w.in_flight or receive_blocking is None:
                    break  # (the loop reports a broken one)
                here = rank[i] if watched else 0
                watch = [fd for j, fd in watched if rank[j] > here] if watched else ()
                r: Any = LATER
                try:
                    left_s = max(deadline - monotonic(), 0.0)
                    frame = receive_blocking(left_s, watch) if watch else receive_blocking(left_s)
                    if frame is not None:
                        w.in_flight = False
                        if decode is not None and frame[0] == STEP_TAG:
                            r = decode(i, frame)  # (reads the frame while it is still in the ring)
                        else:
                            r = w.reply_result(unpack(frame))  # a WorkerError: the worker raised, stays usable
                except WorkerError as exc:
                    r = exc
                except BaseException as exc:  # Ctrl-C in the wait, a malformed reply: replies out of step
                    w.broken = f"waiting for the reply to 'step' was interrupted ({w.spec.env_id})"
                    if not isinstance(exc, Exception):
                        raise
                    r = exc  # in its slot, as request_all does
                    if unexpected is None:
                        unexpected = exc
                if r is LATER:  # not had this way (nothing within the deadline, a hang-up, the slow path)
                    if watched:  # a hang-up, of one of them or of this one (then no need to wait for the others)?
                        hung, replied = hung_up([(j, fd) for j, fd in watched if rank[j] >= here])
                        if hung is not None:
                            return set(order[k:]), unexpected, hung
                        if replied and deadline > monotonic():  # its reply came before it hung up: taken in
                            watched = [(j, fd) for j, fd in watched if fd not in replied]  # its turn
                            continue
                    break
                results[i] = r
                k += 1
            return (set() if k == sent else set(order[k:])), unexpected, None
        except BaseException:  # Ctrl-C: the replies still owed can no longer be matched to requests
            for j in order[k:]:
                w = workers[j]
                if w.in_flight and w.broken is None:
                    w.broken = f"waiting for its reply was interrupted ({w.spec.env_id})"
            raise
        finally:
            self._lock.release()

    def _report_hang_up(self, hung: int, owing: set[int], deadline: float) -> NoReturn:
        """Raise the WorkerError of worker ``hung``, whose connection ended without the reply to its step request
        (``_take_replies``), now (``hangup.hang_up_report``). The replies the workers in ``owing`` still owe are not
        waited for: a task on the loop collects them under ``deadline``; the next call lets it finish first and
        ``close`` cancels it (``_drive``)."""
        owed = [self.workers[i] for i in sorted(owing) if i != hung]
        error, task = self._drive(hang_up_report(self.workers[hung], owed, deadline), HANG_UP_REPORT_S + 2.0)
        if not task.done():
            self._orphans.append(task)
        raise error

    def first_owing(self) -> int:
        """The index of the first worker whose reply is still owed (0 when none is)."""
        return next((w.index for w in self.workers if w.in_flight), 0)

    def submit(self, coro: Coroutine[Any, Any, T]) -> _Pending[T]:
        """Start ``coro`` on the supervisor's loop, run it until it waits, and return; ``.result()`` finishes it."""

        async def start() -> asyncio.Task[T]:
            task = asyncio.get_running_loop().create_task(coro)
            await asyncio.sleep(0)
            return task

        return _Pending(self, self._drive(start(), 5.0))

    def submit_steps(self, messages: Sequence[PackedRequest]) -> _Pending[list[Any]]:
        """``request_all(messages, return_exceptions=True)`` for one step request per worker, returning once every
        request is sent (``send_steps_now``); the replies are taken by ``.result()`` (``_take_replies``, then the
        loop for what is left). Raises as ``send_steps_now``."""
        sent = self.send_steps_now(messages)
        if sent == len(messages):  # all sent: nothing runs until the replies are due
            if self._loop.is_closed():
                raise RuntimeError("the supervisor is closed")
            return _SentPending(self, messages, sent)

        async def start() -> asyncio.Task[list[Any]]:
            done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
            task = asyncio.get_running_loop().create_task(
                self.request_all(messages, return_exceptions=True, sent=done, present=frozenset(range(sent)))
            )
            either: set[asyncio.Future[Any]] = {done, task}
            await asyncio.wait(either, return_when=asyncio.FIRST_COMPLETED)
            return task

        return _Pending(self, self._drive(start(), self.call_timeout_s + 5.0))

    async def request_all(
        self,
        messages: Sequence[Request | None],
        *,
        return_exceptions: bool = False,
        sent: asyncio.Future[None] | None = None,
        present: frozenset[int] = frozenset(),
        wait_s: float | None = None,
    ) -> list[Any]:
        """Send ``messages[i]`` to worker i (None: skip), all before waiting for any (then ``sent`` is set). Once
        every reply is in, raise the first failure (by index), or with ``return_exceptions`` put each WorkerError
        in its slot. ``present``: the workers whose request ``send_steps_now`` has sent already. ``wait_s``: how long
        to wait at most (default: the call timeout, which error messages name either way)."""
        for i, m in enumerate(messages):
            if m is not None and i not in present:
                self.workers[i].check_idle()  # before anything is sent
        t = self.call_timeout_s
        results: list[Any] = [None] * len(messages)
        waiting: list[int] = []
        current: tuple[int, str] | None = None  # the worker and phase a timeout interrupts
        # One deadline for the whole exchange (one timer, not two per worker). The replies are collected one after
        # the other (each waits in its ring meanwhile): no task per worker, so a step costs the fewest event-loop
        # rounds, and a hung worker is still found within the call timeout.
        try:
            async with asyncio.timeout(t if wait_s is None else wait_s):
                for i, m in enumerate(messages):
                    if m is None:
                        continue
                    if i in present:
                        waiting.append(i)
                        continue
                    current = (i, "send")
                    try:
                        await self.workers[i].send_request(m, None)
                    except WorkerError as exc:
                        results[i] = exc
                    else:
                        waiting.append(i)
                if sent is not None and not sent.done():
                    sent.set_result(None)
                while waiting:
                    i = waiting[0]
                    current = (i, "reply")
                    try:
                        results[i] = await self.workers[i].receive_reply(messages[i].get("op"), None)  # type: ignore[union-attr]
                    except Exception as exc:  # noqa: BLE001 - in its slot, raised below
                        results[i] = exc
                    waiting.pop(0)
                current = None
        except TimeoutError:
            assert current is not None
            i, phase = current
            w = self.workers[i]
            op = messages[i].get("op")  # type: ignore[union-attr]
            what = "could not send" if phase == "send" else "no reply to"
            w.broken = f"{what} {op!r} within {t} s ({w.spec.env_id})"
            results[i] = StepTimeoutError(i, w.broken)
            if phase == "reply":
                waiting.pop(0)
            else:  # the requests after the one that could not be sent were not sent either
                for j in range(i + 1, len(messages)):
                    if messages[j] is not None:
                        results[j] = WorkerError(j, f"not sent: worker {i} did not take its request within {t} s")
            for j in waiting:  # same deadline, passed too: only a reply that is already there still counts
                try:
                    results[j] = await self.workers[j].receive_reply(messages[j].get("op"), 0.0)  # type: ignore[union-attr]
                except Exception as exc:  # noqa: BLE001
                    results[j] = exc
                    wj = self.workers[j]
                    if wj.broken is not None:
                        wj.broken = f"no reply to {messages[j].get('op')!r} within {t} s ({wj.spec.env_id})"  # type: ignore[union-attr]
                        results[j] = StepTimeoutError(j, wj.broken)
            waiting.clear()
        finally:
            for j in waiting:  # interrupted: their replies can no longer be matched to requests
                w = self.workers[j]
                if w.broken is None:
                    w.broken = f"waiting for its reply was interrupted ({w.spec.env_id})"
        return _raise_unexpected(results, worker_errors=not return_exceptions)


def _raise_unexpected(results: list[Any], *, worker_errors: bool = False) -> list[Any]:
    """``results``, unless one of them is an exception other than a WorkerError (or is any, with
    ``worker_errors``): the first of those is raised, as ``request_all`` does once every reply is in."""
    for r in results:
        if isinstance(r, BaseException) and (worker_errors or not isinstance(r, WorkerError)):
            raise r
    return results


async def bounded(coro: Coroutine[Any, Any, T], timeout_s: float) -> T:
    try:
        async with asyncio.timeout(timeout_s):
            return await coro
    except TimeoutError:
        raise TimeoutError(f"no result within {timeout_s} s") from None


class _Pending(Generic[T]):
    """Requests started by ``Supervisor.submit``/``submit_steps``; like a concurrent.futures.Future, but ``result``
    runs the supervisor's loop in the calling thread until they are done."""

    def __init__(self, supervisor: StepExchange, task: asyncio.Task[T]) -> None:
        self._sup = supervisor
        self._task = task

    def done(self) -> bool:
        return self._task.done()

    def result(self, timeout: float | None = None) -> T:
        """The result (or exception) of the requests.

        Raises:
            concurrent.futures.TimeoutError: not done within ``timeout`` (they stay pending: call again).
            concurrent.futures.CancelledError: the supervisor closed first.
        """
        task = self._task
        if not task.done():
            t = self._sup.call_timeout_s + 5.0 if timeout is None else timeout
            try:
                self._sup._drive(asyncio.wait({task}, timeout=t), t + 1.0)
            except RuntimeError:  # closed meanwhile
                pass
        if not task.done():
            raise concurrent.futures.TimeoutError()
        if task.cancelled():
            raise concurrent.futures.CancelledError()
        return task.result()


class _SentPending(_Pending[list[Any]]):
    """Step requests of which the first ``sent`` went already (``submit_steps``: every one; ``receive_steps_now``: as
    many as it could): ``result`` takes their replies in the calling thread (``Supervisor._take_replies``, no
    event-loop round) and leaves the rest, requests not sent and replies not had that way, to ``request_all`` on the
    supervisor's loop, under what is left of the same deadline. The call timeout starts at the first ``result``, as
    for a task."""

    def __init__(
        self,
        supervisor: StepExchange,
        messages: Sequence[PackedRequest],
        sent: int,
        results: list[Any] | None = None,
        rest: set[int] | None = None,
    ) -> None:
        """``results`` and ``rest``: what the calling thread took already and what it could not (given together,
        by ``receive_steps_now``, which then calls ``to_loop``)."""
        self._sup = supervisor
        self._messages = messages
        self._sent = sent
        self._results: list[Any] = [None] * len(messages) if results is None else results
        self._rest: set[int] | None = rest  # what the calling thread could not take (None: not tried yet)
        self._task: asyncio.Task[list[Any]] | None = None  # type: ignore[assignment]  # ... by request_all instead
        self._interrupted = False  # taking the replies in the calling thread was interrupted: they cannot complete

    def done(self) -> bool:
        if self._task is not None:
            return self._task.done()
        return self._interrupted or (self._rest is not None and not self._rest)

    def result(self, timeout: float | None = None, decode: StepDecoder | None = None) -> list[Any]:
        """As ``_Pending.result``; ``decode``: what a step reply taken in this thread becomes instead of its result
        (``StepExchange._take_replies``; the replies taken by the event loop are results as usual)."""
        sup = self._sup
        if self._interrupted:
            raise concurrent.futures.CancelledError()
        now = time.monotonic()
        end = None if timeout is None else now + timeout
        if self._rest is None:
            deadline = now + sup.call_timeout_s
            until = deadline if end is None else min(deadline, end)
            try:
                owing, _, hung = sup._take_replies(self._sent, until, self._results, decode)  # raised below
            except BaseException:
                # Ctrl-C while taking the replies: which were taken is lost with the call (the workers still owing
                # one are marked broken), so the requests can never complete; taking them again would wait the whole
                # call timeout for replies already taken
                self._interrupted = True
                raise
            if hung is not None:
                self._rest = set()
                sup._report_hang_up(hung, owing, deadline)
            self._rest = owing.union(range(self._sent, len(self._messages)))
            self.to_loop(deadline)
        if self._task is not None:
            more = super().result(None if end is None else max(end - time.monotonic(), 0.0))
            for i in self._rest or ():
                self._results[i] = more[i]
            self._rest = set()
            self._task = None
        return _raise_unexpected(self._results)

    def to_loop(self, deadline: float) -> None:
        """Start ``request_all`` on the supervisor's loop for what the calling thread could not collect (``rest``),
        with what is left until ``deadline``; ``result`` runs it.

        Raises:
            concurrent.futures.CancelledError: there is something left and the supervisor is closed.
        """
        sup = self._sup
        if self._rest:
            if sup._loop.is_closed():
                raise concurrent.futures.CancelledError()
            left = [m if i in self._rest else None for i, m in enumerate(self._messages)]
            present = frozenset(i for i in self._rest if i < self._sent)  # sent, their replies not taken
            wait_s = max(deadline - time.monotonic(), 0.0)
            coro = sup.request_all(left, return_exceptions=True, present=present, wait_s=wait_s)
            self._task = sup._loop.create_task(coro)
