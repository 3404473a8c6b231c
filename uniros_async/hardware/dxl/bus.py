"""DxlBus: a Dynamixel Protocol 2.0 bus client on asyncio, over a serial port's file descriptor.

    async with await open_dxl_bus("/dev/ttyUSB0", baud=1_000_000) as bus:
        model, firmware = await bus.ping(1)
        state = await bus.sync_read(126, 10, [1, 2, 3, 4, 5])        # {id: present current..position bytes}
        await bus.sync_write(116, 4, {1: goal_bytes, 2: goal_bytes})  # goal positions; no status packets

The tty is opened non-blocking in raw mode at the baud rate (termios) and its fd sits in the event loop
(``loop.add_reader``), so a transaction never blocks the loop: it writes the instruction packet, then awaits the
status packets the reader callback parses (``protocol.PacketParser``). One transaction at a time holds the lock.

Each transaction's timeout comes from the wire: the instruction's bytes and the expected status packets' bytes at
10 bits a byte and the baud rate, plus each answering servo's return delay, plus ``margin_s`` for the host side
(the USB adapter's latency timer, scheduling). A status packet with a bad CRC, or a servo missing at the
timeout, is retried within the same call for the servos still missing (up to ``retries`` times); an answer to an
earlier attempt that comes during a later one counts (the port's input is dropped only before the first attempt:
a status held up on its way in, by a busy host or a pty's kernel worker, is still the answer asked for); then
``DxlCrcError`` or ``DxlTimeoutError`` names them. Both are ``RobotError``s. A status packet whose error byte
holds an error number raises ``DxlStatusError``; its alert bit (a hardware error) only marks the servo in
``alerts``, which the caller reads (Hardware Error Status, address 70, says which error).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import errno
import os
import termios
import tty
from collections.abc import Callable, Mapping, Sequence
from types import TracebackType

from uniros_async.errors import (
    CodecError,
    ConfigError,
    DxlCrcError,
    DxlPortError,
    DxlStatusError,
    DxlTimeoutError,
)
from uniros_async.hardware.dxl.protocol import (
    ALERT_BIT,
    BROADCAST_ID,
    Instruction,
    Packet,
    PacketParser,
    bulk_read_params,
    bulk_write_params,
    describe_status_error,
    encode_instruction,
    parse_fast_sync_read,
    read_params,
    status_bytes,
    sync_read_params,
    sync_write_params,
    write_params,
)

__all__ = ["BusStats", "DxlBus", "open_dxl_bus", "wire_time_s"]

BITS_PER_BYTE = 10
"""A byte at 8N1 on the wire: start bit, 8 data bits, stop bit."""
DEFAULT_MARGIN_S = 0.010
"""Host-side slack added to every transaction's wire time: a USB adapter's latency timer set to 1 ms, and the
scheduling of the process. An FTDI adapter left at its 16 ms default needs about 0.035."""


def wire_time_s(n_bytes: int, baud: int) -> float:
    """Seconds ``n_bytes`` take on the wire at ``baud`` (8N1)."""
    return n_bytes * BITS_PER_BYTE / baud


@dataclasses.dataclass
class BusStats:
    """What the bus has seen since it opened."""

    transactions: int = 0
    crc_errors: int = 0
    timeouts: int = 0
    retries: int = 0
    crc_errors_in_a_row: int = 0
    """Transactions in a row whose last attempt still had a bad CRC (reset by a clean one)."""


def _open_tty(path: str, baud: int) -> int:
    speed = getattr(termios, f"B{baud}", None)
    if speed is None:
        raise ConfigError(f"baud rate {baud} of {path}: expected one termios supports (e.g. 57600, 1000000)")
    try:
        fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except PermissionError as exc:
        raise DxlPortError(
            f"cannot open the Dynamixel port {path}: permission denied. The user needs the dialout group: "
            "sudo usermod -aG dialout $USER, then log out and in again"
        ) from exc
    except FileNotFoundError as exc:
        raise DxlPortError(
            f"cannot open the Dynamixel port {path}: no such device. Check the USB cable and the adapter's path "
            "(ls /dev/ttyUSB* /dev/serial/by-id/)"
        ) from exc
    except OSError as exc:
        raise DxlPortError(f"cannot open the Dynamixel port {path}: {exc.strerror or exc}") from exc
    try:
        if not os.isatty(fd):
            raise DxlPortError(f"the Dynamixel port {path} is not a tty: expected a serial device")
        tty.setraw(fd)
        attrs = termios.tcgetattr(fd)
        attrs[2] = (attrs[2] & ~(termios.CSIZE | termios.PARENB | termios.CSTOPB | termios.CRTSCTS)) | (
            termios.CS8 | termios.CREAD | termios.CLOCAL
        )
        attrs[4] = attrs[5] = speed
        attrs[6][termios.VMIN] = 0
        attrs[6][termios.VTIME] = 0
        termios.tcsetattr(fd, termios.TCSANOW, attrs)
        termios.tcflush(fd, termios.TCIOFLUSH)
    except termios.error as exc:
        os.close(fd)
        raise DxlPortError(f"cannot set up the Dynamixel port {path} at {baud} baud: {exc}") from exc
    except BaseException:
        os.close(fd)
        raise
    return fd


class DxlBus:
    """A Protocol 2.0 bus on one serial port; build it with ``open_dxl_bus``.

    Args:
        path: the serial device (``/dev/ttyUSB0``, a pty's path).
        baud: bit/s, the servos' Baud Rate.
        return_delay_s: the servos' Return Delay Time (9) in s (2 us per unit; the e-manual default 250 is 0.5 ms).
        margin_s: host-side slack added to each transaction's wire time.
        retries: further attempts after a bad CRC or a missing status, within one call.
    """

    def __init__(
        self,
        path: str,
        baud: int = 1_000_000,
        *,
        return_delay_s: float = 0.0,
        margin_s: float = DEFAULT_MARGIN_S,
        retries: int = 2,
    ) -> None:
        if baud <= 0 or return_delay_s < 0 or margin_s <= 0 or retries < 0:
            raise ConfigError(
                f"DxlBus({path!r}): baud {baud}, return_delay_s {return_delay_s}, margin_s {margin_s}, retries "
                f"{retries}: expected baud > 0, return_delay_s >= 0, margin_s > 0, retries >= 0"
            )
        self.path = path
        self.baud = baud
        self.return_delay_s = return_delay_s
        self.margin_s = margin_s
        self.retries = retries
        self.stats = BusStats()
        self.alerts: dict[int, bool] = {}
        """Servo id -> whether its latest status packet had the alert bit (a hardware error) set."""
        self._fd = -1
        self._loop: asyncio.AbstractEventLoop | None = None
        self._lock = asyncio.Lock()
        self._parser = PacketParser(max_length=65535)
        self._rx: list[Packet] = []
        self._want: dict[int, int] = {}  # servo id -> the params its status must carry, for the attempt waited on
        self._have: set[int] = set()
        self._crc_base = 0
        self._waiter: asyncio.Future[None] | None = None
        self._read_error: OSError | None = None

    # ----------------------------------------------------------------------------------------- lifetime

    def _open(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._fd = _open_tty(self.path, self.baud)
        self._loop.add_reader(self._fd, self._on_readable)

    @property
    def closed(self) -> bool:
        """Whether ``aclose`` ran (or the bus never opened)."""
        return self._fd < 0

    async def aclose(self) -> None:
        """Stop reading and close the port; idempotent."""
        if self._fd >= 0:
            fd, self._fd = self._fd, -1
            if self._loop is not None:
                self._loop.remove_reader(fd)
            os.close(fd)
            if self._waiter is not None and not self._waiter.done():
                self._waiter.set_exception(DxlPortError(f"the Dynamixel port {self.path} was closed"))

    async def __aenter__(self) -> DxlBus:
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.aclose()

    # ---------------------------------------------------------------------------------------- the wire

    def timeout_s(self, tx_bytes: int, rx_bytes: int, n_status: int) -> float:
        """A transaction's timeout: its bytes at the baud rate, the return delays, and the margin."""
        return wire_time_s(tx_bytes + rx_bytes, self.baud) + n_status * self.return_delay_s + self.margin_s

    def _on_readable(self) -> None:
        try:
            data = os.read(self._fd, 65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            if exc.errno == errno.EIO:  # a pty whose other end is closed: nothing to read until it reopens
                return
            self._read_error = exc
            data = b""
        if self._waiter is None:
            self._parser.clear()  # bytes outside a transaction: late answers, noise
            return
        if data:
            for pkt in self._parser.feed(data):
                self._rx.append(pkt)
                if pkt.is_status and self._want.get(pkt.servo_id, -1) == len(pkt.params):
                    self._have.add(pkt.servo_id)
        waiter = self._waiter
        if not waiter.done() and (
            self._read_error is not None
            or len(self._have) + self._parser.crc_errors - self._crc_base >= len(self._want)
        ):
            waiter.set_result(None)

    def _drain_input(self) -> None:
        """Drop what arrived outside a transaction (late answers, noise): the kernel's buffer and the parser's."""
        with contextlib.suppress(OSError, termios.error):
            termios.tcflush(self._fd, termios.TCIFLUSH)
        self._parser.clear()

    async def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                n = os.write(self._fd, view)
            except BlockingIOError:
                n = 0
            except OSError as exc:
                raise DxlPortError(f"writing to the Dynamixel port {self.path} failed: {exc.strerror}") from exc
            view = view[n:]
            if view:
                assert self._loop is not None
                ready = self._loop.create_future()
                self._loop.add_writer(self._fd, ready.set_result, None)
                try:
                    async with asyncio.timeout(self.timeout_s(len(view), 0, 0) + 0.1):
                        await ready
                except TimeoutError:
                    raise DxlPortError(
                        f"writing to the Dynamixel port {self.path} stalled: {len(view)} of {len(data)} bytes not "
                        "taken by the port in time"
                    ) from None
                finally:
                    self._loop.remove_writer(self._fd)

    async def _transact(
        self,
        make: Callable[[Sequence[int]], bytes],
        expect: Sequence[int],
        n_params: Mapping[int, int],
        what: str,
    ) -> dict[int, Packet]:
        """Send ``make(ids)`` and gather one status per id of ``expect``, retrying for those still missing."""
        if self._fd < 0:
            raise DxlPortError(f"the Dynamixel port {self.path} is closed")
        assert self._loop is not None
        got: dict[int, Packet] = {}
        async with self._lock:
            self.stats.transactions += 1
            missing = list(expect)
            for attempt in range(self.retries + 1):
                if attempt:
                    self.stats.retries += 1
                packet = make(missing)
                if missing and not attempt:
                    self._drain_input()
                    self._rx = []
                self._want = {i: n_params[i] for i in missing}
                self._have = set()
                self._crc_base = self._parser.crc_errors
                self._read_error = None
                waiter = self._waiter = self._loop.create_future()
                try:
                    await self._write(packet)
                    if not missing:
                        return got
                    rx = sum(status_bytes(n_params[i]) for i in missing)
                    try:
                        async with asyncio.timeout(self.timeout_s(len(packet), rx, len(missing))):
                            await waiter
                    except TimeoutError:
                        pass
                finally:
                    self._waiter = None
                if self._read_error is not None:
                    raise DxlPortError(
                        f"reading the Dynamixel port {self.path} failed: {self._read_error.strerror}"
                    ) from self._read_error
                crc_errors = self._parser.crc_errors - self._crc_base
                self.stats.crc_errors += crc_errors
                for pkt in self._rx:
                    if pkt.is_status and pkt.servo_id in missing and len(pkt.params) == n_params[pkt.servo_id]:
                        got[pkt.servo_id] = pkt
                missing = [i for i in missing if i not in got]
                if not missing:
                    self.stats.crc_errors_in_a_row = 0
                    break
                if not crc_errors:
                    self.stats.timeouts += 1
            else:
                if crc_errors:
                    self.stats.crc_errors_in_a_row += 1
                    raise DxlCrcError(
                        f"{what}: status packets of servo(s) {missing} had bad CRCs in {self.retries + 1} "
                        f"attempts on {self.path}",
                        servo_id=missing[0],
                    )
                raise DxlTimeoutError(
                    f"{what}: servo(s) {missing} did not answer on {self.path} in {self.retries + 1} attempts; "
                    f"check that the bus runs at {self.baud} baud, that the servos have power, and their IDs",
                    servo_id=missing[0],
                )
        for servo_id, pkt in got.items():
            error = pkt.error or 0
            self.alerts[servo_id] = bool(error & ALERT_BIT)
            if error & 0x7F:
                raise DxlStatusError(
                    f"{what}: servo {servo_id} answered with error 0x{error:02X} ({describe_status_error(error)})",
                    servo_id=servo_id,
                    error=error,
                )
        return got

    # ------------------------------------------------------------------------------------ instructions

    async def ping(self, servo_id: int) -> tuple[int, int]:
        """``(model number, firmware version)`` of ``servo_id``."""
        got = await self._transact(
            lambda ids: encode_instruction(servo_id, Instruction.PING), [servo_id], {servo_id: 3}, "ping"
        )
        params = got[servo_id].params
        return params[0] | (params[1] << 8), params[2]

    async def read(self, servo_id: int, address: int, length: int) -> bytes:
        """``length`` bytes of ``servo_id``'s control table from ``address``."""
        packet = encode_instruction(servo_id, Instruction.READ, read_params(address, length))
        got = await self._transact(lambda ids: packet, [servo_id], {servo_id: length}, f"read {address}")
        return got[servo_id].params

    async def write(self, servo_id: int, address: int, data: bytes) -> None:
        """Write ``data`` at ``address`` of ``servo_id`` and wait for its status (none for ``BROADCAST_ID``)."""
        packet = encode_instruction(servo_id, Instruction.WRITE, write_params(address, data))
        expect = [] if servo_id == BROADCAST_ID else [servo_id]
        await self._transact(lambda ids: packet, expect, {servo_id: 0}, f"write {address}")

    async def reboot(self, servo_id: int) -> None:
        """Reboot ``servo_id`` (it answers, then restarts with torque off, clearing its hardware error)."""
        packet = encode_instruction(servo_id, Instruction.REBOOT)
        await self._transact(lambda ids: packet, [servo_id], {servo_id: 0}, "reboot")

    async def sync_read(self, address: int, length: int, ids: Sequence[int]) -> dict[int, bytes]:
        """The same ``length`` bytes from ``address`` of every servo of ``ids``, in one instruction."""

        def make(missing: Sequence[int]) -> bytes:
            return encode_instruction(BROADCAST_ID, Instruction.SYNC_READ, sync_read_params(address, length, missing))

        got = await self._transact(make, ids, dict.fromkeys(ids, length), f"sync read {address}+{length}")
        return {i: got[i].params for i in ids}

    async def fast_sync_read(self, address: int, length: int, ids: Sequence[int]) -> dict[int, bytes]:
        """Like ``sync_read``, answered by one packet carrying every servo's slot (``parse_fast_sync_read``)."""
        params = sync_read_params(address, length, ids)
        packet = encode_instruction(BROADCAST_ID, Instruction.FAST_SYNC_READ, params)
        n_body = len(ids) * (length + 4) - 3  # params after the first slot's error byte, before the last CRC
        for attempt in range(self.retries + 1):
            try:
                got = await self._transact(lambda _: packet, [BROADCAST_ID], {BROADCAST_ID: n_body}, "fast sync read")
            except DxlTimeoutError as exc:
                raise DxlTimeoutError(
                    f"fast sync read of servos {list(ids)} on {self.path}: no complete answer in {self.retries + 1} "
                    "attempts; one of them may be silent (ping each), or its firmware may not know Fast Sync Read",
                    servo_id=None,
                ) from exc
            try:
                slots = parse_fast_sync_read(got[BROADCAST_ID], length)
            except (DxlCrcError, CodecError) as exc:
                self.stats.crc_errors += 1
                if attempt == self.retries:
                    raise DxlCrcError(f"fast sync read on {self.path}: {exc}", servo_id=None) from exc
                continue
            out = {s.servo_id: s.data for s in slots}
            if sorted(out) != sorted(ids):
                raise DxlCrcError(f"fast sync read on {self.path}: answered ids {sorted(out)}, expected {list(ids)}")
            for s in slots:
                self.alerts[s.servo_id] = bool(s.error & ALERT_BIT)
            return {i: out[i] for i in ids}
        raise AssertionError("unreachable")

    async def sync_write(self, address: int, length: int, data: Mapping[int, bytes]) -> None:
        """Write ``length`` bytes at ``address`` of each servo of ``data`` in one instruction (no status packets)."""
        packet = encode_instruction(BROADCAST_ID, Instruction.SYNC_WRITE, sync_write_params(address, length, data))
        await self._transact(lambda ids: packet, [], {}, f"sync write {address}")

    async def bulk_read(self, reads: Sequence[tuple[int, int, int]]) -> dict[int, bytes]:
        """``{id: bytes}`` for each ``(id, address, length)``, in one instruction."""
        by_id = {servo_id: (address, length) for servo_id, address, length in reads}

        def make(missing: Sequence[int]) -> bytes:
            sub = [(i, *by_id[i]) for i in missing]
            return encode_instruction(BROADCAST_ID, Instruction.BULK_READ, bulk_read_params(sub))

        make([r[0] for r in reads])  # bad input raises here, before the lock
        got = await self._transact(make, list(by_id), {i: n for i, (_, n) in by_id.items()}, "bulk read")
        return {i: got[i].params for i in by_id}

    async def bulk_write(self, writes: Sequence[tuple[int, int, bytes]]) -> None:
        """Write each ``(id, address, data)`` in one instruction (no status packets)."""
        packet = encode_instruction(BROADCAST_ID, Instruction.BULK_WRITE, bulk_write_params(writes))
        await self._transact(lambda ids: packet, [], {}, "bulk write")


async def open_dxl_bus(
    path: str,
    baud: int = 1_000_000,
    *,
    return_delay_s: float = 0.0,
    margin_s: float = DEFAULT_MARGIN_S,
    retries: int = 2,
) -> DxlBus:
    """Open ``path`` as a Dynamixel bus in the running loop (see ``DxlBus`` for the arguments).

    Raises:
        DxlPortError: the port cannot be opened; for EACCES the message says to join the dialout group.
        ConfigError: a baud rate termios does not support, or a bad argument.
    """
    bus = DxlBus(path, baud, return_delay_s=return_delay_s, margin_s=margin_s, retries=retries)
    bus._open()
    return bus
