"""Servo maps: which Dynamixel servo drives which joint of an arm, and how each is configured.

A ``ServoMap`` is plain data, like a ``RobotSpec``: the bus's baud rate, one ``ServoConfig`` per servo (ID, model,
the EEPROM settings the arm needs: drive mode, secondary ID, homing offset, position limits, velocity limit,
return delay) and the ``ServoGroup``s the host drives together (operating mode, profile, torque at start-up). The
rx200's map follows Interbotix's ``rx200.yaml`` and ``modes.yaml`` (docs/robot-facts.md section 1.4).

Positions on the wire are ticks, 4096 per turn, with 2048 at the joint's zero: ``rad = (ticks - 2048) * 2 pi /
4096``. A shadow servo (the rx200's shoulder pair) is a second servo on the same joint: its ``Secondary_ID`` is
the primary's ID, so it obeys every instruction sent to the primary and never answers for it, and its drive mode
is the mirror of the primary's, so both report the same ticks.

Maps are registered by name as robots are (``uniros_async.robots.register_robot``), so a user's own Dynamixel arm
is a map in their own package::

    from uniros_async.hardware.dxl.servo_map import ServoConfig, ServoGroup, ServoMap, register_servo_map

    MYARM_SERVOS = ServoMap(name="myarm", robot="myarm", servos=(ServoConfig(id=1, joint="base", ...), ...), ...)
    register_servo_map(MYARM_SERVOS)  # or register_servo_map("my_pkg.servos:MYARM_SERVOS", name="myarm")

A lookup that misses raises ConfigError naming the registered maps and the closest one.
"""

from __future__ import annotations

import dataclasses
import importlib
from dataclasses import dataclass, field
from typing import Literal

from uniros_async.errors import ConfigError
from uniros_async.hardware.dxl.control_table import MODELS, TICKS_PER_TURN
from uniros_async.registry import Registry

__all__ = [
    "DRIVE_MODE_REVERSE",
    "DRIVE_MODE_TIME_PROFILE",
    "OPERATING_MODES",
    "ServoConfig",
    "ServoGroup",
    "ServoMap",
    "arm_servo_map",
    "register_servo_map",
    "servo_map",
    "servo_map_names",
]

NO_SECONDARY_ID = 255
"""Secondary_ID's value for "none" (anything above 252 disables it)."""

OperatingMode = Literal["current", "velocity", "position", "extended_position", "current_position", "pwm"]
OPERATING_MODES: dict[str, int] = {
    "current": 0,
    "velocity": 1,
    "position": 3,
    "extended_position": 4,
    "current_position": 5,
    "pwm": 16,
}
"""The Operating_Mode register's value of each mode (ROBOTIS e-manual, X series, address 11)."""

DRIVE_MODE_REVERSE = 0x01
"""Drive_Mode bit 0: the servo turns (and counts) the other way."""
DRIVE_MODE_TIME_PROFILE = 0x04
"""Drive_Mode bit 2: Profile_Velocity and Profile_Acceleration are times in ms, not velocity and acceleration."""


@dataclass(frozen=True, kw_only=True)
class ServoConfig:
    """One servo on the bus and the EEPROM settings the arm needs in it.

    Attributes:
        id: the servo's ID (0-252).
        joint: the joint it drives; a shadow names its primary's joint.
        model: the model name, e.g. ``"XM430-W350"`` (a key of the control tables).
        drive_mode: the Drive_Mode register without the profile bit (bit 0: reverse); the profile bit comes from
            the servo's group.
        secondary_id: the primary's ID for a shadow servo, else None.
        homing_offset: Homing_Offset in ticks (added to every position the servo reports).
        min_position: Min_Position_Limit in ticks.
        max_position: Max_Position_Limit in ticks.
        velocity_limit: Velocity_Limit (0.229 rpm units).
        return_delay_time: Return_Delay_Time (2 us units).
    """

    id: int
    joint: str
    model: str
    drive_mode: int = 0
    secondary_id: int | None = None
    homing_offset: int = 0
    min_position: int = 0
    max_position: int = TICKS_PER_TURN - 1
    velocity_limit: int = 131
    return_delay_time: int = 0

    def __post_init__(self) -> None:
        where = f"servo ID {self.id} ({self.joint})"
        if not (isinstance(self.id, int) and 0 <= self.id <= 252):
            raise ConfigError(f"{where}: expected an ID in 0..252, got {self.id!r}")
        if self.secondary_id is not None and not 0 <= self.secondary_id <= 252:
            raise ConfigError(f"{where}: secondary_id must be an ID in 0..252 or None, got {self.secondary_id}")
        if self.secondary_id == self.id:
            raise ConfigError(f"{where}: secondary_id equals its own ID")
        if not 0 <= self.min_position < self.max_position <= TICKS_PER_TURN - 1:
            raise ConfigError(
                f"{where}: expected 0 <= min_position < max_position <= {TICKS_PER_TURN - 1}, "
                f"got {self.min_position}..{self.max_position}"
            )
        if self.drive_mode & ~DRIVE_MODE_REVERSE:
            raise ConfigError(f"{where}: drive_mode holds only the reverse bit (1), got {self.drive_mode}")
        if self.model not in MODELS:
            raise ConfigError(f"{where}: unknown model {self.model!r}; expected one of {sorted(MODELS)}")
        if not 0 <= self.return_delay_time <= 254:
            raise ConfigError(
                f"{where}: return_delay_time must be in 0..254 (2 us units), got {self.return_delay_time}"
            )
        if not 0 <= self.velocity_limit <= 1023:
            raise ConfigError(f"{where}: velocity_limit must be in 0..1023, got {self.velocity_limit}")

    @property
    def is_shadow(self) -> bool:
        """A shadow follows its primary's instructions (Secondary_ID) and never answers for it."""
        return self.secondary_id is not None

    @property
    def secondary_id_register(self) -> int:
        """The Secondary_ID register's value (255: none)."""
        return NO_SECONDARY_ID if self.secondary_id is None else self.secondary_id


@dataclass(frozen=True, kw_only=True)
class ServoGroup:
    """Joints the host drives together with one sync read and one sync write per tick.

    Attributes:
        name: ``"arm"``, ``"gripper"``, ...
        joints: the joints, in the order of the robot's joint states.
        operating_mode: one of ``OPERATING_MODES``.
        profile: ``"time"`` (Profile_Velocity and Profile_Acceleration in ms) or ``"velocity"``.
        profile_velocity: Profile_Velocity (ms with a time profile; 0: none).
        profile_acceleration: Profile_Acceleration (ms with a time profile; 0: none).
        torque_enable: whether start-up enables torque in this group.
    """

    name: str
    joints: tuple[str, ...]
    operating_mode: OperatingMode = "position"
    profile: Literal["time", "velocity"] = "velocity"
    profile_velocity: int = 0
    profile_acceleration: int = 0
    torque_enable: bool = True

    def __post_init__(self) -> None:
        if self.operating_mode not in OPERATING_MODES:
            raise ConfigError(
                f"servo group {self.name!r}: operating_mode must be one of {sorted(OPERATING_MODES)}, "
                f"got {self.operating_mode!r}"
            )
        if self.profile not in ("time", "velocity"):
            raise ConfigError(f"servo group {self.name!r}: profile must be 'time' or 'velocity', got {self.profile!r}")
        if not self.joints:
            raise ConfigError(f"servo group {self.name!r}: no joints")
        if self.profile == "time" and self.profile_acceleration > self.profile_velocity / 2:
            raise ConfigError(
                f"servo group {self.name!r}: a time profile needs profile_acceleration <= profile_velocity / 2, "
                f"got {self.profile_acceleration} and {self.profile_velocity}"
            )

    @property
    def drive_mode_bits(self) -> int:
        """The Drive_Mode bits this group sets (the time-profile bit)."""
        return DRIVE_MODE_TIME_PROFILE if self.profile == "time" else 0


@dataclass(frozen=True, kw_only=True)
class ServoMap:
    """The servos of one arm on one bus.

    Attributes:
        name: the registry name (usually the robot's).
        robot: the registered robot (``RobotSpec``) these servos drive.
        servos: every servo on the bus, shadows included.
        groups: the groups the host drives; the first is the arm (its joints are the robot's arm joints).
        baud: the bus's baud rate.
        bus_watchdog_ms: the Bus Watchdog the host sets in every servo (a multiple of 20 ms, at most 100 ms
            for the arm to stop soon after its host goes silent).
        source: where the numbers come from (one line, for docs and error messages).
    """

    name: str
    robot: str
    servos: tuple[ServoConfig, ...]
    groups: tuple[ServoGroup, ...]
    baud: int = 1_000_000
    bus_watchdog_ms: int = 100
    source: str = ""
    _by_id: dict[int, ServoConfig] = field(init=False, repr=False, compare=False)
    _primary: dict[str, ServoConfig] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        where = f"servo map {self.name!r}"
        by_id: dict[int, ServoConfig] = {}
        primary: dict[str, ServoConfig] = {}
        for s in self.servos:
            if s.id in by_id:
                raise ConfigError(f"{where}: ID {s.id} is used by {by_id[s.id].joint!r} and {s.joint!r}")
            by_id[s.id] = s
            if not s.is_shadow:
                if s.joint in primary:
                    raise ConfigError(
                        f"{where}: joint {s.joint!r} has two primary servos (IDs {primary[s.joint].id}, {s.id})"
                    )
                primary[s.joint] = s
        for s in self.servos:
            if s.is_shadow:
                owner = by_id.get(s.secondary_id or -1)
                if owner is None or owner.is_shadow or owner.joint != s.joint:
                    raise ConfigError(
                        f"{where}: shadow ID {s.id} has secondary_id {s.secondary_id}, which must be the ID of the "
                        f"primary servo of {s.joint!r}"
                    )
        grouped: list[str] = []
        for g in self.groups:
            for j in g.joints:
                if j not in primary:
                    raise ConfigError(f"{where}: group {g.name!r} names joint {j!r}, which has no primary servo")
                if j in grouped:
                    raise ConfigError(f"{where}: joint {j!r} is in two groups")
                grouped.append(j)
        if not self.groups:
            raise ConfigError(f"{where}: no groups (the first is the arm)")
        if self.baud <= 0:
            raise ConfigError(f"{where}: baud must be > 0, got {self.baud}")
        if not (self.bus_watchdog_ms % 20 == 0 and 20 <= self.bus_watchdog_ms <= 2540):
            raise ConfigError(
                f"{where}: bus_watchdog_ms must be a multiple of 20 in 20..2540, got {self.bus_watchdog_ms}"
            )
        object.__setattr__(self, "_by_id", by_id)
        object.__setattr__(self, "_primary", primary)

    @property
    def ids(self) -> tuple[int, ...]:
        """Every servo's ID, in map order."""
        return tuple(s.id for s in self.servos)

    @property
    def arm(self) -> ServoGroup:
        """The arm group (the first)."""
        return self.groups[0]

    def by_id(self, servo_id: int) -> ServoConfig:
        """The servo with this ID.

        Raises:
            ConfigError: no such servo in the map.
        """
        try:
            return self._by_id[servo_id]
        except KeyError:
            raise ConfigError(f"servo map {self.name!r} has no servo ID {servo_id}; IDs: {list(self.ids)}") from None

    def primary(self, joint: str) -> ServoConfig:
        """The servo that answers for ``joint``.

        Raises:
            ConfigError: no servo drives that joint.
        """
        try:
            return self._primary[joint]
        except KeyError:
            raise ConfigError(
                f"servo map {self.name!r} has no servo for joint {joint!r}; joints: {list(self._primary)}"
            ) from None

    def with_arm_profile(self, profile_ms: int) -> ServoMap:
        """This map with the arm group's profile set to ``profile_ms``: Profile_Velocity := ``profile_ms`` and
        Profile_Acceleration := the map's, at most half of it (0 and 0 with ``profile_ms`` 0: no profile, so
        each servo runs at its full speed to every goal, as the servo sim with a 0 s command duration does).

        With a time profile (the rx200's), ``profile_ms`` is the move time of each goal in ms; with a velocity
        profile it is in the register's velocity units.

        Raises:
            ConfigError: ``profile_ms`` is not an integer in 0..32767.
        """
        if isinstance(profile_ms, bool) or not isinstance(profile_ms, int) or not 0 <= profile_ms <= 32767:
            raise ConfigError(f"servo map {self.name!r}: profile_ms must be an integer in 0..32767, got {profile_ms!r}")
        arm = dataclasses.replace(
            self.arm,
            profile_velocity=profile_ms,
            profile_acceleration=min(self.arm.profile_acceleration, profile_ms // 2),
        )
        return dataclasses.replace(self, groups=(arm, *self.groups[1:]))

    def group_of(self, servo: ServoConfig) -> ServoGroup | None:
        """The group whose joints include the servo's joint, or None."""
        return next((g for g in self.groups if servo.joint in g.joints), None)

    def drive_mode(self, servo: ServoConfig) -> int:
        """The Drive_Mode register the host writes: the servo's own bits and its group's profile bit."""
        group = self.group_of(servo)
        return servo.drive_mode | (group.drive_mode_bits if group is not None else 0)

    def eeprom(self, servo: ServoConfig) -> dict[str, int]:
        """The EEPROM registers the host sets in ``servo`` (control-table names to values), written only where
        the servo's differ and only with its torque off."""
        group = self.group_of(servo)
        mode = OPERATING_MODES[group.operating_mode] if group is not None else OPERATING_MODES["position"]
        return {
            "return_delay_time": servo.return_delay_time,
            "drive_mode": self.drive_mode(servo),
            "operating_mode": mode,
            "secondary_id": servo.secondary_id_register,
            "homing_offset": servo.homing_offset,
            "velocity_limit": servo.velocity_limit,
            "max_position_limit": servo.max_position,
            "min_position_limit": servo.min_position,
        }


# ------------------------------------------------------------------------------------------------ the rx200

_ARM_JOINTS = ("waist", "shoulder", "elbow", "wrist_angle", "wrist_rotate")

RX200_SERVOS = ServoMap(
    name="rx200",
    robot="rx200",
    servos=(
        ServoConfig(id=1, joint="waist", model="XL430-W250"),
        ServoConfig(id=2, joint="shoulder", model="XM430-W350", min_position=819, max_position=3333),
        ServoConfig(
            id=3,
            joint="shoulder",
            model="XM430-W350",
            drive_mode=1,
            secondary_id=2,
            min_position=819,
            max_position=3333,
        ),
        ServoConfig(id=4, joint="elbow", model="XM430-W350", drive_mode=1, min_position=819, max_position=3106),
        ServoConfig(id=5, joint="wrist_angle", model="XL430-W250", drive_mode=1, min_position=910, max_position=3447),
        ServoConfig(id=6, joint="wrist_rotate", model="XL430-W250"),
        ServoConfig(id=7, joint="gripper", model="XL430-W250"),
    ),
    groups=(
        ServoGroup(
            name="arm",
            joints=_ARM_JOINTS,
            operating_mode="position",
            profile="time",
            profile_velocity=2000,
            profile_acceleration=300,
        ),
        ServoGroup(name="gripper", joints=("gripper",), operating_mode="pwm"),
    ),
    baud=1_000_000,
    bus_watchdog_ms=100,
    source="Interbotix interbotix_xsarm_control config/rx200.yaml and modes.yaml (docs/robot-facts.md 1.4)",
)
"""The ReactorX-200: IDs 1-7 at 1 Mbps, the shoulder pair 2 and 3 (3 the shadow, reverse), rx200.yaml's limits."""


# ------------------------------------------------------------------------------------------------ the registry


def _check_map(name: str, value: object) -> ServoMap:
    if not isinstance(value, ServoMap):
        raise ConfigError(f"servo map {name!r}: the entry point gives a {type(value).__name__}, not a ServoMap")
    return value


_MAPS: Registry[ServoMap] = Registry(
    "servo map", entry_points="attribute", check=_check_map, note="register_servo_map adds one"
)
_MAPS.register("rx200", f"{__name__}:RX200_SERVOS")


def register_servo_map(servos: ServoMap | str, *, name: str | None = None, override: bool = False) -> None:
    """Register a servo map so that ``dxl://...?map=NAME`` and ``uniros robot vbus NAME`` find it.

    Registering the same map (or entry point) again is a no-op.

    Args:
        servos: the ServoMap, or ``"module:attribute"`` naming one (imported on first lookup).
        name: the registry name; None means ``servos.name`` (an entry point needs it).
        override: replace another map already registered under the name.

    Raises:
        ConfigError: no name for an entry point, a malformed entry point, or the name is taken.
    """
    if isinstance(servos, ServoMap):
        name = servos.name if name is None else name
    elif not isinstance(servos, str):
        raise ConfigError(f"register_servo_map: expected a ServoMap or 'module:attribute', got {type(servos).__name__}")
    elif name is None:
        raise ConfigError(f"register_servo_map({servos!r}): an entry point needs name=")
    _MAPS.register(name, servos, override=override)


def servo_map_names() -> tuple[str, ...]:
    """The registered servo maps' names, sorted."""
    return _MAPS.names()


def servo_map(name: str) -> ServoMap:
    """The servo map registered as ``name`` (``"module:name"`` imports ``module`` first).

    Raises:
        ConfigError: nothing is registered under ``name`` (the message names the closest), or its entry point
            cannot be loaded.
    """
    if not isinstance(name, str):
        raise ConfigError(f"servo map: expected a registered name, got {type(name).__name__} {name!r}")
    if ":" in name:
        module, _, name = name.rpartition(":")
        try:
            importlib.import_module(module)
        except ImportError as exc:
            raise ConfigError(f"servo map '{module}:{name}': cannot import {module!r}: {exc}") from exc
    return _MAPS.get(name)


def arm_servo_map(name: str | None, robot: str, profile_ms: int | None = None) -> ServoMap:
    """The servo map ``name`` (None: the one registered under the robot's name), with the arm group's profile set
    to ``profile_ms`` when given (``ServoMap.with_arm_profile``): how the placement, ``serve --dxl`` and its ROS 2
    driver pick their map.

    Raises:
        ConfigError: as ``servo_map``.
    """
    servos = servo_map(name or robot)
    return servos if profile_ms is None else servos.with_arm_profile(profile_ms)
