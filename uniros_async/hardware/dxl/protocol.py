"""Dynamixel Protocol 2.0 packets: encoding, a stream parser, and the parameters of every instruction.

A packet on the wire (ROBOTIS e-manual, "Protocol 2.0")::

    FF FF FD 00 | id | len_l len_h | instruction | [error] params... | crc_l crc_h

``len`` counts the instruction, the error byte of a status packet, the parameters and the CRC. Before the CRC is
computed, every ``FF FF FD`` inside the instruction and parameter fields is stuffed to ``FF FF FD FD`` (and ``len``
counts the stuffed bytes); a receiver checks the CRC over the stuffed bytes, then removes the stuffing. The CRC is
CRC-16 with polynomial 0x8005, initial value 0, no reflection (``crc16``).

Fast Sync Read answers with one status packet (id ``BROADCAST_ID``) carrying every servo's slot, ``error, id,
data, crc``, where each slot's CRC is the CRC of the packet from its header to the end of that slot's data, so the
last slot's CRC is the packet's. Servos append their slots one after the other without knowing what the others
send, so that packet is never stuffed; ``encode_fast_sync_read_status`` builds it and ``parse_fast_sync_read``
reads it.

Nothing here does I/O: ``bus.py`` moves the bytes and the virtual servo bus answers them.
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Iterable, Mapping, Sequence

from uniros_async.errors import CodecError, ConfigError, DxlCrcError

__all__ = [
    "BROADCAST_ID",
    "HEADER",
    "MAX_ID",
    "STATUS_ERRORS",
    "FastReadSlot",
    "Instruction",
    "Packet",
    "PacketParser",
    "bulk_read_params",
    "bulk_write_params",
    "crc16",
    "describe_status_error",
    "encode_fast_sync_read_status",
    "encode_instruction",
    "encode_status",
    "instruction_bytes",
    "parse_fast_sync_read",
    "read_params",
    "status_bytes",
    "stuff",
    "sync_read_params",
    "sync_write_params",
    "unstuff",
    "write_params",
]

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
MAX_ID = 0xFC
"""The highest id a servo can have (0xFD and 0xFF would look like a header)."""
MAX_PACKET_LENGTH = 4096
"""The largest ``len`` field the parser accepts; a longer one is taken as noise and skipped."""

_MIN_INSTRUCTION_LENGTH = 3  # instruction + CRC
_MIN_STATUS_LENGTH = 4  # instruction + error + CRC


class Instruction(enum.IntEnum):
    """The instruction byte of a Protocol 2.0 packet."""

    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    FACTORY_RESET = 0x06
    REBOOT = 0x08
    CLEAR = 0x10
    STATUS = 0x55
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83
    FAST_SYNC_READ = 0x8A
    BULK_READ = 0x92
    BULK_WRITE = 0x93
    FAST_BULK_READ = 0x9A


STATUS_ERRORS: dict[int, str] = {
    0x01: "result fail",
    0x02: "instruction error",
    0x03: "CRC error",
    0x04: "data range error",
    0x05: "data length error",
    0x06: "data limit error",
    0x07: "access error",
}
"""The error number (bits 0-6 of a status packet's error byte) and its meaning (e-manual, "Status Packet")."""
ALERT_BIT = 0x80
"""Bit 7 of the error byte: the servo has a hardware error; Hardware Error Status (70) says which."""


def describe_status_error(error: int) -> str:
    """Say what a status packet's error byte means, e.g. ``"data range error"`` or ``"ok, hardware alert"``."""
    number = error & 0x7F
    text = "ok" if number == 0 else STATUS_ERRORS.get(number, f"unknown error number {number}")
    return f"{text}, hardware alert" if error & ALERT_BIT else text


def _crc_table() -> tuple[int, ...]:
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc16(data: bytes | bytearray | memoryview, crc: int = 0) -> int:
    """CRC-16 of Protocol 2.0 (polynomial 0x8005, MSB first, initial 0), continued from ``crc``."""
    table = _CRC_TABLE
    for byte in data:
        crc = ((crc << 8) & 0xFFFF) ^ table[(crc >> 8) ^ byte]
    return crc


def stuff(body: bytes) -> bytes:
    """Insert an ``FD`` after every ``FF FF FD`` of ``body`` (the instruction and parameter fields).

    Only patterns inside ``body`` count, as in dynamixel-sdk's ``addStuffing`` for any real packet (one reaching
    back into the length field would need a length of 0xFFxx).
    """
    if b"\xff\xff\xfd" not in body:
        return body
    return body.replace(b"\xff\xff\xfd", b"\xff\xff\xfd\xfd")


def unstuff(body: bytes) -> bytes:
    """Remove the stuffing ``stuff`` inserted: every ``FF FF FD FD`` becomes ``FF FF FD``."""
    if b"\xff\xff\xfd\xfd" not in body:
        return body
    return body.replace(b"\xff\xff\xfd\xfd", b"\xff\xff\xfd")


def _check_id(servo_id: int, *, broadcast_ok: bool = True) -> None:
    if not 0 <= servo_id <= MAX_ID and not (broadcast_ok and servo_id == BROADCAST_ID):
        expected = f"0..{MAX_ID}" + (f" or {BROADCAST_ID} (broadcast)" if broadcast_ok else "")
        raise ConfigError(f"servo id {servo_id!r} is out of range: expected {expected}")


def _frame(servo_id: int, body: bytes) -> bytes:
    head = HEADER + bytes((servo_id, (len(body) + 2) & 0xFF, (len(body) + 2) >> 8))
    crc = crc16(body, crc16(head))
    return head + body + bytes((crc & 0xFF, crc >> 8))


def encode_instruction(servo_id: int, instruction: int, params: bytes = b"") -> bytes:
    """Build an instruction packet, stuffed and with its CRC.

    Raises:
        ConfigError: ``servo_id`` is not 0..252 or 254, or the packet would be longer than 65535 bytes.
    """
    _check_id(servo_id)
    body = stuff(bytes((instruction,)) + bytes(params))
    if len(body) + 2 > 0xFFFF:
        raise ConfigError(f"instruction packet of {len(body) + 2} bytes after its header: expected at most 65535")
    return _frame(servo_id, body)


def encode_status(servo_id: int, error: int, params: bytes = b"") -> bytes:
    """Build a status packet (instruction 0x55) with ``error`` as its error byte, stuffed and with its CRC.

    Raises:
        ConfigError: ``servo_id`` is not 0..252, or ``error`` is not a byte.
    """
    _check_id(servo_id, broadcast_ok=False)
    if not 0 <= error <= 0xFF:
        raise ConfigError(f"status error byte {error!r}: expected 0..255")
    body = stuff(bytes((Instruction.STATUS, error)) + bytes(params))
    return _frame(servo_id, body)


def instruction_bytes(servo_id: int, instruction: int, params: bytes = b"") -> int:
    """The length on the wire of an instruction packet (with its stuffing)."""
    return 9 + len(stuff(bytes((instruction,)) + bytes(params)))


def status_bytes(n_params: int) -> int:
    """The length on the wire of an unstuffed status packet with ``n_params`` parameter bytes."""
    return 11 + n_params


@dataclasses.dataclass(slots=True)
class Packet:
    """One decoded packet.

    Attributes:
        servo_id: the packet's id (``BROADCAST_ID`` for broadcasts and Fast Sync/Bulk Read answers).
        instruction: the instruction byte (``Instruction.STATUS`` for a status packet).
        params: the parameters, unstuffed; for a status packet, those after the error byte.
        error: a status packet's error byte; ``None`` for an instruction packet.
        raw: the packet as it was on the wire (stuffed, with header and CRC).
    """

    servo_id: int
    instruction: int
    params: bytes
    error: int | None = None
    raw: bytes = dataclasses.field(default=b"", compare=False, repr=False)

    @property
    def is_status(self) -> bool:
        """Whether this is a status packet (instruction 0x55)."""
        return self.instruction == Instruction.STATUS


class PacketParser:
    """Turns a byte stream into packets: resyncs on noise, checks each CRC, removes stuffing.

    Bytes arrive in any chunks (``feed``); a packet is returned once all of it is in. Bytes that cannot start a
    packet (no header, reserved byte not 0, an id of 0xFD or 0xFF, a length out of range, a status packet with
    no error byte) are skipped one at a time, so a packet after noise is still found.

    A packet with a bad CRC is dropped and counted in ``crc_errors`` (``last_crc_error`` names its id); with
    ``raise_on_crc=True``, ``feed`` raises ``DxlCrcError`` as well, and the packets it had already completed are
    returned by the next ``feed`` (``feed(b"")`` will do).
    """

    def __init__(self, *, raise_on_crc: bool = False, max_length: int = MAX_PACKET_LENGTH) -> None:
        self._buf = bytearray()
        self._out: list[Packet] = []
        self.raise_on_crc = raise_on_crc
        self.max_length = max_length
        self.crc_errors = 0
        self.skipped_bytes = 0
        self.last_crc_error: DxlCrcError | None = None

    @property
    def buffered(self) -> int:
        """Bytes held back as the start of a packet not yet complete."""
        return len(self._buf)

    def clear(self) -> None:
        """Forget buffered bytes (e.g. before a new transaction, as a port flush does)."""
        self._buf.clear()

    def feed(self, data: bytes | bytearray | memoryview) -> list[Packet]:
        """Add bytes from the stream; return the packets they completed, in order.

        Raises:
            DxlCrcError: with ``raise_on_crc``, a packet's CRC did not match (it is dropped and counted).
        """
        buf = self._buf
        buf += data
        out = self._out
        while True:
            start = buf.find(b"\xff\xff\xfd")
            if start < 0:
                # keep a possible start of a header
                keep = 2 if buf.endswith(b"\xff\xff") else 1 if buf.endswith(b"\xff") else 0
                self.skipped_bytes += len(buf) - keep
                del buf[: len(buf) - keep]
                break
            if start:
                self.skipped_bytes += start
                del buf[:start]
            if len(buf) < 7:
                break
            servo_id = buf[4]
            length = buf[5] | (buf[6] << 8)
            if (
                buf[3] != 0
                or servo_id in (0xFD, 0xFF)
                or length < _MIN_INSTRUCTION_LENGTH
                or length > self.max_length
                or (len(buf) > 7 and buf[7] == Instruction.STATUS and length < _MIN_STATUS_LENGTH)
            ):
                self.skipped_bytes += 1
                del buf[0]
                continue
            end = 7 + length
            if len(buf) < end:
                break
            raw = bytes(buf[:end])
            del buf[:end]
            crc = raw[-2] | (raw[-1] << 8)
            if crc16(memoryview(raw)[:-2]) != crc:
                self.crc_errors += 1
                error = DxlCrcError(
                    f"servo {servo_id}: packet CRC mismatch (received 0x{crc:04X}, computed 0x{crc16(raw[:-2]):04X})",
                    servo_id=servo_id,
                )
                self.last_crc_error = error
                if self.raise_on_crc:
                    raise error
                continue
            instruction = raw[7]
            fast_status = instruction == Instruction.STATUS and servo_id == BROADCAST_ID
            body = raw[7:-2] if fast_status else unstuff(raw[7:-2])
            if instruction == Instruction.STATUS:
                out.append(Packet(servo_id, instruction, bytes(body[2:]), body[1], raw))
            else:
                out.append(Packet(servo_id, instruction, bytes(body[1:]), None, raw))
        result = list(out)
        out.clear()
        return result


# ----------------------------------------------------------------------------------------- parameters


def _u16(value: int, what: str) -> bytes:
    if not 0 <= value <= 0xFFFF:
        raise ConfigError(f"{what} {value!r} is out of range: expected 0..65535")
    return bytes((value & 0xFF, value >> 8))


def read_params(address: int, length: int) -> bytes:
    """Parameters of READ: the start address and the byte count, little-endian."""
    return _u16(address, "address") + _u16(length, "length")


def write_params(address: int, data: bytes) -> bytes:
    """Parameters of WRITE and REG_WRITE: the start address, then the bytes."""
    return _u16(address, "address") + bytes(data)


def sync_read_params(address: int, length: int, ids: Iterable[int]) -> bytes:
    """Parameters of SYNC_READ and FAST_SYNC_READ: address, length, then one id per servo to answer, in order."""
    id_bytes = bytes(ids)
    for servo_id in id_bytes:
        _check_id(servo_id, broadcast_ok=False)
    if len(set(id_bytes)) != len(id_bytes):
        raise ConfigError(f"sync read ids {list(id_bytes)} repeat an id: expected each servo once")
    return read_params(address, length) + id_bytes


def sync_write_params(address: int, length: int, data: Mapping[int, bytes]) -> bytes:
    """Parameters of SYNC_WRITE: address, length, then ``id, data`` for each servo (each ``length`` bytes)."""
    parts = [read_params(address, length)]
    for servo_id, chunk in data.items():
        _check_id(servo_id, broadcast_ok=False)
        if len(chunk) != length:
            raise ConfigError(f"sync write data for servo {servo_id} has {len(chunk)} bytes: expected {length}")
        parts.append(bytes((servo_id,)))
        parts.append(bytes(chunk))
    return b"".join(parts)


def bulk_read_params(reads: Sequence[tuple[int, int, int]]) -> bytes:
    """Parameters of BULK_READ and FAST_BULK_READ: ``id, address, length`` for each ``(id, address, length)``."""
    parts = []
    seen: set[int] = set()
    for servo_id, address, length in reads:
        _check_id(servo_id, broadcast_ok=False)
        if servo_id in seen:
            raise ConfigError(f"bulk read names servo {servo_id} twice: expected each servo once")
        seen.add(servo_id)
        parts.append(bytes((servo_id,)) + read_params(address, length))
    return b"".join(parts)


def bulk_write_params(writes: Sequence[tuple[int, int, bytes]]) -> bytes:
    """Parameters of BULK_WRITE: ``id, address, length, data`` for each ``(id, address, data)``."""
    parts = []
    seen: set[int] = set()
    for servo_id, address, data in writes:
        _check_id(servo_id, broadcast_ok=False)
        if servo_id in seen:
            raise ConfigError(f"bulk write names servo {servo_id} twice: expected each servo once")
        seen.add(servo_id)
        parts.append(bytes((servo_id,)) + read_params(address, len(data)) + bytes(data))
    return b"".join(parts)


# ---------------------------------------------------------------------------------------- fast reads


@dataclasses.dataclass(frozen=True, slots=True)
class FastReadSlot:
    """One servo's part of a Fast Sync Read answer."""

    servo_id: int
    error: int
    data: bytes


def encode_fast_sync_read_status(slots: Sequence[tuple[int, int, bytes]]) -> bytes:
    """Build the one status packet that answers a Fast Sync Read, from ``(id, error, data)`` per servo.

    Every ``data`` has the same length. Each slot's CRC is the CRC of the packet up to the end of its data.

    Raises:
        ConfigError: no slots, an id out of range, or data of unequal lengths.
    """
    if not slots:
        raise ConfigError("a fast sync read answer needs at least one servo's slot")
    size = len(slots[0][2])
    length = 1 + len(slots) * (size + 4)
    if length > 0xFFFF:
        raise ConfigError(f"fast sync read answer of {length} bytes after its header: expected at most 65535")
    out = bytearray(HEADER + bytes((BROADCAST_ID, length & 0xFF, length >> 8, Instruction.STATUS)))
    crc = crc16(out)
    for servo_id, error, data in slots:
        _check_id(servo_id, broadcast_ok=False)
        if len(data) != size:
            raise ConfigError(f"fast sync read data for servo {servo_id} has {len(data)} bytes: expected {size}")
        chunk = bytes((error & 0xFF, servo_id)) + bytes(data)
        out += chunk
        crc = crc16(chunk, crc)
        out += bytes((crc & 0xFF, crc >> 8))
        crc = crc16(out[-2:], crc)
    return bytes(out)


def parse_fast_sync_read(packet: Packet, length: int) -> list[FastReadSlot]:
    """Split a Fast Sync Read answer into its servos' slots, checking each slot's CRC.

    Args:
        packet: the status packet the parser returned (id ``BROADCAST_ID``); its ``raw`` bytes are used.
        length: the data bytes per servo that the Fast Sync Read asked for.

    Raises:
        DxlCrcError: a slot's CRC does not match; the error names the slot's servo id.
        CodecError: the packet is not a fast read answer of slots of ``length`` data bytes.
    """
    raw = packet.raw
    slot = length + 4
    n_body = len(raw) - 8  # bytes after the instruction byte
    if packet.servo_id != BROADCAST_ID or packet.instruction != Instruction.STATUS or not raw:
        raise CodecError(f"packet from id {packet.servo_id} is not a fast sync read answer (broadcast status)")
    if n_body <= 0 or n_body % slot:
        raise CodecError(
            f"fast sync read answer has {n_body} bytes of slots: expected a multiple of {slot} "
            f"({length} data bytes + error, id and CRC per servo)"
        )
    slots = []
    for start in range(8, len(raw), slot):
        end = start + 2 + length
        servo_id = raw[start + 1]
        crc = raw[end] | (raw[end + 1] << 8)
        if crc16(memoryview(raw)[:end]) != crc:
            raise DxlCrcError(f"servo {servo_id}: fast sync read slot CRC mismatch", servo_id=servo_id)
        slots.append(FastReadSlot(servo_id, raw[start], bytes(raw[start + 2 : end])))
    return slots
