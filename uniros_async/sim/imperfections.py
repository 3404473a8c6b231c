"""Servo-level imperfections of a real arm as knobs with a strength: 0 is the sim, 1 a real arm, up to 3.

One knob per effect. Strength 1 is the best estimate of a real Dynamixel arm from public specs (the figures and
their sources: docs/robot-facts.md, "Imperfections at strength 1"); a strength scales the effect as the table says.

==============  =====================================================  ===========================================
knob            what it does at strength s                             strength 1
==============  =====================================================  ===========================================
backlash        a play of width s * b between the servo setpoint and   b = 0.25 deg (15 arcmin, ROBOTIS X-series)
                the joint: the joint settles b/2 short of a target
                on the side it came from (a hysteresis of width b)
offsets         a per-joint calibration offset U(-s o, s o) on the     o = 0.5 deg (estimate)
                encoder: the servo reaches goal - offset and reports
                the true angle + offset
quantization    goal and present position in steps of s * 2 pi/4096;   4096 ticks/turn, 1 tick of deadband,
                present velocity in steps of s * 0.229 rev/min; the    0.229 rev/min velocity unit
                setpoint moves only when the goal differs from it by
                more than s ticks (the deadband)
sag             arm servo kp x (kp_real / kp_sim) ** s, so a P         kp_real from the firmware P gain and stall
                controller's steady-state error under load grows       torque (rx200: ~0.2 of the sim's kp)
limits          velocity limits x 0.72 ** s, force ranges x 0.93 ** s  the torque-speed line at the worst gravity
                                                                       load; stall torque at 11.1 V vs 12 V
latency         command delay s * (1.5 ms + U(+-1 ms)), state delay    1 Mbps bus transfer + 1 ms USB frames
                s * (2.5 ms + U(+-1 ms)), FIFO
lost_states     a joint state is lost with p = s * 1 %, and with       estimate (no public figure)
                p = s * 1 % the previous state is sent again (a
                driver keeps its last values when a read fails)
noise           N(0, s * 1 tick) on positions, N(0, s * 1 velocity     one unit of each register
                unit) on velocities
dynamics        EmulationConfig's mass, damping, friction and gain     +-10 %, +-30 %, +-30 %, +-15 %
                ranges x s (capped at 0.9)
==============  =====================================================  ===========================================

``Randomization`` draws the strengths afresh for every episode. An env with ``randomize`` has its servo sim draw
the next episode at every reset (the sim node's ``new_episode`` service, ``uniros_async.envs.randomize``) from a
seed of its own ``np_random``, so the draws follow the env's reset seed, and reports the draw in the reset's
``info``: ``info["imperfections"]`` (knob -> strength) and ``info["imperfections_seed"]`` (with the strengths,
``Imperfections(strengths=..., seed=...)`` rebuilds the episode's arm).

``Imperfections.of(1.0)`` sets every knob to 1; ``Imperfections.of({"backlash": 2.0})`` one knob (the others 0).
``emulation()`` gives the EmulationConfig of the bus-side knobs (latency, lost_states, noise, dynamics) and
``servo_effects(sim)`` the ServoEffects of the servo-side ones (backlash, offsets, quantization, sag, limits),
which a ServoSim applies to every setpoint and every state it reads.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from uniros_async.errors import ConfigError
from uniros_async.sim.emulated import EmulationConfig, LatencyModel

if TYPE_CHECKING:
    import mujoco

    from uniros_async.robots import RobotSpec

__all__ = ["KNOBS", "MAX_STRENGTH", "Imperfections", "Randomization", "ServoEffects", "real_kp"]

KNOBS = (
    "backlash",
    "offsets",
    "quantization",
    "sag",
    "limits",
    "latency",
    "lost_states",
    "noise",
    "dynamics",
)
SERVO_KNOBS = ("backlash", "offsets", "quantization", "sag", "limits")
MAX_STRENGTH = 3.0

TICK_RAD = 2.0 * math.pi / 4096.0
VELOCITY_UNIT_RAD_S = 0.229 * 2.0 * math.pi / 60.0
BACKLASH_RAD = math.radians(0.25)
OFFSET_RAD = math.radians(0.5)
DEADBAND_TICKS = 1.0
LIMITS_VELOCITY_FACTOR = 0.72
LIMITS_FORCE_FACTOR = 0.93
COMMAND_LATENCY_S = (0.0015, 0.001)
STATE_LATENCY_S = (0.0025, 0.001)
LOST_STATE_P = 0.01
REPEATED_STATE_P = 0.01
DYNAMICS = {"mass_scale": 0.10, "damping_scale": 0.30, "friction_scale": 0.30, "kp_scale": 0.15}
SAG_FALLBACK_RATIO = 0.25
PWM_LIMIT = 885.0


def real_kp(stall_torque_nm: float, position_p_gain: float) -> float:
    """The stiffness (N m/rad) of a Dynamixel X position loop with P gain only.

    The firmware's PWM output is ``P / 128`` per tick of error and 885 is full PWM, at which the servo gives
    its stall torque: kp = stall * (P / 128) / 885 * 4096 / (2 pi).
    """
    return stall_torque_nm * (position_p_gain / 128.0) / PWM_LIMIT / TICK_RAD


# per robot: each arm joint's real stiffness (N m/rad), or None where the actuator is not a P-only Dynamixel
_XM430 = real_kp(4.1, 800.0)
_XL430 = real_kp(1.4, 640.0)
REAL_KP: dict[str, tuple[float | None, ...]] = {
    "rx200": (_XL430, 2.0 * _XM430, _XM430, _XL430, _XL430),
    "ned2": (None, None, None, _XL430, _XL430, None),
}


def _check_strength(name: str, s: Any) -> float:
    if isinstance(s, bool) or not isinstance(s, int | float) or not math.isfinite(s) or not 0.0 <= s <= MAX_STRENGTH:
        raise ConfigError(f"imperfections.{name}: expected a strength in [0, {MAX_STRENGTH}], got {s!r}")
    return float(s)


@dataclass(frozen=True, kw_only=True)
class Imperfections:
    """The strength of every knob (``KNOBS``), and the seed of every draw.

    Attributes:
        strengths: knob name -> strength in [0, 3]; a knob not named has strength 0.
        seed: seeds the per-joint offsets and the bus-side draws.
    """

    strengths: Mapping[str, float] = field(default_factory=dict)
    seed: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.strengths, Mapping):
            raise ConfigError(f"imperfections: expected a mapping of knob -> strength, got {self.strengths!r}")
        unknown = sorted(set(self.strengths) - set(KNOBS))
        if unknown:
            raise ConfigError(f"imperfections: unknown knob(s) {unknown}; expected some of {list(KNOBS)}")
        checked = {k: _check_strength(k, v) for k, v in self.strengths.items()}
        object.__setattr__(self, "strengths", {k: checked.get(k, 0.0) for k in KNOBS})

    @classmethod
    def of(cls, strength: float | Mapping[str, float], seed: int = 0) -> Imperfections:
        """All knobs at one ``strength``, or a per-knob dict (knobs not named: 0).

        Raises:
            ConfigError: an unknown knob or a strength outside [0, 3].
        """
        if isinstance(strength, Mapping):
            return cls(strengths=dict(strength), seed=seed)
        s = _check_strength("strength", strength)
        return cls(strengths=dict.fromkeys(KNOBS, s), seed=seed)

    def __getitem__(self, knob: str) -> float:
        return self.strengths[knob]

    @property
    def is_zero(self) -> bool:
        """Every knob at 0: the sim."""
        return not any(self.strengths.values())

    def emulation(self) -> EmulationConfig:
        """The EmulationConfig of the bus-side knobs (latency, lost_states, noise, dynamics)."""
        s_lat, s_lost, s_noise, s_dyn = (self[k] for k in ("latency", "lost_states", "noise", "dynamics"))
        loss = min(0.9, s_lost * LOST_STATE_P)

        def line(base_jitter: tuple[float, float], p: float) -> LatencyModel:
            base, jitter = base_jitter
            return LatencyModel(base_s=s_lat * base, jitter_s=s_lat * jitter, distribution="uniform", loss=p)

        return EmulationConfig(
            seed=self.seed,
            **{k: min(0.9, s_dyn * v) for k, v in DYNAMICS.items()},
            position_noise_std=s_noise * TICK_RAD,
            velocity_noise_std=s_noise * VELOCITY_UNIT_RAD_S,
            state_latency=line(STATE_LATENCY_S, loss),
            command_latency=line(COMMAND_LATENCY_S, 0.0),
            state_repeat=min(0.9, s_lost * REPEATED_STATE_P),
        )

    def servo_effects(self, robot: RobotSpec) -> ServoEffects | None:
        """The ServoEffects of the servo-side knobs for ``robot``, or None when they are all 0."""
        if not any(self[k] for k in SERVO_KNOBS):
            return None
        return ServoEffects(self, robot)

    def as_dict(self) -> dict[str, Any]:
        """The strengths and seed, for ``info`` and logs."""
        return {"strengths": dict(self.strengths), "seed": self.seed}


class ServoEffects:
    """The servo-side knobs of one arm, applied by a ServoSim (see the module docstring).

    ``setpoint`` maps the servo targets (the goal the host commanded, along the servo's profile) to the position
    setpoints of the MuJoCo actuators; ``measure`` maps the joints' true positions and velocities to what the
    servo reports; ``perturb`` changes the model (sag, force limits) and ``velocity_factor`` the velocity limits.
    """

    def __init__(self, imperfections: Imperfections, robot: RobotSpec) -> None:
        n = robot.n_arm_joints
        self.n = n
        self.imperfections = imperfections
        s = imperfections.strengths
        rng = np.random.default_rng([imperfections.seed, 41])
        self.backlash_rad = s["backlash"] * BACKLASH_RAD
        self.offsets = rng.uniform(-1.0, 1.0, size=n) * s["offsets"] * OFFSET_RAD
        self.step_rad = s["quantization"] * TICK_RAD
        self.velocity_step = s["quantization"] * VELOCITY_UNIT_RAD_S
        self.deadband_rad = s["quantization"] * DEADBAND_TICKS * TICK_RAD
        self.s_sag = s["sag"]
        self.s_limits = s["limits"]
        self.velocity_factor = LIMITS_VELOCITY_FACTOR ** s["limits"]
        self.robot = robot
        self._register: np.ndarray | None = None
        self._play: np.ndarray | None = None
        self.sag_factors = np.ones(n)

    def perturb(self, model: mujoco.MjModel, actuator_ids: np.ndarray) -> None:
        """Soften the arm servos' kp (sag) and lower their force ranges (limits), in place."""
        reals = REAL_KP.get(self.robot.name)
        for j, i in enumerate(actuator_ids):
            kp = float(model.actuator_gainprm[i, 0])
            real = reals[j] if reals is not None and j < len(reals) else None
            if reals is None:
                ratio = SAG_FALLBACK_RATIO
            else:
                ratio = 1.0 if real is None or kp <= 0.0 else min(1.0, real / kp)
            f = ratio**self.s_sag
            self.sag_factors[j] = f
            model.actuator_gainprm[i, 0] *= f
            model.actuator_biasprm[i, 1] *= f
            model.actuator_biasprm[i, 2] *= math.sqrt(f)
            if self.s_limits:
                model.actuator_forcerange[i] *= LIMITS_FORCE_FACTOR**self.s_limits
                model.actuator_forcelimited[i] = 1

    def reset(self, q: np.ndarray) -> None:
        """Start over at rest at ``q`` (the servo targets): the play sits centred, the register holds ``q``."""
        self._register = None
        self._play = None
        self.setpoint(q)

    def setpoint(self, target: np.ndarray) -> np.ndarray:
        """The actuator setpoint for the servo target ``target`` (quantized, deadband, offset, backlash)."""
        goal = target
        if self.step_rad:
            goal = np.round(goal / self.step_rad) * self.step_rad
        if self.deadband_rad and self._register is not None:
            moved = np.abs(goal - self._register) > self.deadband_rad * (1.0 + 1e-9)
            goal = np.where(moved, goal, self._register)
        self._register = goal
        x = goal - self.offsets
        if self.backlash_rad:
            half = self.backlash_rad / 2.0
            self._play = x.copy() if self._play is None else np.clip(self._play, x - half, x + half)
            return self._play
        return x

    def measure(self, position: np.ndarray, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What the servos report for the arm joints' true ``position`` and ``velocity``."""
        pos = position + self.offsets
        vel = velocity
        if self.step_rad:
            pos = np.round(pos / self.step_rad) * self.step_rad
            vel = np.round(vel / self.velocity_step) * self.velocity_step
        return pos, vel

    def drawn(self) -> dict[str, Any]:
        """The drawn and derived values, for ``info`` and logs."""
        return {
            "backlash_rad": self.backlash_rad,
            "offsets_rad": self.offsets.tolist(),
            "step_rad": self.step_rad,
            "deadband_rad": self.deadband_rad,
            "sag_kp_factors": self.sag_factors.tolist(),
            "velocity_factor": self.velocity_factor,
            "force_factor": LIMITS_FORCE_FACTOR**self.s_limits,
        }


@dataclass(frozen=True, kw_only=True)
class Randomization:
    """A range of strengths per knob, drawn afresh for every episode (``draw``), seeded.

    Attributes:
        ranges: knob name -> (low, high), both in [0, 3], low <= high; a knob not named stays at 0.
        seed: seeds the draws (episode after episode, the same sequence).
    """

    ranges: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    seed: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.ranges, Mapping) or not self.ranges:
            raise ConfigError(f"randomize: expected a mapping of knob -> [low, high], got {self.ranges!r}")
        unknown = sorted(set(self.ranges) - set(KNOBS))
        if unknown:
            raise ConfigError(f"randomize: unknown knob(s) {unknown}; expected some of {list(KNOBS)}")
        out: dict[str, tuple[float, float]] = {}
        for k, r in self.ranges.items():
            if isinstance(r, str) or not hasattr(r, "__len__") or len(r) != 2:
                raise ConfigError(f"randomize.{k}: expected [low, high], got {r!r}")
            lo, hi = _check_strength(k, r[0]), _check_strength(k, r[1])
            if lo > hi:
                raise ConfigError(f"randomize.{k}: expected low <= high, got [{lo}, {hi}]")
            out[k] = (lo, hi)
        object.__setattr__(self, "ranges", out)

    def draw(self, rng: np.random.Generator) -> Imperfections:
        """One episode's strengths, each U(low, high); the Imperfections' own seed is drawn too."""
        strengths = {k: float(rng.uniform(lo, hi)) for k, (lo, hi) in self.ranges.items()}
        return Imperfections(strengths=strengths, seed=int(rng.integers(2**31)))
