"""VirtualBus: the Dynamixel servos of an arm answered from its MuJoCo servo sim.

Each servo of a ``ServoMap`` gets a register memory laid out by its model's control table (EEPROM and RAM,
filled with the model's defaults and the map's EEPROM settings), with the servo's access rules: read-only
registers refuse writes, the EEPROM area refuses writes while Torque_Enable is 1, a Goal_Position outside the
position limits is refused with a data limit error. ``handle(packet)`` applies one instruction packet to every
servo it addresses and returns the status packets they send, in the order the real bus sends them; servos whose
Secondary_ID is the packet's ID obey it and never answer (the rx200's shoulder shadow).

The arm itself is a ``ServoSim`` stepped on the wall clock (``advance(now_s)``, 10 ms steps):

- Goal_Position of the arm's servos drives the sim's servo targets, with the servos' profile (time-based:
  Profile_Velocity is the move time in ms); a servo with its torque off holds where it is (its gearbox holds
  the joint; the sim does not let it fall). The gripper in PWM mode opens for a positive Goal_PWM and closes for a
  negative one; in position mode its Goal_Position is the horn angle.
- Present_Position, Present_Velocity and Present_Current (Present_Load on the XL430) are the sim's, quantized to
  the registers' units; a shadow reports its primary's ticks (its reverse drive mode mirrors its mounting).
- The Bus Watchdog (address 98, 20 ms units): a servo whose torque is on and that receives no instruction for
  longer than its watchdog stops and holds (Goal_Position := Present_Position), sets Bus_Watchdog to -1 and
  refuses goal writes until Bus_Watchdog is written 0, as the X series do.

Faults are set per servo (``ServoFaults``): corrupted status CRCs, dropped status packets, a silent servo, and
Hardware_Error_Status bits (the alert bit in every status; torque off where the Shutdown register says).

One servo's register memory and access rules are ``vbus_servo.py``; the pty, timing and command channel around
the bus are ``vbus_pty.py``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import numpy as np

from uniros_async.bus.messages import Header, JointCommand
from uniros_async.errors import ConfigError
from uniros_async.hardware.dxl.control_table import MODELS, rad_to_ticks, ticks_to_rad
from uniros_async.hardware.dxl.protocol import (
    BROADCAST_ID,
    Instruction,
    Packet,
    encode_fast_sync_read_status,
    encode_status,
)
from uniros_async.hardware.dxl.servo_map import DRIVE_MODE_TIME_PROFILE, OPERATING_MODES, ServoMap
from uniros_async.hardware.dxl.vbus_servo import (
    ERR_DATA_LENGTH,
    ERR_INSTRUCTION,
    ServoFaults,
    VirtualServo,
)
from uniros_async.robots import get_robot_spec
from uniros_async.sim.emulated import EmulationConfig, add_sensor_noise
from uniros_async.sim.imperfections import Imperfections
from uniros_async.sim.node import build_sim
from uniros_async.sim.servo import ServoSimConfig

__all__ = ["ServoFaults", "VirtualBus", "VirtualServo"]

logger = logging.getLogger(__name__)

SIM_STEP_S = 0.01
"""The sim's step on the wall clock (5 physics steps of 2 ms)."""
VELOCITY_UNIT_RAD_S = 0.229 * 2.0 * math.pi / 60.0
"""Present_Velocity's unit, 0.229 rpm, in rad/s."""
CURRENT_UNIT_A = 0.00269
"""Present_Current's unit on the XM430, 2.69 mA."""
TORQUE_CONSTANT_NM_A = {"XM430-W350": 4.1 / 2.3, "XL430-W250": 1.4 / 1.3, "XL330-M288": 0.52 / 1.47}
"""Stall torque over stall current at 12 V (11.1 V for the XL430, 5 V for the XL330), ROBOTIS e-manual."""
STALL_TORQUE_NM = {"XM430-W350": 4.1, "XL430-W250": 1.4, "XL330-M288": 0.52}
_CRANK_R, _CRANK_L = 0.014, 0.024  # the rx200 gripper's horn radius and arm length (rx200.yaml)
_FINGER_RANGE = (0.015, 0.037)


def _horn_to_finger(theta: float) -> float:
    """The finger's distance from the centre line for a gripper horn angle (the crank-slider law of rx200.xml)."""
    d = _CRANK_R * math.sin(theta) + math.sqrt(_CRANK_L**2 - (_CRANK_R * math.cos(theta)) ** 2)
    return min(max(d, _FINGER_RANGE[0]), _FINGER_RANGE[1])


class VirtualBus:
    """The servos of ``servos`` (a ServoMap) on one bus, answered from the arm's ServoSim.

    Args:
        servos: the arm's servo map.
        emulation: make the sim the emulated real arm (perturbed dynamics, sensor noise); None: the nominal sim.
        imperfections: servo-level imperfections of the sim's servos (``Imperfections.servo_effects``: backlash,
            offsets, quantization and deadband, sag, limits); None: none.
        on_event: called with one line for every notable event (watchdog trips, hardware errors).

    Raises:
        ConfigError: the map names a model without a control table, or a robot that is not registered.
    """

    def __init__(
        self,
        servos: ServoMap,
        *,
        emulation: EmulationConfig | None = None,
        imperfections: Imperfections | None = None,
        on_event: Callable[[str], None] | None = None,
    ) -> None:
        self.map = servos
        self.robot = get_robot_spec(servos.robot)
        self.emulation = emulation
        self.on_event = on_event or (lambda line: None)
        config = ServoSimConfig(control_period_s=SIM_STEP_S, command_timeout_s=None, target_update_steps=5)
        self.sim, _ = build_sim(self.robot, config, emulation, imperfections)
        self._rng = np.random.default_rng(None if emulation is None else emulation.seed + 2)
        self.servos: dict[int, VirtualServo] = {}
        self._ram_defaults: dict[int, dict[str, int]] = {}
        for s in servos.servos:
            table = MODELS[s.model]
            preset = dict(servos.eeprom(s))
            # the profile bit and the operating mode are the host's to set at start-up
            preset["drive_mode"] = s.drive_mode
            preset["operating_mode"] = OPERATING_MODES["position"]
            servo = VirtualServo(s, table, preset)
            self.servos[s.id] = servo
            self._ram_defaults[s.id] = {
                r.name: r.default
                for r in table.registers.values()
                if r.area == "RAM" and r.writable and r.default is not None
            }
        names = self.robot.joint_state_names
        self._arm = list(self.robot.arm_joint_names)
        self._index = {name: i for i, name in enumerate(names)}
        self._gripper_finger: float | None = None
        self._goal_dirty = False
        self._t0_s: float | None = None
        self._steps = 0
        self.instructions = 0
        self._update_present()
        for servo in self.servos.values():
            servo.put("goal_position", servo.get("present_position"))

    # ------------------------------------------------------------------------------------------ packets

    def addressed(self, servo_id: int) -> list[VirtualServo]:
        """The servos that obey an instruction to ``servo_id``: that servo, and those with it as Secondary_ID."""
        return [
            s
            for s in self.servos.values()
            if not s.faults.silent and (s.id == servo_id or s.secondary_id == servo_id or servo_id == BROADCAST_ID)
        ]

    def _answering(self, servo_id: int) -> VirtualServo | None:
        servo = self.servos.get(servo_id)
        return None if servo is None or servo.faults.silent else servo

    def handle(self, packet: Packet, now_s: float) -> list[tuple[int, bytes]]:
        """Apply one instruction packet; return the status packets as ``(answering id, bytes)``, in bus order.

        Status packets are returned before the ``ServoFaults`` of their servo apply (``finish_status`` does).
        """
        if packet.is_status:
            return []
        self.instructions += 1
        inst, pid, params = packet.instruction, packet.servo_id, packet.params
        out: list[tuple[int, bytes]] = []
        if inst in (Instruction.SYNC_READ, Instruction.SYNC_WRITE, Instruction.FAST_SYNC_READ):
            ids = self._sync_ids(inst, params)
            touched = [
                s for s in self.servos.values() if not s.faults.silent and (s.id in ids or s.secondary_id in ids)
            ]
        elif inst in (Instruction.BULK_READ, Instruction.BULK_WRITE):
            ids = self._bulk_ids(inst, params)
            touched = [
                s for s in self.servos.values() if not s.faults.silent and (s.id in ids or s.secondary_id in ids)
            ]
        else:
            touched = self.addressed(pid)
        for s in touched:
            s.last_instruction_s = now_s
        answer = pid != BROADCAST_ID
        if inst == Instruction.PING:
            for s in touched:
                if s.id == pid or (pid == BROADCAST_ID and s.secondary_id is None):
                    info = s.get("model_number").to_bytes(2, "little") + bytes((s.get("firmware_version"),))
                    out.append((s.id, encode_status(s.id, s.error_byte, info)))
        elif inst == Instruction.READ:
            if len(params) != 4:
                out += self._errors(touched, pid, ERR_DATA_LENGTH) if answer else []
            else:
                address, length = _u16(params, 0), _u16(params, 2)
                servo = self._answering(pid)
                if servo is not None:
                    err, data = servo.read(address, length)
                    out.append((pid, encode_status(pid, err | servo.error_byte, data)))
        elif inst in (Instruction.WRITE, Instruction.REG_WRITE):
            if len(params) < 3:
                out += self._errors(touched, pid, ERR_DATA_LENGTH) if answer else []
            else:
                address, data = _u16(params, 0), params[2:]
                for s in touched:
                    if inst == Instruction.REG_WRITE:
                        err = s.check_write(address, data)
                        if not err:
                            s.pending_write = (address, data)
                    else:
                        err = self._write(s, address, data)
                    if answer and s.id == pid:
                        out.append((s.id, encode_status(s.id, err | s.error_byte)))
        elif inst == Instruction.ACTION:
            for s in touched:
                if s.pending_write is not None:
                    self._write(s, *s.pending_write)
                    s.pending_write = None
                if answer and s.id == pid:
                    out.append((s.id, encode_status(s.id, s.error_byte)))
        elif inst == Instruction.REBOOT:
            for s in touched:
                s.reboot(self._ram_defaults[s.config.id])
                self._goal_dirty = True
                self.on_event(f"reboot id={s.id}")
                if answer and s.id == pid:
                    out.append((s.id, encode_status(s.id, 0)))
        elif inst == Instruction.SYNC_WRITE:
            self._sync_write(params, touched)
        elif inst == Instruction.BULK_WRITE:
            self._bulk_write(params, touched)
        elif inst == Instruction.SYNC_READ:
            address, length = _u16(params, 0), _u16(params, 2)
            for servo_id in params[4:]:
                servo = self._answering(servo_id)
                if servo is not None:
                    err, data = servo.read(address, length)
                    out.append((servo_id, encode_status(servo_id, err | servo.error_byte, data)))
        elif inst == Instruction.FAST_SYNC_READ:
            address, length = _u16(params, 0), _u16(params, 2)
            slots = []
            for servo_id in params[4:]:
                servo = self._answering(servo_id)
                if servo is None:
                    break  # the chain of slots ends at the first servo that does not answer
                err, data = servo.read(address, length)
                slots.append((servo_id, err | servo.error_byte, data if not err else bytes(length)))
            if slots:
                out.append((slots[0][0], encode_fast_sync_read_status(slots)))
        elif inst == Instruction.BULK_READ:
            for k in range(0, len(params) - 4, 5):
                servo_id, address, length = params[k], _u16(params, k + 1), _u16(params, k + 3)
                servo = self._answering(servo_id)
                if servo is not None:
                    err, data = servo.read(address, length)
                    out.append((servo_id, encode_status(servo_id, err | servo.error_byte, data)))
        else:
            if answer:
                out += self._errors(touched, pid, ERR_INSTRUCTION)
        return out

    def finish_status(self, servo_id: int, status: bytes) -> bytes | None:
        """Apply the servo's status faults to one status packet: None when it is dropped."""
        servo = self.servos.get(servo_id)
        if servo is None:
            return status
        if servo.faults.take("drop_status"):
            return None
        if servo.faults.take("corrupt_crc"):
            return status[:-1] + bytes((status[-1] ^ 0x5A,))
        return status

    def _errors(self, touched: list[VirtualServo], pid: int, err: int) -> list[tuple[int, bytes]]:
        return [(s.id, encode_status(s.id, err | s.error_byte)) for s in touched if s.id == pid]

    @staticmethod
    def _sync_ids(inst: int, params: bytes) -> set[int]:
        if inst in (Instruction.SYNC_READ, Instruction.FAST_SYNC_READ):
            return set(params[4:])
        length = _u16(params, 2) if len(params) >= 4 else 0
        return {params[k] for k in range(4, len(params), length + 1)} if length else set()

    @staticmethod
    def _bulk_ids(inst: int, params: bytes) -> set[int]:
        ids: set[int] = set()
        k = 0
        while k + 5 <= len(params):
            ids.add(params[k])
            k += 5 if inst == Instruction.BULK_READ else 5 + _u16(params, k + 3)
        return ids

    def _sync_write(self, params: bytes, touched: list[VirtualServo]) -> None:
        if len(params) < 4:
            return
        address, length = _u16(params, 0), _u16(params, 2)
        for k in range(4, len(params) - length, length + 1):
            target, data = params[k], params[k + 1 : k + 1 + length]
            for s in touched:
                if s.id == target or s.secondary_id == target:
                    self._write(s, address, data)

    def _bulk_write(self, params: bytes, touched: list[VirtualServo]) -> None:
        k = 0
        while k + 5 <= len(params):
            target, address, length = params[k], _u16(params, k + 1), _u16(params, k + 3)
            data = params[k + 5 : k + 5 + length]
            for s in touched:
                if s.id == target or s.secondary_id == target:
                    self._write(s, address, data)
            k += 5 + length

    def _write(self, servo: VirtualServo, address: int, data: bytes) -> int:
        err, written = servo.write(address, data)
        if written & {"goal_position", "goal_pwm", "torque_enable", "operating_mode", "profile_velocity"}:
            self._goal_dirty = True
        if "torque_enable" in written and servo.torque_on:
            # torque on: hold where the servo's goal is (the host sets it to the present position first)
            self._goal_dirty = True
        return err

    # ------------------------------------------------------------------------------------------ faults

    def set_hardware_error(self, servo_id: int, bits: int) -> None:
        """Set Hardware_Error_Status bits of a servo (0 clears them); torque goes off where Shutdown says.

        Raises:
            ConfigError: no such servo, or bits that are not a byte.
        """
        servo = self.servos.get(servo_id)
        if servo is None:
            raise ConfigError(f"no servo ID {servo_id} on this bus; IDs: {sorted(self.servos)}")
        if not 0 <= bits <= 0xFF:
            raise ConfigError(f"hardware error bits: expected 0..255, got {bits}")
        servo.put("hardware_error_status", bits)
        if bits & servo.get("shutdown"):
            servo.put("torque_enable", 0)
            self._goal_dirty = True
        self.on_event(f"hardware_error id={servo_id} bits=0x{bits:02x}")

    # ------------------------------------------------------------------------------------------ the sim

    def _command(self) -> JointCommand:
        q = self.sim.qpos
        target = self.sim.target
        goals = []
        for i, joint in enumerate(self._arm):
            servo = self.servos[self.map.primary(joint).id]
            if not servo.torque_on or servo.watchdog_tripped:
                goals.append(float(target[i]) if servo.torque_on else float(q[i]))
            else:
                goals.append(ticks_to_rad(servo.get("goal_position") - servo.get("homing_offset")))
        lo, hi = self.sim.lower, self.sim.upper
        position = list(np.clip(goals, lo, hi))
        arm = self.servos[self.map.primary(self._arm[0]).id]
        duration_s = 0.0
        if arm.get("drive_mode") & DRIVE_MODE_TIME_PROFILE and arm.get("profile_velocity") > 0:
            duration_s = arm.get("profile_velocity") / 1000.0
        gripper = self._gripper_goal()
        if gripper is not None:
            position.append(gripper)
        return JointCommand(
            header=Header(stamp_ns=self.sim.time_ns), position=np.asarray(position), duration_s=duration_s
        )

    def _gripper_goal(self) -> float | None:
        if self.robot.gripper_actuator is None or len(self.map.groups) < 2:
            return None
        joint = self.map.groups[1].joints[0]
        servo = self.servos[self.map.primary(joint).id]
        if joint not in self._index:
            return None
        if self._gripper_finger is None:
            self._gripper_finger = _horn_to_finger(float(self.sim.data.qpos[self.sim._qadr[self._index[joint]]]))
        if not servo.torque_on or servo.watchdog_tripped:
            return self._gripper_finger
        mode = servo.get("operating_mode")
        if mode == OPERATING_MODES["pwm"]:
            pwm = servo.get("goal_pwm")
            if pwm != 0:
                self._gripper_finger = _FINGER_RANGE[1] if pwm > 0 else _FINGER_RANGE[0]
        elif mode in (OPERATING_MODES["position"], OPERATING_MODES["extended_position"]):
            self._gripper_finger = _horn_to_finger(
                ticks_to_rad(servo.get("goal_position") - servo.get("homing_offset"))
            )
        return self._gripper_finger

    def advance(self, now_s: float, *, watchdogs: bool = True) -> None:
        """Step the sim to the wall-clock time ``now_s``, apply new goals, trip watchdogs (unless told not to, when
        an instruction has just come), update Present_*."""
        if self._t0_s is None:
            self._t0_s = now_s
        if watchdogs:
            self._check_watchdogs(now_s)
        due = int((now_s - self._t0_s) / SIM_STEP_S)
        if due - self._steps > 10:  # more than 100 ms behind (a stalled process): skip, do not race
            self._steps = due - 1
        while self._steps < due:
            cmd = self._command() if self._goal_dirty else None
            self._goal_dirty = False
            self.sim.tick(cmd)
            self._steps += 1
        self._update_present()

    def next_due_s(self) -> float:
        """When the sim's next step is due (wall clock), for the server's wait."""
        t0 = self._t0_s if self._t0_s is not None else 0.0
        return t0 + (self._steps + 1) * SIM_STEP_S

    def next_watchdog_s(self) -> float:
        """When the first armed Bus Watchdog runs out (wall clock), or infinity, for the server's wait."""
        due = math.inf
        for s in self.servos.values():
            limit = s.watchdog_s()
            if limit and s.torque_on and not s.watchdog_tripped and s.last_instruction_s is not None:
                due = min(due, s.last_instruction_s + limit)
        return due

    def _check_watchdogs(self, now_s: float) -> None:
        for s in self.servos.values():
            limit = s.watchdog_s()
            if not limit or not s.torque_on or s.watchdog_tripped or s.last_instruction_s is None:
                continue
            silent = now_s - s.last_instruction_s
            if silent > limit:
                s.watchdog_tripped = True
                s.put("bus_watchdog", -1)
                s.put("goal_position", s.get("present_position"))
                self._goal_dirty = True
                self.on_event(f"watchdog id={s.id} silent_ms={silent * 1e3:.1f} t={now_s:.6f}")

    def _update_present(self) -> None:
        state = self.sim.joint_state()
        if self.emulation is not None and (self.emulation.position_noise_std or self.emulation.velocity_noise_std):
            state = add_sensor_noise(state, self.emulation, self._rng)
        pos, vel, eff = state.position, state.velocity, state.effort
        tick_ms = int(self.sim.time_ns // 1_000_000) % 32768
        for s in self.servos.values():
            joint = s.config.joint
            i = self._index.get(joint)
            if i is None:
                continue
            q, v, tau = float(pos[i]), float(vel[i]), float(eff[i])
            if s.config.is_shadow or any(o.config.secondary_id == s.config.id for o in self.servos.values()):
                tau /= 2.0  # the pair shares the joint's torque
            s.put("present_position", rad_to_ticks(q) + s.get("homing_offset"))
            s.put("present_velocity", round(v / VELOCITY_UNIT_RAD_S))
            model = s.config.model
            if "present_current" in s.table:
                s.put("present_current", round(tau / TORQUE_CONSTANT_NM_A.get(model, 1.0) / CURRENT_UNIT_A))
            elif "present_load" in s.table:
                s.put("present_load", round(tau / STALL_TORQUE_NM.get(model, 1.0) * 1000.0))
            s.put("moving", int(abs(v) > 0.02))
            s.put("realtime_tick", tick_ms)
            if i < len(self._arm):
                s.put("position_trajectory", rad_to_ticks(float(self.sim.target[i])) + s.get("homing_offset"))


def _u16(data: bytes, at: int) -> int:
    return data[at] | (data[at + 1] << 8)
