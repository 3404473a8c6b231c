"""A render process: an arm's sim cameras rendered in a child process, the frames handed back in shared memory.

Rendering with Mesa's software rasteriser holds the GIL of the process that asks for the pixels while the frame is
drawn (``mjr_readPixels`` waits for the rasteriser's threads), milliseconds per frame: an env loop in that process
would wait for it. ``RenderProcess`` keeps the GL context in a child process of its own instead
(``python -m uniros_async.camera.render_process``: a fresh interpreter, so a user's script needs no main guard; it
ends when its socket to the parent closes, and the kernel ends it when the parent dies), so the loop's process pays
only a message and one copy per frame:

- the parent creates one memfd per camera, of one frame's size, and hands the fds to the child when it starts;
  memfds have no name, so nothing is left in ``/dev/shm`` whoever dies;
- per frame the parent sends ``(index, joint names, positions, markers)``; the child poses its model, renders and
  writes the frame into the camera's memfd (the one copy out of GL, flipped to top-down rows), and answers
  ``(index, render_ns)``; the parent copies the frame out, into a new array or (``view=True``: the memfd's own
  view is handed over) straight into a loaned frame (a camera has one request in flight at a time, so the memfd is
  not written while it is read).

The parent reads answers with ``loop.add_reader`` on the socket: nothing blocks the loop.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import ctypes
import logging
import mmap
import os
import signal
import socket
import subprocess
import sys
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from uniros_async.bus.messages import Marker
from uniros_async.robots import RobotSpec

__all__ = ["RenderProcess"]

logger = logging.getLogger(__name__)

START_TIMEOUT_S = 30.0
"""Bound on the child's start (a spawned interpreter importing MuJoCo, then a GL context)."""
STOP_TIMEOUT_S = 5.0


def _child_main(conn: Connection, frame_fds: Sequence[int]) -> None:
    """The child: get the arm and cameras, map the memfds, open the renderer, render on request until the socket
    closes."""
    # Mesa's llvmpipe rasterises in a pool of one thread per core by default: on a machine whose cores the loops
    # need, one rendering thread (this one) costs the least switching; a user's own setting is kept
    os.environ.setdefault("LP_NUM_THREADS", "1")
    from uniros_async.camera.sim import SimRenderer

    views = []
    try:
        robot, cameras = conn.recv()
        renderer = SimRenderer(robot, cameras)
        for cfg, fd in zip(cameras, frame_fds, strict=True):
            buf = mmap.mmap(fd, cfg.height * cfg.width * 3)
            os.close(fd)
            views.append(np.ndarray((cfg.height, cfg.width, 3), np.uint8, buffer=buf))
        renderer.render(0)  # the GL context, now: a failure is reported before the first frame is asked for
        conn.send(("ready", None))
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which raises it
        with contextlib.suppress(OSError):
            conn.send(("error", f"{type(exc).__name__}: {exc}"))
        return
    try:
        while True:
            try:
                req = conn.recv()
            except (EOFError, OSError):  # the parent is gone
                return
            if req is None:
                return
            index, names, position, markers = req
            t0 = _now_ns()
            renderer.pose(names, position)
            renderer.render_into(index, markers, views[index])
            conn.send((index, _now_ns() - t0))
    finally:
        renderer.close()


def _spawn(sock_fd: int, frame_fds: Sequence[int]) -> subprocess.Popen[bytes]:
    cmd = [sys.executable, "-m", "uniros_async.camera.render_process", "--sock", str(sock_fd), "--frames"]
    cmd += [str(fd) for fd in frame_fds]
    return subprocess.Popen(cmd, pass_fds=(sock_fd, *frame_fds), stdin=subprocess.DEVNULL, close_fds=True)


def _die_with_parent() -> None:
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m uniros_async.camera.render_process --sock FD --frames FD...``: the child's entry point."""
    parser = argparse.ArgumentParser(prog="uniros_async.camera.render_process")
    parser.add_argument("--sock", type=int, required=True)
    parser.add_argument("--frames", type=int, nargs="+", required=True)
    args = parser.parse_args(argv)
    _die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops it (a ctrl-C reaches the whole group)
    _child_main(Connection(args.sock), args.frames)


def _now_ns() -> int:
    import time

    return time.perf_counter_ns()


class RenderProcess:
    """The cameras of one arm rendered in a child process (see the module docstring).

    Args:
        robot: the arm.
        cameras: the cameras (``SimCameraConfig``).
        on_frame: called on the loop with ``(index, frame, render_ns)`` for every frame, ``frame`` a new array.
        view: hand ``on_frame`` the memfd's own view instead of a copy; it holds the frame until the next request
            for that camera (the caller copies it out, e.g. into a loaned frame, before asking again).
    """

    def __init__(
        self,
        robot: RobotSpec,
        cameras: Sequence[Any],
        on_frame: Callable[[int, np.ndarray, int], None],
        *,
        view: bool = False,
    ) -> None:
        self.robot = robot
        self.cameras = tuple(cameras)
        self.on_frame = on_frame
        self._hand_view = view
        self._fds: list[int] = []
        self._views: list[np.ndarray] = []
        self._maps: list[mmap.mmap] = []
        self._conn: Connection | None = None
        self._proc: subprocess.Popen[bytes] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.failed: asyncio.Future[None] | None = None

    @property
    def pid(self) -> int | None:
        """The child's pid (None before start)."""
        return None if self._proc is None else self._proc.pid

    async def start(self) -> None:
        """Start the child and wait until it renders.

        Raises:
            RenderError: the child could not render (its message says why, with the packages to install).
            TimeoutError: it did not answer within ``START_TIMEOUT_S``.
        """
        from uniros_async.sim.render import RenderError

        self._loop = asyncio.get_running_loop()
        self.failed = self._loop.create_future()
        for cfg in self.cameras:
            size = cfg.height * cfg.width * 3
            fd = os.memfd_create("uniros-camera", os.MFD_CLOEXEC)
            self._fds.append(fd)
            os.ftruncate(fd, size)
            m = mmap.mmap(fd, size)
            self._maps.append(m)
            self._views.append(np.ndarray((cfg.height, cfg.width, 3), np.uint8, buffer=m))
        parent_sock, child_sock = socket.socketpair()
        parent = Connection(parent_sock.detach())
        self._conn = parent
        child_fd = child_sock.detach()
        try:
            self._proc = await asyncio.to_thread(_spawn, child_fd, self._fds)  # a fork of a big process takes a while
        finally:
            os.close(child_fd)
        parent.send((self.robot, self.cameras))
        try:
            async with asyncio.timeout(START_TIMEOUT_S):
                while not parent.poll():
                    if self._proc.poll() is not None:
                        raise RenderError(f"the camera render process exited with code {self._proc.returncode}")
                    await asyncio.sleep(0.01)
        except TimeoutError:
            raise TimeoutError(f"the camera render process did not start within {START_TIMEOUT_S} s") from None
        kind, detail = parent.recv()
        if kind != "ready":
            raise RenderError(f"the camera render process cannot render: {detail}")
        self._loop.add_reader(parent.fileno(), self._on_readable)

    def request(self, index: int, names: Sequence[str], position: np.ndarray, markers: Sequence[Marker]) -> None:
        """Ask for camera ``index``'s frame of the arm at ``position`` (one request per camera in flight; none once
        closed)."""
        if self._conn is None:
            return
        self._conn.send((index, tuple(names), position, tuple(markers)))

    def _on_readable(self) -> None:
        conn = self._conn
        assert conn is not None
        try:
            while conn.poll():
                index, render_ns = conn.recv()
                frame = self._views[index]
                self.on_frame(index, frame if self._hand_view else frame.copy(), render_ns)
        except (EOFError, OSError) as exc:
            assert self._loop is not None
            self._loop.remove_reader(conn.fileno())
            if self.failed is not None and not self.failed.done():
                code = None if self._proc is None else self._proc.poll()
                self.failed.set_exception(RuntimeError(f"the camera render process ended (exit code {code}): {exc}"))

    async def aclose(self) -> None:
        """Stop the child (asked, then after ``STOP_TIMEOUT_S`` killed) and free the memfds; idempotent."""
        conn, proc = self._conn, self._proc
        self._conn = self._proc = None
        if conn is not None:
            if self._loop is not None:
                with contextlib.suppress(ValueError, OSError):
                    self._loop.remove_reader(conn.fileno())
            with contextlib.suppress(OSError):
                conn.send(None)
        if proc is not None:
            try:
                await asyncio.to_thread(proc.wait, STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                await asyncio.to_thread(proc.wait, STOP_TIMEOUT_S)
        if conn is not None:
            conn.close()
        self._views.clear()
        for m in self._maps:
            with contextlib.suppress(BufferError):
                m.close()
        self._maps.clear()
        for fd in self._fds:
            os.close(fd)
        self._fds.clear()


if __name__ == "__main__":
    main()
