"""DxlArm: an arm of Dynamixel servos on one bus, driven from the env's own process with no middleware.

Start-up (``start``), in the order that keeps the arm still:

1. ping every servo of the map: a silent ID is named with the baud rate, power and ID to check; a wrong model
   names the ID, the model expected and the model found; firmware older than the Bus Watchdog's is refused;
2. the EEPROM settings of the map (drive mode, operating mode, secondary ID, homing offset, limits, velocity
   limit, return delay) are written only where a servo's differ, and only while its torque is off (a servo that
   already holds torque and needs an EEPROM change is refused, never let go);
3. the present positions are read, and every goal is set to them before torque is enabled, so nothing jumps;
4. the group's profile, then torque on, then the Bus Watchdog: if this process goes silent (killed, cable
   pulled), every servo stops and holds by itself within ``ServoMap.bus_watchdog_ms``.

Each tick (``read_state`` and ``write_goals``) is one sync read of the contiguous present current (load on the
XL430), velocity and position block of every answering servo, and one sync write of the arm's goal positions; the
gripper, a group of its own in PWM mode, gets its own sync write when its command changes. The temperatures are a
sync read of their own (``read_temperatures``), taken far less often, and so are the Bus Watchdogs
(``check_watchdogs``: a servo stopped by its watchdog refuses goals, which no sync write reports). Goals meet the
servos' position limits in ticks before they reach the wire, by the ROS bridges' policy: at most ``LIMIT_CLAMP_RAD``
past a limit, clamped to it; further out, refused (the arm keeps its last goal). Each joint's clamp and refusal is
said once in the log.

Errors are ``RobotError``s that name the joint, the ID and what happened: a servo whose status has the alert bit
(its Hardware_Error_Status names the error bits; the arm holds, and the servo is rebooted only when asked,
``reboot``), a servo that stops answering, or status packets with bad CRCs ``max_crc_errors`` ticks in a row.

Shutdown (``close``) as configured: ``"hold"`` keeps the torque on with every goal at the present position (the
watchdog then keeps the arm still), ``"rest"`` moves to the robot's rest pose, waits for it, and only then
turns the torque off. Torque is never simply dropped.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from uniros_async.bus.messages import Header, JointState
from uniros_async.errors import ConfigError, DxlCrcError, DxlError, DxlTimeoutError, RobotError
from uniros_async.hardware.dxl.bus import DxlBus
from uniros_async.hardware.dxl.control_table import (
    BUS_WATCHDOG_UNIT_S,
    MODELS,
    TICKS_PER_TURN,
    ControlTable,
    rad_to_ticks,
    ticks_to_rad,
    velocity_to_rad_s,
)
from uniros_async.hardware.dxl.servo_map import OPERATING_MODES, ServoConfig, ServoMap
from uniros_async.robots import RobotSpec, get_robot_spec

__all__ = ["HARDWARE_ERROR_BITS", "LIMIT_CLAMP_RAD", "MIN_FIRMWARE", "ArmState", "DxlArm", "describe_hardware_error"]

logger = logging.getLogger(__name__)

MIN_FIRMWARE = 38
"""The oldest X-series firmware with the Bus Watchdog (ROBOTIS e-manual, Bus Watchdog)."""
HARDWARE_ERROR_BITS = {
    0x01: "input voltage",
    0x04: "overheating",
    0x08: "motor encoder",
    0x10: "electrical shock",
    0x20: "overload",
}
"""Hardware_Error_Status (70) bits of the X series (ROBOTIS e-manual)."""
STATE_BLOCK = (126, 10)
"""Present current (or load) 126, velocity 128, position 132: one contiguous block, as Interbotix's driver reads."""
GRIPPER_PWM = 350
"""Goal_PWM of the gripper while it opens or closes (of 885), Interbotix's default gripper pressure."""
_CRANK_R, _CRANK_L = 0.014, 0.024  # the rx200 gripper's horn radius and arm length (rx200.yaml)
LIMIT_CLAMP_RAD = 0.05
"""How far past a joint limit a goal may be and still be sent, clamped to the limit; one further out is refused.
The ROS bridges' policy (``adapters/_bridge.py``), so an env meets the same arm behind either."""
RAD_PER_TICK = 2.0 * math.pi / TICKS_PER_TURN
_STALL_TORQUE_NM = {"XM430-W350": 4.1, "XL430-W250": 1.4, "XL330-M288": 0.52}
_TORQUE_CONSTANT_NM_A = {"XM430-W350": 4.1 / 2.3, "XL330-M288": 0.52 / 1.47}


def describe_hardware_error(bits: int) -> str:
    """Name the bits of Hardware_Error_Status, e.g. ``"overload (0x20)"``."""
    names = [name for bit, name in HARDWARE_ERROR_BITS.items() if bits & bit]
    return f"{', '.join(names) or 'unknown'} (0x{bits:02x})"


@dataclass(frozen=True)
class ArmState:
    """One tick's reading of the bus: the joint state, and what ``info`` shows of the servos."""

    joint_state: JointState
    current_a: dict[str, float] = field(default_factory=dict)
    """Present current per joint in A (servos that sense current)."""
    load_pct: dict[str, float] = field(default_factory=dict)
    """Present load per joint in % of the stall torque (servos that report load instead, the XL430)."""


class DxlArm:
    """The arm of ``servos`` on ``bus`` (see the module docstring).

    Args:
        bus: an open DxlBus.
        servos: the arm's servo map.
        robot: its RobotSpec, or None: the registered robot the map names.
        shutdown: ``"hold"`` or ``"rest"``.
        max_crc_errors: ticks in a row whose status packets keep bad CRCs before RobotError.
    """

    def __init__(
        self,
        bus: DxlBus,
        servos: ServoMap,
        robot: RobotSpec | None = None,
        *,
        shutdown: Literal["hold", "rest"] = "hold",
        max_crc_errors: int = 3,
    ) -> None:
        if shutdown not in ("hold", "rest"):
            raise ConfigError(f"shutdown: expected 'hold' or 'rest', got {shutdown!r}")
        self.bus = bus
        self.map = servos
        self.robot = robot if robot is not None else get_robot_spec(servos.robot)
        self.shutdown = shutdown
        self.max_crc_errors = max_crc_errors
        self.arm_joints = tuple(self.robot.arm_joint_names)
        missing = [j for j in self.arm_joints if j not in servos.arm.joints]
        if missing:
            raise ConfigError(f"servo map {servos.name!r}: its arm group lacks the robot's joints {missing}")
        self.arm_servos = [servos.primary(j) for j in self.arm_joints]
        self.gripper = servos.primary(servos.groups[1].joints[0]) if len(servos.groups) > 1 else None
        self.read_servos = self.arm_servos + ([self.gripper] if self.gripper is not None else [])
        self.read_ids = [s.id for s in self.read_servos]
        self._tables: dict[int, ControlTable] = {s.id: MODELS[s.model] for s in servos.servos}
        self._lower = np.array([s.min_position for s in self.arm_servos])
        self._upper = np.array([s.max_position for s in self.arm_servos])
        self._offset = np.array([s.homing_offset for s in self.arm_servos])
        self._clamp_said: set[str] = set()
        self._refuse_said: set[str] = set()
        self.clamped = 0
        """Goal writes with a joint clamped to its limit (at most ``LIMIT_CLAMP_RAD`` past it)."""
        self.refused = 0
        """Goals refused (a joint more than ``LIMIT_CLAMP_RAD`` past its limit): the arm kept its last goal."""
        self._goal: np.ndarray | None = None  # the last goal written, in ticks
        self._gripper_pwm = 0
        self._crc_ticks = 0
        self._last_io_s: float | None = None  # when the last tick's bus I/O ended (the watchdog's clock, host side)
        self._watchdog_s = servos.bus_watchdog_ms / 1e3
        self._commanded = False  # a goal other than start-up's was written
        self.started = False
        self.last_q: np.ndarray | None = None
        self.firmware: dict[int, int] = {}

    # ------------------------------------------------------------------------------------------ helpers

    def _joint(self, servo_id: int) -> str:
        return self.map.by_id(servo_id).joint

    def _error(self, what: str, exc: DxlError) -> RobotError:
        servo_id = getattr(exc, "servo_id", None)
        who = f"joint {self._joint(servo_id)!r} (servo ID {servo_id})" if servo_id in self.map.ids else "the bus"
        if isinstance(exc, DxlTimeoutError):
            return RobotError(
                f"{self.robot.name}: {what}: {who} does not answer on {self.bus.path} ({exc}); check the baud rate "
                f"({self.bus.baud}), the servo's power and its ID"
            )
        return RobotError(f"{self.robot.name}: {what}: {who}: {exc}")

    async def _write_reg(self, servo: ServoConfig, name: str, value: int) -> None:
        reg = self._tables[servo.id].register(name)
        await self.bus.write(servo.id, reg.address, reg.encode(value))

    async def _read_reg(self, servo: ServoConfig, name: str) -> int:
        reg = self._tables[servo.id].register(name)
        return reg.decode(await self.bus.read(servo.id, reg.address, reg.size))

    async def _sync_write(self, name: str, values: dict[int, int]) -> None:
        if not values:
            return
        reg = self._tables[next(iter(values))].register(name)
        await self.bus.sync_write(reg.address, reg.size, {i: reg.encode(v) for i, v in values.items()})

    # ------------------------------------------------------------------------------------------ start-up

    async def start(self) -> None:
        """Ping, check, configure, read, hold, torque on, watchdog on (see the module docstring).

        Raises:
            RobotError: a servo is silent, of the wrong model or firmware, or refuses its configuration.
        """
        for servo in self.map.servos:
            try:
                model, firmware = await self.bus.ping(servo.id)
            except DxlTimeoutError:
                raise RobotError(
                    f"{self.robot.name}: servo ID {servo.id} ({servo.joint}) does not answer a ping on "
                    f"{self.bus.path}; check the baud rate ({self.bus.baud}), the servo's power and that its ID is "
                    f"{servo.id}"
                ) from None
            except DxlError as exc:
                raise self._error("ping", exc) from exc
            expected = MODELS[servo.model]
            if model != expected.model_number:
                found = next((t.name for t in MODELS.values() if t.model_number == model), "an unknown model")
                raise RobotError(
                    f"{self.robot.name}: servo ID {servo.id} ({servo.joint}) is model number {model} ({found}), "
                    f"expected {expected.model_number} ({servo.model}) by servo map {self.map.name!r}"
                )
            if firmware < MIN_FIRMWARE:
                raise RobotError(
                    f"{self.robot.name}: servo ID {servo.id} ({servo.joint}) has firmware {firmware}; the Bus "
                    f"Watchdog needs {MIN_FIRMWARE} or later: update it with ROBOTIS's Dynamixel Wizard"
                )
            self.firmware[servo.id] = firmware
        try:
            await self._configure()
            q_ticks = await self.bus.sync_read(132, 4, list(self.map.ids))
            present = {i: int.from_bytes(b, "little", signed=True) for i, b in q_ticks.items()}
            primaries = [s for s in self.map.servos if not s.is_shadow]
            # goal := present before torque on, so nothing moves (a shadow follows its primary's goal)
            await self._sync_write("goal_position", {s.id: present[s.id] for s in primaries})
            self._goal = np.array([present[s.id] for s in self.arm_servos])
            if self.gripper is not None:
                await self._write_reg(self.gripper, "goal_pwm", 0)
            await self._sync_write(
                "torque_enable", {s.id: 1 for s in primaries if (g := self.map.group_of(s)) is None or g.torque_enable}
            )
            await self._arm_watchdog()
        except DxlError as exc:
            raise self._error("start-up", exc) from exc
        self.started = True
        self._last_io_s = time.monotonic()
        logger.info(
            "%s: %d servos on %s at %d baud, torque on, bus watchdog %d ms",
            self.robot.name,
            len(self.map.servos),
            self.bus.path,
            self.bus.baud,
            self.map.bus_watchdog_ms,
        )

    async def _arm_watchdog(self) -> None:
        """Clear any Bus Watchdog error, then set the map's watchdog time in every servo."""
        await self._sync_write("bus_watchdog", dict.fromkeys(self.map.ids, 0))
        watchdog = round(self.map.bus_watchdog_ms / 1e3 / BUS_WATCHDOG_UNIT_S)
        await self._sync_write("bus_watchdog", dict.fromkeys(self.map.ids, watchdog))

    async def _configure(self) -> None:
        for servo in self.map.servos:
            wanted = self.map.eeprom(servo)
            diff = {}
            for name, value in wanted.items():
                if await self._read_reg(servo, name) != value:
                    diff[name] = value
            torque = await self._read_reg(servo, "torque_enable")
            if diff and torque:
                raise RobotError(
                    f"{self.robot.name}: servo ID {servo.id} ({servo.joint}) holds torque and its EEPROM differs "
                    f"from servo map {self.map.name!r} ({sorted(diff)}); it is not let go to write them: rest the arm, "
                    "power-cycle the servos (torque off) and start again"
                )
            # a watchdog error from an earlier host is cleared first (goal writes are refused while it stands)
            await self._write_reg(servo, "bus_watchdog", 0)
            for name, value in diff.items():
                logger.info("%s: servo ID %d: %s := %d", self.robot.name, servo.id, name, value)
                await self._write_reg(servo, name, value)
            group = self.map.group_of(servo)
            if group is not None and not servo.is_shadow:
                await self._write_reg(servo, "profile_acceleration", group.profile_acceleration)
                await self._write_reg(servo, "profile_velocity", group.profile_velocity)

    # ------------------------------------------------------------------------------------------ a tick

    async def read_state(self, stamp_ns: int) -> ArmState:
        """One sync read of the state block of every arm and gripper servo.

        Raises:
            RobotError: a servo in hardware error (the arm then holds), a silent servo, bad CRCs too often, or a
                bus silent for longer than the Bus Watchdog since the last tick (the servos then stopped and hold,
                and refuse goals).
        """
        now = time.monotonic()
        if self.started and self._last_io_s is not None and now - self._last_io_s > self._watchdog_s:
            if not self._commanded:
                # nothing was commanded since start-up: the stop held the servos where start-up put them
                await self._arm_watchdog()
                self._last_io_s = time.monotonic()
                logger.info("%s: the bus watchdog fired before the first command; armed again", self.robot.name)
                return await self.read_state(stamp_ns)
            raise RobotError(
                f"{self.robot.name}: the bus was silent for {(now - self._last_io_s) * 1e3:.0f} ms, longer than the "
                f"servos' Bus Watchdog ({self.map.bus_watchdog_ms} ms): they stopped and hold, and refuse goals. This "
                "process fell behind its bus loop (a stalled or overloaded host); start the env again"
            )
        try:
            block = await self.bus.sync_read(*STATE_BLOCK, self.read_ids)
        except DxlCrcError as exc:
            self._crc_ticks += 1
            if self._crc_ticks >= self.max_crc_errors:
                raise self._error(f"{self._crc_ticks} ticks in a row with bad status CRCs", exc) from exc
            raise
        except DxlError as exc:
            await self._hold_quietly()
            raise self._error("reading the state", exc) from exc
        self._crc_ticks = 0
        self._last_io_s = time.monotonic()
        n = len(self.read_servos)
        pos, vel, eff = np.empty(n), np.empty(n), np.empty(n)
        current: dict[str, float] = {}
        load_pct: dict[str, float] = {}
        for k, servo in enumerate(self.read_servos):
            raw = block[servo.id]
            load = int.from_bytes(raw[0:2], "little", signed=True)
            vel[k] = velocity_to_rad_s(int.from_bytes(raw[2:6], "little", signed=True))
            ticks = int.from_bytes(raw[6:10], "little", signed=True)
            pos[k] = ticks_to_rad(ticks - servo.homing_offset)
            table = self._tables[servo.id]
            if table.current_unit_a is not None:
                amps = load * table.current_unit_a
                current[servo.joint] = amps
                eff[k] = amps * _TORQUE_CONSTANT_NM_A.get(servo.model, 1.0)
            else:
                load_pct[servo.joint] = load / 10.0  # Present_Load's unit is 0.1 %
                eff[k] = load / 1000.0 * _STALL_TORQUE_NM.get(servo.model, 1.0)
        self.last_q = pos[: len(self.arm_servos)].copy()
        alerts = [i for i in self.read_ids if self.bus.alerts.get(i)]
        if alerts:
            await self._hardware_error(alerts)  # the arm holds where this read found it
        names = self.robot.joint_state_names
        position, velocity, effort = np.zeros(len(names)), np.zeros(len(names)), np.zeros(len(names))
        position[:n], velocity[:n], effort[:n] = pos, vel, eff
        if self.gripper is not None and len(names) >= n + 2:  # the fingers follow the horn (rx200.yaml's crank)
            d = _horn_to_finger(float(pos[n - 1]))
            position[n], position[n + 1] = d, -d
        state = JointState(
            header=Header(stamp_ns=stamp_ns), name=names, position=position, velocity=velocity, effort=effort
        )
        return ArmState(joint_state=state, current_a=current, load_pct=load_pct)

    async def write_goals(self, q_arm: np.ndarray, gripper_m: float | None = None) -> None:
        """One sync write of the arm's goal positions (clamped or refused at the servos' limits, ``_goal_ticks``);
        the gripper's PWM when its command changed (``gripper_m``: the finger's target distance from the centre line).

        Raises:
            RobotError: a non-finite goal, or the bus failed.
        """
        q = np.asarray(q_arm, dtype=np.float64)
        self._commanded = True
        if q.shape != (len(self.arm_servos),) or not np.isfinite(q).all():
            raise RobotError(
                f"{self.robot.name}: expected {len(self.arm_servos)} finite goals {self.arm_joints}, got {q.tolist()}"
            )
        clamped = self._goal_ticks(q)
        try:
            await self._sync_write(
                "goal_position", {s.id: int(c) for s, c in zip(self.arm_servos, clamped, strict=True)}
            )
            if gripper_m is not None and self.gripper is not None and math.isfinite(gripper_m):
                await self._gripper(gripper_m)
            self._last_io_s = time.monotonic()
        except DxlError as exc:
            raise self._error("writing goals", exc) from exc

    def _goal_ticks(self, q: np.ndarray) -> np.ndarray:
        """The goal ticks to write for ``q``, by the ROS bridges' policy: a goal at most ``LIMIT_CLAMP_RAD`` past a
        limit is clamped to it; one further out is refused, and the arm keeps its last goal (start-up's: where
        it was). Each joint's clamp, and each joint's refusal, is said once in the log; both are counted."""
        ticks = np.array([rad_to_ticks(float(x)) for x in q]) + self._offset
        clamped: np.ndarray = np.clip(ticks, self._lower, self._upper)
        past_rad = np.abs(ticks - clamped) * RAD_PER_TICK
        refused = past_rad > LIMIT_CLAMP_RAD
        if refused.any():
            self.refused += 1
            new = [j for j, r in zip(self.arm_joints, refused, strict=True) if r and j not in self._refuse_said]
            if new:
                self._refuse_said.update(new)
                bad = {
                    j: f"{v:.4f} not in [{ticks_to_rad(lo - o):.4f}, {ticks_to_rad(hi - o):.4f}]"
                    for j, v, lo, hi, o, r in zip(
                        self.arm_joints, q, self._lower, self._upper, self._offset, refused, strict=True
                    )
                    if r
                }
                logger.warning(
                    "%s: goal not sent to the servos: beyond the joint limits (by more than %s rad): %s; said once "
                    "per joint",
                    self.robot.name,
                    LIMIT_CLAMP_RAD,
                    bad,
                )
            if self._goal is None:
                raise RobotError(f"{self.robot.name}: a goal before start-up read where the arm is")
            return self._goal
        if (clamped != ticks).any():
            self.clamped += 1
            for j, t, c, o in zip(self.arm_joints, ticks, clamped, self._offset, strict=True):
                if t != c and j not in self._clamp_said:
                    self._clamp_said.add(j)
                    logger.warning(
                        "%s: goal of %s (%d ticks, %.4f rad) clamped to its limit %d ticks; said once per joint",
                        self.robot.name,
                        j,
                        t,
                        ticks_to_rad(t - o),
                        c,
                    )
        self._goal = clamped
        return clamped

    async def _gripper(self, target_m: float) -> None:
        assert self.gripper is not None
        if self.last_q is None:
            return
        mode = OPERATING_MODES[self.map.group_of(self.gripper).operating_mode]  # type: ignore[union-attr]
        if mode != OPERATING_MODES["pwm"]:
            return
        # the measured finger: the last read's gripper horn
        pwm = GRIPPER_PWM if target_m > 0.026 else -GRIPPER_PWM
        if pwm != self._gripper_pwm:
            await self._write_reg(self.gripper, "goal_pwm", pwm)
            self._gripper_pwm = pwm

    async def read_temperatures(self) -> dict[str, float]:
        """Present_Temperature of every arm and gripper servo, in degC, by joint (one sync read).

        Raises:
            RobotError: the bus failed.
        """
        try:
            raw = await self.bus.sync_read(146, 1, self.read_ids)
        except DxlError as exc:
            raise self._error("reading the temperatures", exc) from exc
        return {s.joint: float(raw[s.id][0]) for s in self.read_servos}

    async def check_watchdogs(self) -> None:
        """One sync read of Bus_Watchdog (98) of every arm and gripper servo: a servo whose watchdog stopped it
        refuses goals, and a sync write has no status to say so, so this is how a stop the host did not see
        itself (its packets held up on the way to the servos past the watchdog time) comes out.

        Raises:
            RobotError: a servo stopped on its Bus Watchdog after the arm was commanded (naming it; the arm
                holds, as the stopped servos do), or the bus failed.
        """
        try:
            raw = await self.bus.sync_read(98, 1, self.read_ids)
        except DxlError as exc:
            raise self._error("reading the bus watchdogs", exc) from exc
        stopped = [s for s in self.read_servos if int.from_bytes(raw[s.id], "little", signed=True) < 0]
        if not stopped:
            return
        if not self._commanded:
            await self._arm_watchdog()  # the stop held the servos where start-up put them
            return
        await self._hold_quietly()
        names = ", ".join(f"{s.joint!r} (servo ID {s.id})" for s in stopped)
        raise RobotError(
            f"{self.robot.name}: {names} stopped on the Bus Watchdog ({self.map.bus_watchdog_ms} ms) and refuse "
            "goals, though this host's last tick was in time: its packets were held up on the way to the servos "
            "(a stalled link or host); start the env again"
        )

    # ------------------------------------------------------------------------------------------ errors

    async def _hardware_error(self, ids: list[int]) -> None:
        details = []
        for servo_id in ids:
            servo = self.map.by_id(servo_id)
            try:
                bits = await self._read_reg(servo, "hardware_error_status")
            except DxlError:
                bits = 0
            details.append(f"joint {servo.joint!r} (servo ID {servo_id}): {describe_hardware_error(bits)}")
        await self._hold_quietly()
        raise RobotError(
            f"{self.robot.name}: hardware error: {'; '.join(details)}; the arm holds; reboot the servo "
            "(DxlArm.reboot) once the cause is gone"
        )

    async def _hold_quietly(self) -> None:
        """Every arm servo's goal := its position at the last read, in one sync write (no status packets, so a servo
        that went silent costs no timeout); before any read, goal := present servo by servo. Errors are logged,
        not raised: the arm is already failing."""
        try:
            if self.last_q is not None:
                ticks = [
                    rad_to_ticks(float(q)) + s.homing_offset for s, q in zip(self.arm_servos, self.last_q, strict=True)
                ]
                clamped = np.clip(ticks, self._lower, self._upper)
                await self._sync_write(
                    "goal_position", {s.id: int(t) for s, t in zip(self.arm_servos, clamped, strict=True)}
                )
                return
            for servo in self.map.servos:
                if servo.is_shadow:
                    continue
                try:
                    await self.bus.write(servo.id, 116, await self.bus.read(servo.id, 132, 4))
                except DxlError:
                    continue
        except Exception:  # noqa: BLE001 - holding is best effort here
            logger.exception("%s: could not hold the arm", self.robot.name)

    async def reboot(self, servo_id: int) -> None:
        """Reboot one servo (clears its hardware error; it comes back with torque off), then hold it where it is.

        Raises:
            RobotError: it does not come back.
        """
        servo = self.map.by_id(servo_id)
        try:
            await self.bus.reboot(servo_id)
            await asyncio.sleep(0.05)
            raw = await self.bus.read(servo_id, 132, 4)
            await self.bus.write(servo_id, 116, raw)
            await self._write_reg(servo, "torque_enable", 1)
        except DxlError as exc:
            raise self._error("reboot", exc) from exc

    # ------------------------------------------------------------------------------------------ shutdown

    async def close(self, *, timeout_s: float = 10.0) -> None:
        """Shut down as configured: hold (torque stays on), or move to the rest pose and then torque off."""
        if not self.started:
            return
        self.started = False
        try:
            if self.shutdown == "hold":
                with contextlib.suppress(DxlError, RobotError):
                    await self.read_state(time.monotonic_ns())  # hold where the arm is now, not a tick ago
                await self._hold_quietly()
                return
            rest = np.asarray(self.robot.rest_q_rad)
            await self.write_goals(rest)
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline:
                state = await self.read_state(time.monotonic_ns())
                q = state.joint_state.position[: len(self.arm_servos)]
                if np.max(np.abs(q - rest)) < 0.03 and np.max(np.abs(state.joint_state.velocity[: len(q)])) < 0.05:
                    break
                await asyncio.sleep(0.02)  # a read every 20 ms keeps the bus watchdog fed
            else:
                logger.warning(
                    "%s: the rest pose was not reached in %.1f s: holding, torque stays on", self.robot.name, timeout_s
                )
                await self._hold_quietly()
                return
            await self._sync_write("torque_enable", {s.id: 0 for s in self.map.servos if not s.is_shadow})
        except (DxlError, RobotError):
            logger.exception("%s: shutdown failed; the servos' watchdog holds them", self.robot.name)


def _horn_to_finger(theta: float) -> float:
    """The finger's distance from the centre line for a gripper horn angle (rx200.yaml's crank: r 0.014, L 0.024)."""
    return _CRANK_R * math.sin(theta) + math.sqrt(max(_CRANK_L**2 - (_CRANK_R * math.cos(theta)) ** 2, 0.0))
