"""Dynamixel X-series control tables, one per model, and the conversions between register units and SI.

The registers, their addresses, sizes, access, areas, units, ranges and defaults come from ROBOTIS's e-manual
pages for each model; docs/dynamixel.md copies them with the pages and commits they were taken from.

>>> from uniros_async.hardware.dxl.control_table import MODELS, model_by_number
>>> table = model_by_number(1020)
>>> table.name, table.register("present_position").address
('XM430-W350', 132)

A model of your own is a ``ControlTable`` passed to ``register_model`` (as gymnasium's ``register`` adds an env).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping
from typing import Literal

from uniros_async.errors import ConfigError

__all__ = [
    "BAUD_RATES",
    "MODELS",
    "TICKS_PER_TURN",
    "XL330_M288",
    "XL430_W250",
    "XM430_W350",
    "ControlTable",
    "Register",
    "baud_code",
    "current_to_amps",
    "model_by_number",
    "rad_to_ticks",
    "temperature_to_celsius",
    "rad_s_to_velocity",
    "register_model",
    "ticks_to_rad",
    "velocity_to_rad_s",
    "voltage_to_volts",
]

TICKS_PER_TURN = 4096
"""Encoder ticks per turn of the X series' 12-bit absolute encoder."""
CENTRE_TICKS = 2048
"""The tick of 0 rad: the middle of the 0..4095 position range."""
VELOCITY_UNIT_RPM = 0.229
"""One unit of the velocity registers (Present/Goal Velocity, Velocity Limit, Profile Velocity), rev/min."""
VOLTAGE_UNIT_V = 0.1
"""One unit of Present Input Voltage and the voltage limits, V."""
RETURN_DELAY_UNIT_S = 2e-6
"""One unit of Return Delay Time (9), s."""
BUS_WATCHDOG_UNIT_S = 0.020
"""One unit of Bus Watchdog (98), s."""

BAUD_RATES: dict[int, int] = {
    0: 9_600,
    1: 57_600,
    2: 115_200,
    3: 1_000_000,
    4: 2_000_000,
    5: 3_000_000,
    6: 4_000_000,
    7: 4_500_000,
}
"""Baud Rate (8) code -> bit/s for the X series (XL330 stops at code 6)."""

Access = Literal["R", "RW"]
Area = Literal["EEPROM", "RAM"]


@dataclasses.dataclass(frozen=True, slots=True)
class Register:
    """One entry of a control table.

    Attributes:
        name: snake_case of the e-manual's Data Name ("present_position").
        address: the first byte's address.
        size: bytes (1, 2 or 4), little-endian.
        access: "R" or "RW".
        area: "EEPROM" (written only with torque off, kept over power cycles) or "RAM".
        unit: the e-manual's unit ("0.229 rev/min", "1 pulse"), "" when it has none.
        min: the least value the e-manual allows, ``None`` when it gives none (or a range set by another register).
        max: the greatest value, likewise.
        default: the e-manual's initial value, ``None`` when it gives none.
        signed: whether the value is two's complement (velocities, currents, positions, offsets).
    """

    name: str
    address: int
    size: int
    access: Access
    area: Area
    unit: str = ""
    min: int | None = None
    max: int | None = None
    default: int | None = None
    signed: bool = False

    @property
    def writable(self) -> bool:
        """Whether the register can be written."""
        return self.access == "RW"

    def encode(self, value: int) -> bytes:
        """The register's bytes for ``value``.

        Raises:
            ConfigError: the register is read-only, or ``value`` is outside its range or its size.
        """
        if not self.writable:
            raise ConfigError(f"register {self.name} ({self.address}) is read-only: expected a RW register")
        if (self.min is not None and value < self.min) or (self.max is not None and value > self.max):
            raise ConfigError(f"{value} for register {self.name} ({self.address}): expected {self.min}..{self.max}")
        try:
            return int(value).to_bytes(self.size, "little", signed=self.signed)
        except OverflowError:
            kind = "signed" if self.signed else "unsigned"
            raise ConfigError(
                f"{value} for register {self.name} ({self.address}) does not fit its {self.size} {kind} bytes"
            ) from None

    def decode(self, data: bytes, offset: int = 0) -> int:
        """The register's value from ``data[offset:offset + size]``."""
        return int.from_bytes(data[offset : offset + self.size], "little", signed=self.signed)


@dataclasses.dataclass(frozen=True)
class ControlTable:
    """The control table of one Dynamixel model.

    Attributes:
        name: the model's name ("XM430-W350").
        model_number: what Model Number (0) and a ping report.
        registers: by name, in address order.
        current_unit_a: one unit of the current registers, A (``None`` for a model without them).
        source: the e-manual page the table comes from.
    """

    name: str
    model_number: int
    registers: Mapping[str, Register]
    current_unit_a: float | None
    source: str = ""

    def register(self, name: str) -> Register:
        """The register called ``name``.

        Raises:
            ConfigError: the model has no such register; the message lists the ones it has.
        """
        try:
            return self.registers[name]
        except KeyError:
            raise ConfigError(
                f"{self.name} has no register {name!r}: expected one of {', '.join(self.registers)}"
            ) from None

    def at(self, address: int) -> Register | None:
        """The register that starts at ``address``, or ``None``."""
        for reg in self.registers.values():
            if reg.address == address:
                return reg
        return None

    def span(self, first: str, last: str) -> tuple[int, int]:
        """``(address, length)`` of the contiguous block from register ``first`` through register ``last``."""
        a, b = self.register(first), self.register(last)
        if b.address < a.address:
            raise ConfigError(f"register {last} ({b.address}) comes before {first} ({a.address}): expected it after")
        return a.address, b.address + b.size - a.address

    def __contains__(self, name: object) -> bool:
        return name in self.registers


def _table(name: str, number: int, current_unit_a: float | None, source: str, rows: Iterable[Register]) -> ControlTable:
    regs = sorted(rows, key=lambda r: r.address)
    return ControlTable(name, number, {r.name: r for r in regs}, current_unit_a, source)


def _r(
    name: str,
    address: int,
    size: int,
    access: Access,
    unit: str = "",
    lo: int | None = None,
    hi: int | None = None,
    default: int | None = None,
    *,
    signed: bool = False,
) -> Register:
    return Register(name, address, size, access, "EEPROM" if address < 64 else "RAM", unit, lo, hi, default, signed)


_POS = "1 pulse"
_VEL = "0.229 rev/min"


def _x_common(
    *,
    velocity_limit: tuple[int, int],
    voltage: tuple[int, int, int, int],
    temperature_limit: int,
    gains: tuple[int, int, int, int, int],
    drive_mode_max: int,
    baud_max: int = 7,
    protocol: tuple[int, int] = (1, 2),
    shutdown: int = 52,
) -> list[Register]:
    """The registers the X-series models share; the model's own values where they differ."""
    v_max, v_min, v_lo, v_hi = voltage
    vel_i, vel_p, pos_d, pos_i, pos_p = gains
    return [
        _r("model_number", 0, 2, "R"),
        _r("model_information", 2, 4, "R"),
        _r("firmware_version", 6, 1, "R"),
        _r("id", 7, 1, "RW", "", 0, 252, 1),
        _r("baud_rate", 8, 1, "RW", "", 0, baud_max, 1),
        _r("return_delay_time", 9, 1, "RW", "2 usec", 0, 254, 250),
        _r("drive_mode", 10, 1, "RW", "", 0, drive_mode_max, 0),
        _r("operating_mode", 11, 1, "RW", "", 0, 16, 3),
        _r("secondary_id", 12, 1, "RW", "", 0, 255, 255),
        _r("protocol_type", 13, 1, "RW", "", protocol[0], protocol[1], 2),
        _r("homing_offset", 20, 4, "RW", _POS, -1_044_479, 1_044_479, 0, signed=True),
        _r("moving_threshold", 24, 4, "RW", _VEL, 0, 1023, 10),
        _r("temperature_limit", 31, 1, "RW", "1 degC", 0, 100, temperature_limit),
        _r("max_voltage_limit", 32, 2, "RW", "0.1 V", v_lo, v_hi, v_max),
        _r("min_voltage_limit", 34, 2, "RW", "0.1 V", v_lo, v_hi, v_min),
        _r("pwm_limit", 36, 2, "RW", "0.113 %", 0, 885, 885),
        _r("velocity_limit", 44, 4, "RW", _VEL, 0, velocity_limit[1], velocity_limit[0]),
        _r("max_position_limit", 48, 4, "RW", _POS, 0, 4095, 4095),
        _r("min_position_limit", 52, 4, "RW", _POS, 0, 4095, 0),
        _r("shutdown", 63, 1, "RW", "", None, None, shutdown),
        _r("torque_enable", 64, 1, "RW", "", 0, 1, 0),
        _r("led", 65, 1, "RW", "", 0, 1, 0),
        _r("status_return_level", 68, 1, "RW", "", 0, 2, 2),
        _r("registered_instruction", 69, 1, "R", "", 0, 1, 0),
        _r("hardware_error_status", 70, 1, "R", "", None, None, 0),
        _r("velocity_i_gain", 76, 2, "RW", "", 0, 16383, vel_i),
        _r("velocity_p_gain", 78, 2, "RW", "", 0, 16383, vel_p),
        _r("position_d_gain", 80, 2, "RW", "", 0, 16383, pos_d),
        _r("position_i_gain", 82, 2, "RW", "", 0, 16383, pos_i),
        _r("position_p_gain", 84, 2, "RW", "", 0, 16383, pos_p),
        _r("feedforward_2nd_gain", 88, 2, "RW", "", 0, 16383, 0),
        _r("feedforward_1st_gain", 90, 2, "RW", "", 0, 16383, 0),
        # 0 disables it; 1..127 arm it; the servo writes -1 when it fired (e-manual, Bus Watchdog)
        _r("bus_watchdog", 98, 1, "RW", "20 msec", -1, 127, 0, signed=True),
        _r("goal_pwm", 100, 2, "RW", "0.113 %", -885, 885, signed=True),
        _r("goal_velocity", 104, 4, "RW", _VEL, -velocity_limit[1], velocity_limit[1], signed=True),
        _r("profile_acceleration", 108, 4, "RW", "214.577 rev/min^2 or 1 ms", 0, 32767, 0),
        _r("profile_velocity", 112, 4, "RW", _VEL, 0, 32767, 0),
        # 0..4095 in position mode; -1,048,575..1,048,575 in extended position modes
        _r("goal_position", 116, 4, "RW", _POS, -1_048_575, 1_048_575, signed=True),
        _r("realtime_tick", 120, 2, "R", "1 msec", 0, 32767),
        _r("moving", 122, 1, "R", "", 0, 1, 0),
        _r("moving_status", 123, 1, "R", "", None, None, 0),
        _r("present_pwm", 124, 2, "R", "0.113 %", signed=True),
        _r("present_velocity", 128, 4, "R", _VEL, signed=True),
        _r("present_position", 132, 4, "R", _POS, signed=True),
        _r("velocity_trajectory", 136, 4, "R", _VEL, signed=True),
        _r("position_trajectory", 140, 4, "R", _POS, signed=True),
        _r("present_input_voltage", 144, 2, "R", "0.1 V"),
        _r("present_temperature", 146, 1, "R", "1 degC"),
    ]


def _indirect(n_low: int, n_high: int, address_hi: int) -> list[Register]:
    """Indirect Address 1..n and Indirect Data 1..n (and 29..56 above address 578 where the model has them)."""
    rows = []
    data_low = 168 + 2 * n_low
    for i in range(n_low):
        rows.append(_r(f"indirect_address_{i + 1}", 168 + 2 * i, 2, "RW", "", 64, address_hi, data_low + i))
        rows.append(_r(f"indirect_data_{i + 1}", data_low + i, 1, "RW", "", 0, 255, 0))
    for i in range(n_high):
        rows.append(_r(f"indirect_address_{n_low + i + 1}", 578 + 2 * i, 2, "RW", "", 64, address_hi, 634 + i))
        rows.append(_r(f"indirect_data_{n_low + i + 1}", 634 + i, 1, "RW", "", 0, 255, 0))
    return rows


XL430_W250 = _table(
    "XL430-W250",
    1060,
    None,
    "https://emanual.robotis.com/docs/en/dxl/x/xl430-w250/",
    [
        *_x_common(
            velocity_limit=(265, 1023),
            voltage=(140, 60, 60, 140),
            temperature_limit=72,
            gains=(1000, 100, 4000, 0, 640),
            drive_mode_max=13,
        ),
        _r("startup_configuration", 60, 1, "RW", "", 0, 3, 0),
        _r("present_load", 126, 2, "R", "0.1 %", -1000, 1000, signed=True),
        _r("backup_ready", 147, 1, "R", "", 0, 1),
        *_indirect(28, 28, 661),
    ],
)
"""XL430-W250-T (model number 1060): no current sensing; Present Load (126) in 0.1 % of the stall torque."""

XM430_W350 = _table(
    "XM430-W350",
    1020,
    2.69e-3,
    "https://emanual.robotis.com/docs/en/dxl/x/xm430-w350/",
    [
        *_x_common(
            velocity_limit=(200, 1023),
            voltage=(160, 95, 95, 160),
            temperature_limit=80,
            gains=(1920, 100, 0, 0, 800),
            drive_mode_max=13,
        ),
        _r("current_limit", 38, 2, "RW", "2.69 mA", 0, 1193, 1193),
        _r("goal_current", 102, 2, "RW", "2.69 mA", -1193, 1193, signed=True),
        _r("present_current", 126, 2, "R", "2.69 mA", signed=True),
        *_indirect(28, 28, 661),
    ],
)
"""XM430-W350-T/R (model number 1020): current in units of 2.69 mA."""

XL330_M288 = _table(
    "XL330-M288",
    1200,
    1e-3,
    "https://emanual.robotis.com/docs/en/dxl/x/xl330-m288/",
    [
        *_x_common(
            velocity_limit=(445, 2047),
            voltage=(70, 35, 31, 70),
            temperature_limit=70,
            gains=(1600, 180, 0, 0, 400),
            drive_mode_max=5,
            baud_max=6,
            protocol=(2, 22),
            shutdown=53,
        ),
        _r("startup_configuration", 60, 1, "RW", "", 0, 3, 0),
        _r("pwm_slope", 62, 1, "RW", "1.977 mV/msec", 1, 255, 140),
        _r("current_limit", 38, 2, "RW", "1 mA", 0, 1750, 1750),
        _r("goal_current", 102, 2, "RW", "1 mA", -1750, 1750, signed=True),
        _r("present_current", 126, 2, "R", "1 mA", signed=True),
        _r("backup_ready", 147, 1, "R", "", 0, 1),
        *_indirect(20, 0, 227),
    ],
)
"""XL330-M288-T (model number 1200): current in units of 1 mA; Baud Rate codes 0..6; Protocol Type 2..22."""


MODELS: dict[str, ControlTable] = {t.name: t for t in (XL430_W250, XM430_W350, XL330_M288)}
"""Every known model by name; ``register_model`` adds one."""


def register_model(table: ControlTable) -> None:
    """Make ``table`` known to ``MODELS`` and ``model_by_number``.

    Raises:
        ConfigError: another table already has its name or model number.
    """
    for other in MODELS.values():
        if other is not table and (other.name == table.name or other.model_number == table.model_number):
            raise ConfigError(
                f"model {table.name} ({table.model_number}) clashes with {other.name} ({other.model_number}): "
                "expected a new name and model number"
            )
    MODELS[table.name] = table


def model_by_number(number: int) -> ControlTable:
    """The table of the model whose Model Number (0) is ``number``.

    Raises:
        ConfigError: no known model has that number; the message lists the known ones.
    """
    for table in MODELS.values():
        if table.model_number == number:
            return table
    known = ", ".join(f"{t.name} ({t.model_number})" for t in MODELS.values())
    raise ConfigError(f"no Dynamixel model with model number {number}: expected one of {known}")


def baud_code(baud: int, table: ControlTable | None = None) -> int:
    """The Baud Rate (8) code of ``baud`` bit/s.

    Raises:
        ConfigError: the X series (or ``table``'s model) has no such rate.
    """
    top = table.register("baud_rate").max if table is not None else None
    for code, rate in BAUD_RATES.items():
        if rate == baud and (top is None or code <= top):
            return code
    rates = [r for c, r in BAUD_RATES.items() if top is None or c <= top]
    raise ConfigError(f"baud rate {baud}: expected one of {rates}")


# ---------------------------------------------------------------------------------------- conversions


def ticks_to_rad(ticks: int | float) -> float:
    """Present/Goal Position ticks -> rad, with 2048 ticks at 0 rad and 4096 per turn."""
    return (ticks - CENTRE_TICKS) * (2.0 * math.pi / TICKS_PER_TURN)


def rad_to_ticks(rad: float) -> int:
    """rad -> the nearest position tick (2048 at 0 rad, 4096 per turn)."""
    return CENTRE_TICKS + round(rad * (TICKS_PER_TURN / (2.0 * math.pi)))


def velocity_to_rad_s(units: int | float) -> float:
    """Velocity register units (0.229 rev/min) -> rad/s."""
    return units * VELOCITY_UNIT_RPM * (2.0 * math.pi / 60.0)


def rad_s_to_velocity(rad_s: float) -> int:
    """rad/s -> the nearest velocity register unit (0.229 rev/min)."""
    return round(rad_s / (VELOCITY_UNIT_RPM * 2.0 * math.pi / 60.0))


def current_to_amps(units: int | float, table: ControlTable) -> float:
    """Current register units -> A for ``table``'s model.

    Raises:
        ConfigError: the model does not sense current (XL430-W250 reports Present Load instead).
    """
    if table.current_unit_a is None:
        raise ConfigError(f"{table.name} has no current registers: expected a model that senses current")
    return units * table.current_unit_a


def voltage_to_volts(units: int | float) -> float:
    """Present Input Voltage units (0.1 V) -> V."""
    return units * VOLTAGE_UNIT_V


def temperature_to_celsius(units: int) -> float:
    """Present Temperature (1 degC per unit) -> degC."""
    return float(units)
