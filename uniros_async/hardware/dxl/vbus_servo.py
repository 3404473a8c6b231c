"""One virtual Dynamixel servo: its register memory, laid out by its model's control table, and the servo's
access rules (``VirtualServo``), and the faults a test sets on it (``ServoFaults``). ``vbus.VirtualBus`` holds one
per servo of a map and routes the instructions to them.

The rules are the X series': read-only registers refuse writes, the EEPROM area refuses writes while
Torque_Enable is 1, a register written in part is a data length error, a value outside its range a data limit
error, a Goal_Position outside the position limits (position mode) a data limit error, goal writes are refused
while the Bus Watchdog has tripped, and torque cannot be enabled while a hardware error stands.
"""

from __future__ import annotations

import dataclasses

from uniros_async.hardware.dxl.control_table import ControlTable, Register
from uniros_async.hardware.dxl.protocol import ALERT_BIT
from uniros_async.hardware.dxl.servo_map import OPERATING_MODES, ServoConfig

__all__ = [
    "ERR_ACCESS",
    "ERR_DATA_LENGTH",
    "ERR_DATA_LIMIT",
    "ERR_DATA_RANGE",
    "ERR_INSTRUCTION",
    "ERR_RESULT_FAIL",
    "FIRMWARE_VERSION",
    "ServoFaults",
    "VirtualServo",
]

ERR_RESULT_FAIL = 0x01
ERR_INSTRUCTION = 0x02
ERR_DATA_RANGE = 0x04
ERR_DATA_LENGTH = 0x05
ERR_DATA_LIMIT = 0x06
ERR_ACCESS = 0x07

FIRMWARE_VERSION = 46
"""What the virtual servos report as Firmware_Version."""
_GOAL_NAMES = ("goal_pwm", "goal_current", "goal_velocity", "goal_position")


@dataclasses.dataclass
class ServoFaults:
    """Faults a test sets on one servo.

    Attributes:
        corrupt_crc: the next this many status packets carry a wrong CRC (-1: every one).
        drop_status: the next this many status packets are not sent (-1: none is).
        silent: the servo neither obeys nor answers anything.
    """

    corrupt_crc: int = 0
    drop_status: int = 0
    silent: bool = False

    def take(self, what: str) -> bool:
        """Whether the next status packet gets fault ``what`` (``"corrupt_crc"`` or ``"drop_status"``)."""
        n = getattr(self, what)
        if n == 0:
            return False
        if n > 0:
            setattr(self, what, n - 1)
        return True


class VirtualServo:
    """One servo's register memory and access rules.

    Args:
        config: its entry in the servo map.
        table: its model's control table.
        preset: EEPROM values set at power-up (register names to values), as left by an earlier configuration.
    """

    def __init__(self, config: ServoConfig, table: ControlTable, preset: dict[str, int]) -> None:
        self.config = config
        self.table = table
        self.registers = tuple(table.registers.values())
        self.mem = bytearray(max(r.address + r.size for r in self.registers))
        for reg in self.registers:
            if reg.default is not None:
                self._store(reg, reg.default)
        self.put("model_number", table.model_number)
        self.put("firmware_version", FIRMWARE_VERSION)
        self.put("id", config.id)
        self.put("present_input_voltage", 120)
        self.put("present_temperature", 30)
        for name, value in preset.items():
            self.put(name, value)
        self.faults = ServoFaults()
        self.last_instruction_s: float | None = None
        self.watchdog_tripped = False
        self.pending_write: tuple[int, bytes] | None = None

    # ---- raw access

    def _store(self, reg: Register, value: int) -> None:
        self.mem[reg.address : reg.address + reg.size] = int(value).to_bytes(reg.size, "little", signed=value < 0)

    def get(self, name: str) -> int:
        """A register's value (signed where the register is)."""
        reg = self.table.register(name)
        raw = self.mem[reg.address : reg.address + reg.size]
        return int.from_bytes(raw, "little", signed=reg.signed)

    def put(self, name: str, value: int) -> None:
        """Set a register, bypassing the access rules (the servo's own updates)."""
        self._store(self.table.register(name), value)

    @property
    def id(self) -> int:
        return self.mem[self.table.register("id").address]

    @property
    def secondary_id(self) -> int | None:
        """The Secondary_ID register, or None when it is off (above 252)."""
        value = self.get("secondary_id")
        return None if value > 252 else value

    @property
    def torque_on(self) -> bool:
        return self.get("torque_enable") == 1

    @property
    def hardware_error(self) -> int:
        return self.get("hardware_error_status")

    @property
    def error_byte(self) -> int:
        """The error byte of a status packet without an instruction error: the alert bit when in hardware error."""
        return ALERT_BIT if self.hardware_error else 0

    def watchdog_s(self) -> float:
        """The Bus Watchdog time in seconds (0: off, or tripped)."""
        value = self.get("bus_watchdog")
        return value * 0.020 if value > 0 else 0.0

    # ---- instructions

    def read(self, address: int, length: int) -> tuple[int, bytes]:
        """READ: the error number and the bytes (empty on error)."""
        if length <= 0 or address < 0 or address + length > len(self.mem):
            return ERR_DATA_RANGE, b""
        return 0, bytes(self.mem[address : address + length])

    def check_write(self, address: int, data: bytes) -> int:
        """The error number a WRITE of ``data`` at ``address`` gets (0: allowed)."""
        end = address + len(data)
        if not data or address < 0 or end > len(self.mem):
            return ERR_DATA_RANGE
        for reg in self.registers:
            if reg.address >= end or reg.address + reg.size <= address:
                continue
            if reg.address < address or reg.address + reg.size > end:
                return ERR_DATA_LENGTH  # a register written in part
            if not reg.writable:
                return ERR_ACCESS
            if reg.area == "EEPROM" and self.torque_on:
                return ERR_ACCESS
            if self.watchdog_tripped and reg.name in _GOAL_NAMES:
                return ERR_ACCESS
            raw = data[reg.address - address : reg.address - address + reg.size]
            value = reg.decode(raw)
            if (reg.min is not None and value < reg.min) or (reg.max is not None and value > reg.max):
                return ERR_DATA_LIMIT
            if reg.name == "goal_position" and self.get("operating_mode") == OPERATING_MODES["position"]:
                if not self.get("min_position_limit") <= value <= self.get("max_position_limit"):
                    return ERR_DATA_LIMIT
        return 0

    def write(self, address: int, data: bytes) -> tuple[int, set[str]]:
        """WRITE: the error number and the names of the registers written."""
        error = self.check_write(address, data)
        if error:
            return error, set()
        end = address + len(data)
        written = {r.name for r in self.registers if address <= r.address and r.address + r.size <= end}
        before_torque = self.torque_on
        self.mem[address:end] = data
        if "bus_watchdog" in written and self.get("bus_watchdog") == 0:
            self.watchdog_tripped = False
        if "torque_enable" in written and self.torque_on and not before_torque:
            if self.hardware_error:  # a servo in hardware error keeps its torque off until rebooted
                self.put("torque_enable", 0)
                return ERR_RESULT_FAIL, written
        return 0, written

    def reboot(self, ram_defaults: dict[str, int]) -> None:
        """REBOOT: hardware error cleared, torque off, RAM back to its defaults (Goal_Position := present)."""
        present = self.get("present_position")
        for name, value in ram_defaults.items():
            self.put(name, value)
        self.put("hardware_error_status", 0)
        self.put("goal_position", present)
        self.watchdog_tripped = False
