"""``uniros robot vbus``: a VirtualBus on a pty, so any Dynamixel tool can open it as a serial port.

    $ uniros robot vbus rx200              # prints the pty's path first, e.g. /dev/pts/5, then serves until SIGINT
    $ uniros robot vbus rx200 --emulate-real --seed 3

The server is one thread with one ``select`` loop: it reads instruction packets from the pty's master end (the
pty is in raw mode; the server keeps its slave end open too, so a client may close and reopen the path), applies
them to the ``VirtualBus`` and writes each status packet when it would have arrived on a real wire: after the
instruction's bytes, the servo's Return_Delay_Time and the status packet's own bytes at the bus's baud rate (10
bits a byte), one servo after the other, and after whatever the wire still carried when the instruction came (a
sync write's bytes before the next sync read). Between packets the arm's sim follows the wall clock in 10 ms steps.

Faults are lines on stdin (each answered ``ok ...`` or ``error: ...`` on stdout):

=====================  =========================================================================
``crc ID [N]``         the next N (default 1; -1: every) status packets of servo ID carry a bad CRC
``drop ID [N]``        the next N (default 1; -1: every) status packets of servo ID are not sent
``silent ID``          servo ID neither obeys nor answers anything (``answer ID`` undoes it)
``error ID BITS``      set servo ID's Hardware_Error_Status bits (e.g. ``0x20``, overload; 0 clears)
``stop`` / ``start``   the whole bus stops answering (and obeying), then starts again
``clear``              every fault off (hardware errors stay until a reboot or ``error ID 0``)
``temperature ID C``   servo ID's Present_Temperature becomes C degC (a servo warming up: the sim has no heat)
``get ID NAME``        answers ``ok get ID NAME VALUE``: register NAME of servo ID as the servo holds it now
=====================  =========================================================================

Events go to stdout as lines too: ``watchdog id=N silent_ms=... t=...`` when a servo's Bus Watchdog stops it
(``t`` is ``time.monotonic()``, which every process of the machine shares), ``hardware_error ...``, ``reboot ...``.
SIGINT or SIGTERM ends the server; it closes both ends of the pty, so the path disappears.
"""

from __future__ import annotations

import contextlib
import os
import selectors
import signal
import sys
import time
import tty
from collections.abc import Callable
from typing import IO

from uniros_async.errors import ConfigError
from uniros_async.hardware.dxl.control_table import RETURN_DELAY_UNIT_S
from uniros_async.hardware.dxl.protocol import PacketParser
from uniros_async.hardware.dxl.servo_map import ServoMap
from uniros_async.hardware.dxl.vbus import VirtualBus, VirtualServo
from uniros_async.priority import MAX_LOOP_RANK, freeze_heap, raise_loop_priority
from uniros_async.sim.emulated import EmulationConfig

__all__ = ["VbusServer", "serve_vbus"]

BITS_PER_BYTE = 10
"""A byte on the wire at 8N1: start bit, 8 data bits, stop bit."""
_MAX_WAIT_S = 0.005  # the loop wakes at least this often
_WATCHDOG_SLACK_S = 0.0002  # a watchdog trips once the silence is longer than its time: wake just after it


class VbusServer:
    """A VirtualBus behind a pty (see the module docstring).

    Args:
        servos: the arm's servo map.
        baud: the bus's baud rate for the timing model; None: the map's.
        emulation: the emulated real arm's perturbations, or None.
        emit: called with every event and control answer (one line, no newline).

    Attributes:
        path: the pty's path (``/dev/pts/N``), for the client to open.
        bus: the VirtualBus.
    """

    def __init__(
        self,
        servos: ServoMap,
        *,
        baud: int | None = None,
        emulation: EmulationConfig | None = None,
        emit: Callable[[str], None] | None = None,
    ) -> None:
        self.emit = emit or (lambda line: None)
        self.baud = baud or servos.baud
        if self.baud <= 0:
            raise ConfigError(f"baud: expected a rate > 0, got {self.baud}")
        self.bus = VirtualBus(servos, emulation=emulation, on_event=self.emit)
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)
        self.stopped = False  # the "stop" fault: the bus is dead
        self._running = True
        self._parser = PacketParser()
        self.status_sent = 0
        self._wire_free_at = 0.0  # when the modelled wire has carried the last packet and its answers

    def close(self) -> None:
        """Close both ends of the pty (the path disappears); idempotent."""
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._master = self._slave = -1

    def request_stop(self) -> None:
        """End ``run`` at its next wake-up (a signal handler calls this)."""
        self._running = False

    # ------------------------------------------------------------------------------------------ the loop

    def run(self, control_fd: int | None = None) -> None:
        """Serve until ``request_stop``; ``control_fd`` is a file descriptor of fault lines (stdin's), or None."""
        sel = selectors.DefaultSelector()
        sel.register(self._master, selectors.EVENT_READ, "bus")
        if control_fd is not None:
            try:
                sel.register(control_fd, selectors.EVENT_READ, "control")
            except (PermissionError, ValueError):  # a regular file or /dev/null: no fault lines can come
                control_fd = None
        pending = b""
        try:
            while self._running:
                wake = min(self.bus.next_due_s(), self.bus.next_watchdog_s() + _WATCHDOG_SLACK_S)
                timeout = min(_MAX_WAIT_S, max(0.0, wake - time.monotonic()))
                # the bytes that came in are read before the watchdogs are checked: a servo's UART takes them as
                # they come, even when this process was late to run
                for key, _ in sel.select(timeout):
                    if key.data == "bus":
                        self._on_bus()
                    elif control_fd is not None:
                        chunk = os.read(control_fd, 4096)
                        if not chunk:  # EOF: no more faults; serve on
                            sel.unregister(control_fd)
                            control_fd = None
                        pending += chunk
                        *lines, pending = pending.split(b"\n")
                        for raw in lines:
                            line = raw.decode(errors="replace").strip()
                            if line:
                                self.emit(self.command(line))
                self.bus.advance(time.monotonic())
        finally:
            sel.close()

    def _on_bus(self) -> None:
        try:
            data = os.read(self._master, 65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:  # EIO: no slave end open (cannot happen while we hold one); wait for the next
            return
        arrived = time.monotonic()
        if self.stopped:
            self._parser.clear()
            return
        byte_s = BITS_PER_BYTE / self.baud
        for packet in self._parser.feed(data):
            if packet.is_status:
                continue
            self.bus.advance(arrived, watchdogs=False)  # this packet is the host's sign of life
            # the wire carries one packet at a time: an instruction that came right after another (a sync write,
            # then a sync read) starts when the one before it, and its status packets, have passed
            due = max(arrived, self._wire_free_at) + len(packet.raw) * byte_s
            for servo_id, status in self.bus.handle(packet, arrived):
                servo = self.bus.servos[servo_id]
                due += servo.get("return_delay_time") * RETURN_DELAY_UNIT_S + len(status) * byte_s
                final = self.bus.finish_status(servo_id, status)
                if final is None:
                    continue
                _sleep_until(due)
                try:
                    os.write(self._master, final)
                    self.status_sent += 1
                except (BlockingIOError, OSError):
                    pass  # nobody reads: the status is lost, as on a bus with no host listening
            self._wire_free_at = due

    # ------------------------------------------------------------------------------------------ faults

    def command(self, line: str) -> str:
        """Apply one control line (see the module docstring); returns the answer line."""
        words = line.split()
        try:
            verb, args = words[0], words[1:]
            if verb in ("stop", "start", "clear") and not args:
                if verb == "clear":
                    for s in self.bus.servos.values():
                        s.faults.corrupt_crc = s.faults.drop_status = 0
                        s.faults.silent = False
                    self.stopped = False
                else:
                    self.stopped = verb == "stop"
                return f"ok {line}"
            if verb in ("crc", "drop") and 1 <= len(args) <= 2:
                faults = self._servo(args[0]).faults
                n = int(args[1], 0) if len(args) == 2 else 1
                setattr(faults, "corrupt_crc" if verb == "crc" else "drop_status", n)
                return f"ok {line}"
            if verb in ("silent", "answer") and len(args) == 1:
                self._servo(args[0]).faults.silent = verb == "silent"
                return f"ok {line}"
            if verb == "error" and len(args) == 2:
                self.bus.set_hardware_error(self._servo(args[0]).id, int(args[1], 0))
                return f"ok {line}"
            if verb == "temperature" and len(args) == 2:
                self._servo(args[0]).put("present_temperature", int(args[1], 0))
                return f"ok {line}"
            if verb == "get" and len(args) == 2:
                return f"ok {line} {self._servo(args[0]).get(args[1])}"
        except (ValueError, ConfigError) as exc:
            return f"error: {line!r}: {exc}"
        return (
            f"error: {line!r}: expected one of 'crc ID [N]', 'drop ID [N]', 'silent ID', 'answer ID', "
            "'error ID BITS', 'stop', 'start', 'clear', 'temperature ID C', 'get ID NAME'"
        )

    def _servo(self, word: str) -> VirtualServo:
        servo_id = int(word, 0)
        servo = self.bus.servos.get(servo_id)
        if servo is None:
            raise ConfigError(f"no servo ID {servo_id} on this bus; IDs: {sorted(self.bus.servos)}")
        return servo


def _sleep_until(t: float) -> None:
    """Wait until ``time.monotonic()`` reaches ``t``. A sleep, not a spin: a real-time thread has no timer slack,
    so it wakes within tens of microseconds, and a spin would hold a core at a real-time priority."""
    left = t - time.monotonic()
    if left > 0.0:
        time.sleep(left)


def serve_vbus(
    servos: ServoMap,
    *,
    baud: int | None = None,
    emulation: EmulationConfig | None = None,
    out: IO[str] | None = None,
    control_fd: int | None = None,
) -> int:
    """Serve ``servos`` on a new pty until SIGINT or SIGTERM: the first line on ``out`` is the pty's path.

    Returns:
        0 after an orderly stop; the pty is closed.
    """
    stream = out if out is not None else sys.stdout

    def emit(line: str) -> None:
        stream.write(line + "\n")
        stream.flush()

    server = VbusServer(servos, baud=baud, emulation=emulation, emit=emit)
    previous = {sig: signal.signal(sig, lambda *_: server.request_stop()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        # it stands in for servos, which answer whatever else the host runs: the real-time class above every env
        # loop (a few ms of work a second), taken once start-up is done and before the path is out
        freeze_heap()
        raise_loop_priority(MAX_LOOP_RANK)
        emit(server.path)
        server.run(control_fd)
    finally:
        server.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
