"""Start ``uniros robot vbus`` as a real process on a real pty, and talk to it with unmodified dynamixel-sdk."""

from __future__ import annotations

import contextlib
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import dynamixel_sdk as sdk

MARGIN_MS = 50
"""The bus client's host-side slack in these tests (its default is 10 ms, for a real adapter): the test host is
shared, and under other suites' load the virtual servos' answers may come tens of ms late."""


@dataclass
class Vbus:
    """A running vbus process: its pty path, its stdout lines (events, control answers), its stdin."""

    process: subprocess.Popen[str]
    path: str
    lines: queue.Queue[str] = field(default_factory=queue.Queue)

    def send(self, line: str, timeout_s: float = 5.0) -> str:
        """Send a control line; return its answer (``ok ...`` or ``error: ...``)."""
        assert self.process.stdin is not None
        self.process.stdin.write(line + "\n")
        self.process.stdin.flush()
        return self.expect(("ok ", "error:"), timeout_s)

    def expect(self, prefixes: tuple[str, ...], timeout_s: float) -> str:
        """The next stdout line starting with one of ``prefixes`` (others are skipped)."""
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"vbus printed no line starting with {prefixes} within {timeout_s} s")
            try:
                line = self.lines.get(timeout=left)
            except queue.Empty:
                continue
            if line.startswith(prefixes):
                return line

    def stop(self) -> int:
        """SIGINT, then wait; returns the exit code."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
        try:
            return self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
            raise AssertionError("vbus did not end within 10 s of SIGINT") from None


@contextlib.contextmanager
def running_vbus(*extra: str, servos: str = "rx200", pythonpath: str | None = None) -> Iterator[Vbus]:
    """``uniros robot vbus SERVOS [extra]`` for the block (``pythonpath`` prepended to its $PYTHONPATH); stopped by
    SIGINT at its end."""
    argv = [sys.executable, "-m", "uniros_async.cli", "robot", "vbus", servos, *extra]
    env = dict(os.environ)
    if pythonpath is not None:
        env["PYTHONPATH"] = os.pathsep.join(p for p in (pythonpath, env.get("PYTHONPATH", "")) if p)
    process = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1, env=env)
    assert process.stdout is not None
    path = process.stdout.readline().strip()
    if not path.startswith("/dev/"):
        process.kill()
        process.wait()
        raise AssertionError(f"vbus printed {path!r} first, expected the pty's path")
    vbus = Vbus(process, path)

    def pump() -> None:
        assert process.stdout is not None
        for line in process.stdout:
            vbus.lines.put(line.strip())

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    try:
        yield vbus
    finally:
        vbus.stop()
        reader.join(5)
        for stream in (process.stdin, process.stdout):
            if stream is not None:
                stream.close()


@contextlib.contextmanager
def sdk_port(path: str, baud: int = 1_000_000) -> Iterator[tuple[sdk.PortHandler, sdk.PacketHandler]]:
    """dynamixel-sdk's PortHandler and Protocol 2.0 PacketHandler on ``path``."""
    port = sdk.PortHandler(path)
    assert port.openPort(), f"dynamixel-sdk could not open {path}"
    assert port.setBaudRate(baud)
    try:
        yield port, sdk.PacketHandler(2.0)
    finally:
        port.closePort()


def pty_gone(path: str, timeout_s: float = 5.0) -> bool:
    """Whether the pty's device node disappears (both its ends closed) within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if not os.path.exists(path):
            return True
        time.sleep(0.05)
    return False


def read(ph: sdk.PacketHandler, port: sdk.PortHandler, servo_id: int, address: int, size: int) -> int:
    """A register's value read with dynamixel-sdk, retried as a host does when a status is late on a loaded
    machine; fails the test when none of 5 reads succeeds."""
    fn = {1: ph.read1ByteTxRx, 2: ph.read2ByteTxRx, 4: ph.read4ByteTxRx}[size]
    for _ in range(5):
        value, result, error = fn(port, servo_id, address)
        if result == sdk.COMM_SUCCESS:
            return int(value)
    raise AssertionError(
        f"servo {servo_id}: reading {size} bytes at {address} failed 5 times: {ph.getTxRxResult(result)}"
    )


def ping_ok(ph: sdk.PacketHandler, port: sdk.PortHandler, servo_id: int) -> tuple[int, int]:
    """dynamixel-sdk's ping of a servo that must answer: ``(model number, error byte)``, retried as ``read`` is."""
    for _ in range(5):
        model, result, error = ph.ping(port, servo_id)
        if result == sdk.COMM_SUCCESS:
            return model, error
    raise AssertionError(f"servo {servo_id}: ping failed 5 times: {ph.getTxRxResult(result)}")
