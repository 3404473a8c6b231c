"""One worker's connection as the agent side holds it: ``WorkerHandle``.

A handle sends a request and takes its reply (``request``, or its halves ``send_request`` and ``receive_reply``)
on the supervisor's event loop; the step exchange (runtime/exchange.py) sends steps and takes their replies in the
calling thread instead, with the transport's ``try_send`` and ``receive_blocking`` where it has them (shm, tcp). One
request at a time per connection. A reply that does not come within its deadline raises StepTimeoutError (a
WorkerError and a TimeoutError, naming the worker's index, the operation and the timeout); a broken connection or a
dead process raises WorkerError with why (``_death_reason``: the exit code, or a Ray-placed worker's lost node).
Either marks the worker broken: every later request to it raises at once.
"""

from __future__ import annotations

import asyncio
import dataclasses
import functools
from typing import Any

import gymnasium as gym

from uniros_async.errors import StepTimeoutError, TransportError, WorkerError
from uniros_async.runtime.launch import WorkerProcess
from uniros_async.runtime.protocol import PackedRequest, pack, unpack
from uniros_async.runtime.ray_process import RayWorkerProcess
from uniros_async.runtime.worker import WorkerSpec

__all__ = ["Request", "WorkerHandle"]

Request = dict[str, Any] | PackedRequest
"""A request to a worker: a message, or a step request already packed (``protocol.pack_step_request``)."""


@dataclasses.dataclass
class WorkerHandle:
    """The supervisor's side of one worker."""

    spec: WorkerSpec
    process: WorkerProcess | RayWorkerProcess
    conn: Any = None  # the start-up pipe end (None for a Ray-placed worker)
    transport: Any = None
    broken: str | None = None
    info: dict[str, Any] = dataclasses.field(default_factory=dict)
    in_flight: bool = False  # a request was sent and its reply not yet taken
    try_send: Any = None  # the transport's try_send and receive_blocking where it has them (shm, tcp), else None
    receive_blocking: Any = None
    hangup_fd: int = -1  # a Ray-placed worker's tcp socket, watched for a hang-up while another reply is awaited
    group: tuple[int, ...] = ()
    """The indices of the envs its process hosts, in the order they listen (``make_vec(envs_per_worker=...)``):
    stopped, restarted and pinned together."""

    def __post_init__(self) -> None:
        if not self.group:
            self.group = (self.spec.index,)

    def check_idle(self) -> None:
        """Raise AlreadyPendingCallError if a reply is still outstanding (one request at a time per connection:
        a second one would take the first one's reply)."""
        if self.in_flight and self.broken is None:
            raise gym.error.AlreadyPendingCallError(
                f"worker {self.index} still owes the reply to an earlier request (step_async without step_wait?)",
                "call",
            )

    @property
    def index(self) -> int:
        return self.spec.index

    @functools.cached_property
    def remote(self) -> RayWorkerProcess | None:
        """The handle of a worker started elsewhere (by a Ray actor), or None for a local one (read on every step; a
        handle keeps its process: a restart makes a new handle)."""
        return self.process if isinstance(self.process, RayWorkerProcess) else None

    async def request(self, message: dict[str, Any], timeout_s: float) -> Any:
        """Send ``message`` and wait for the reply's result.

        Raises:
            StepTimeoutError: it did not answer within ``timeout_s`` (the worker is then broken).
            WorkerError: the worker raised (its traceback attached; the worker stays usable), or its connection broke
                or its process died (the worker is then broken).
        """
        await self.send_request(message, timeout_s)
        return await self.receive_reply(message.get("op"), timeout_s)

    async def send_request(self, message: Request, timeout_s: float | None) -> None:
        """The first half of ``request``: send ``message`` (``receive_reply`` must follow). Raises as ``request``;
        ``timeout_s=None``: no deadline of its own (the caller's bounds the wait)."""
        if self.broken is not None:
            raise WorkerError(self.index, self.broken)
        self.check_idle()
        remote = self.remote
        if remote is not None and remote.lifeline_has_news():  # its actor reported the exit, or died
            self.broken = await self._death_reason()
            raise WorkerError(self.index, self.broken)
        op = message.get("op")
        frame = pack(message)
        try:
            if timeout_s is None:
                await self.transport.send(frame)
            else:
                async with asyncio.timeout(timeout_s):
                    await self.transport.send(frame)
        except TimeoutError:
            self.broken = f"could not send {op!r} within {timeout_s} s ({self.spec.env_id})"
            raise StepTimeoutError(self.index, self.broken) from None
        except TransportError as exc:
            self.broken = await self._death_reason()
            raise WorkerError(self.index, self.broken) from exc
        except BaseException:  # cancelled, or Ctrl-C inside this frame: the connection is out of step
            self.broken = f"a {op!r} request was interrupted while being sent ({self.spec.env_id})"
            raise
        self.in_flight = True

    async def receive_reply(self, op: Any, timeout_s: float | None) -> Any:
        """The second half of ``request``: wait for the reply to the request of ``op`` sent last, at most
        ``timeout_s`` (None: no deadline of its own; the caller's bounds the wait)."""
        if self.broken is not None:
            raise WorkerError(self.index, self.broken)
        try:
            if timeout_s is None:
                frame = await self.transport.receive()
            else:
                async with asyncio.timeout(timeout_s):
                    frame = await self.transport.receive()
            self.in_flight = False
            reply = unpack(frame)
        except TimeoutError:
            self.broken = f"no reply to {op!r} within {timeout_s} s ({self.spec.env_id})"
            raise StepTimeoutError(self.index, self.broken) from None
        except TransportError as exc:
            self.broken = await self._death_reason()
            raise WorkerError(self.index, self.broken) from exc
        except BaseException:  # cancelled, Ctrl-C inside this frame, a malformed reply: replies out of step
            self.broken = f"waiting for the reply to {op!r} was interrupted ({self.spec.env_id})"
            raise
        return self.reply_result(reply)

    def reply_result(self, reply: dict[str, Any]) -> Any:
        """A reply's result.

        Raises:
            WorkerError: the reply says the worker raised (its traceback attached).
        """
        if not reply.get("ok"):
            raise WorkerError(
                self.index, f"{self.spec.env_id}: {reply.get('error')}", remote_traceback=reply.get("traceback", "")
            )
        return reply.get("result")

    async def _death_reason(self) -> str:
        remote = self.remote
        if remote is not None:
            code = await remote.poll_exit(0.5)  # the actor reports the exit a moment after the connection broke
            if remote.lost:
                return f"the remote worker ({self.spec.env_id}, {remote.where()}) is lost: {remote.lost}"
            if code is not None:
                return f"the remote worker process ({self.spec.env_id}, {remote.where()}) died with exit code {code}"
            return f"the connection to the remote worker ({self.spec.env_id}, {remote.where()}) broke"
        for _ in range(20):  # the connection usually breaks a moment before the process is reaped
            if self.process.exitcode is not None:
                break
            await asyncio.sleep(0.025)
        code = self.process.exitcode
        if code is None:
            return f"the connection to the worker ({self.spec.env_id}, pid {self.process.pid}) broke"
        return f"the worker process ({self.spec.env_id}, pid {self.process.pid}) died with exit code {code}"
