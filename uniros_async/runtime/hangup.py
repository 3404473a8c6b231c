"""Hang-up detection: a Ray-placed worker whose connection ends while the agent waits for another worker's reply.

A worker on another node can vanish with its node. Its tcp connection then ends (the actor on that node ends the
worker as soon as it sees the raylet end: runtime/ray_host.py), but the agent may be waiting for another worker's
reply meanwhile. ``StepExchange._take_replies`` therefore watches the tcp connections of the Ray-placed workers
that still owe their reply (``fail_fast``); ``hung_up`` tells which of them ended, and ``hang_up_report`` makes
that worker's WorkerError at once (``StepExchange._report_hang_up`` raises it), leaving the replies the others still
owe to a task on the supervisor's loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import select
import socket
import time
from typing import TYPE_CHECKING

from uniros_async.errors import WorkerError

if TYPE_CHECKING:
    from uniros_async.runtime.handle import WorkerHandle

__all__ = ["HANG_UP_REPORT_S", "hang_up_report", "hung_up"]

_HANG_UP = getattr(select, "POLLRDHUP", 0x2000)  # poll(2): the peer closed its end (POLLHUP, POLLERR: always reported)
HANG_UP_REPORT_S = 0.5
"""How long the report of a hung-up worker may take (its connection's end, then its actor's report of the exit,
``RayWorkerProcess.poll_exit``); a few milliseconds when its actor still answers."""


def hung_up(watched: list[tuple[int, int]]) -> tuple[int | None, set[int]]:
    """Which of ``watched`` ((index, socket descriptor), in the order their replies are taken) hung up or were
    reset: the index of the first one whose peer is gone with nothing left to read (its reply will never come), or
    None; and the descriptors of those hung up with data still to read (a reply sent before the hang-up)."""
    poller = select.poll()
    for _, fd in watched:
        poller.register(fd, _HANG_UP)
    fired = {fd for fd, _ in poller.poll(0)}
    replied: set[int] = set()
    for i, fd in watched:
        if fd not in fired:
            continue
        sock = socket.socket(fileno=fd)
        try:
            ended = sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
        except BlockingIOError:
            ended = False
        except OSError:  # reset
            ended = True
        finally:
            sock.detach()
        if ended:
            return i, replied
        replied.add(fd)
    return None, replied


async def hang_up_report(
    w: WorkerHandle, owed: list[WorkerHandle], deadline: float
) -> tuple[WorkerError, asyncio.Task[None]]:
    """The WorkerError of ``w``, whose connection ended without the reply to its step request: what
    ``WorkerHandle.receive_reply`` makes of it (its Ray actor's report: exit code, or its node lost), waited for at
    most ``HANG_UP_REPORT_S``; and a task, started on the running loop, that collects the replies the workers in
    ``owed`` still owe under ``deadline`` (``StepExchange._report_hang_up`` leaves it to the next call)."""

    async def collect() -> None:
        for other in owed:
            with contextlib.suppress(Exception):
                await other.receive_reply("step", max(deadline - time.monotonic(), 0.0))

    task = asyncio.get_running_loop().create_task(collect())
    try:
        await w.receive_reply("step", HANG_UP_REPORT_S)
    except WorkerError as exc:
        return exc, task
    return WorkerError(w.index, f"the connection to the worker ({w.spec.env_id}) ended after its reply"), task
