"""ServoSim: a MuJoCo arm behind a synchronous servo core that behaves like the arm's hardware control loop.

One ``tick(cmd)`` is one cycle of the robot's hardware loop (rx200 10 Hz, ned2 25 Hz), in the order of
ros_control's ``read(); update(); write()``:

1. physics steps one hardware period (``control_period_s / physics_dt_s`` substeps of ``physics_dt_s``) under the servo
   targets set at the previous tick, so the state returned by a tick is the state *at* that tick;
2. the joint state (positions, velocities, efforts of ``RobotSpec.joint_state_names``) is read;
3. the newest command is applied: there is no buffering, the caller passes the newest JointCommand it has (a
   newer command overwrites an older one, as on ros_control) or None when nothing new arrived.

Commands are checked before they act: a non-finite value or a wrong length is rejected (counted in
``stats.rejected``, logged, ``stats.last_error`` says why) and the arm keeps its current goal; positions outside
the joint limits are clipped to them (counted in ``stats.clipped``): a servo target past a limit is never set.

Servo profiles (``RobotSpec.servo_profile``), evaluated every physics substep:

* ``duration_s > 0``: a Dynamixel time-based profile: every joint moves from the current servo target to the
  goal in ``duration_s``, synchronised, with a trapezoid velocity whose acceleration time is the profile's
  ``accel_time_s`` (at most half the duration); the duration is stretched when a joint would exceed its
  velocity limit. Re-sending the same goal (an env's action repeat) does not restart the profile.
* ``duration_s == 0`` and a ``"time"`` profile (rx200): the target steps straight to the goal, limited only by
  the joint velocity limits.
* ``duration_s == 0`` and a ``"velocity"`` profile (ned2): an online trapezoid: the target follows the goal
  with the profile's per-joint velocity and acceleration bounds, keeping its velocity when a new goal arrives.

Controller modes: ``"position"`` (default), ``"velocity"`` (``JointCommand.velocity`` integrated into the target,
clipped to the limits), ``"hold"`` (the servos hold the position the arm had when switched; commands are
ignored and counted) and ``"stop"`` (the motion is braked at ``stop_deceleration_rad_s2`` and then held;
commands are ignored). ``set_mode("position")`` or ``reset()`` resume. A watchdog holds the arm where it is when
no new command arrived for ``command_timeout_s`` after the last command's motion ended (``stats.watchdog_holds``).

Divergence (NaN/inf or absurd joint velocities, or MuJoCo's bad-qpos/qvel/qacc warnings, after which MuJoCo
silently resets the state) raises SimulationError; the sim then refuses to tick until ``reset()``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, cast

import mujoco
import numpy as np
from numpy.typing import ArrayLike

from uniros_async.bus.messages import Header, JointCommand, JointState
from uniros_async.errors import ConfigError, SimulationError
from uniros_async.robots import RobotSpec, get_robot_spec
from uniros_async.sim.profiles import AccelLimited, Brake, Constant, Integrate, Profile, TimeSegment, VelocityLimited

if TYPE_CHECKING:
    from uniros_async.sim.imperfections import ServoEffects

__all__ = ["MODES", "ServoSim", "ServoSimConfig", "ServoStats", "load_model"]

logger = logging.getLogger(__name__)

MODES = ("position", "velocity", "hold", "stop")

_DIVERGENCE_WARNINGS = (
    mujoco.mjtWarning.mjWARN_BADQPOS,
    mujoco.mjtWarning.mjWARN_BADQVEL,
    mujoco.mjtWarning.mjWARN_BADQACC,
)
_WARN_IDX = np.array([int(w) for w in _DIVERGENCE_WARNINGS])
# the model fields that emulation and imperfections change (ServoSim.set_effects restores them)
_PERTURBED = (
    "body_mass",
    "body_inertia",
    "dof_damping",
    "dof_frictionloss",
    "actuator_gainprm",
    "actuator_biasprm",
    "actuator_forcerange",
    "actuator_forcelimited",
)


@dataclass(frozen=True, kw_only=True)
class ServoSimConfig:
    """Settings of a ServoSim.

    Attributes:
        physics_dt_s: MuJoCo time step (overrides the MJCF's ``timestep``).
        control_period_s: hardware loop period; None: the robot's (``RobotSpec.hardware_period_s``). Must be a
            whole number of physics steps.
        command_timeout_s: watchdog: hold the arm when no new command came for this long after the last
            command's motion ended; None disables it.
        mode: the controller mode at start and after ``reset()``; one of ``MODES``.
        stop_deceleration_rad_s2: how hard ``"stop"`` brakes the servo targets.
        max_abs_qvel: a joint velocity above this (rad/s or m/s) is treated as divergence.
        initial_q_rad: arm pose at start and after ``reset()`` without a pose; None: ``RobotSpec.home_q_rad``.
        target_update_steps: physics steps between servo target updates along a profile (5 at the default
            ``physics_dt_s``: a 100 Hz setpoint, far above the servos' bandwidth, and cheaper than updating every
            step, since a tick is mostly MuJoCo steps). Must divide the steps per period.
    """

    physics_dt_s: float = 0.002
    control_period_s: float | None = None
    command_timeout_s: float | None = 1.0
    mode: str = "position"
    stop_deceleration_rad_s2: float = 10.0
    max_abs_qvel: float = 1000.0
    initial_q_rad: tuple[float, ...] | None = None
    target_update_steps: int = 5

    def __post_init__(self) -> None:
        if not (math.isfinite(self.physics_dt_s) and self.physics_dt_s > 0.0):
            raise ConfigError(f"ServoSimConfig.physics_dt_s: expected a finite value > 0, got {self.physics_dt_s}")
        if self.control_period_s is not None:
            if not (math.isfinite(self.control_period_s) and self.control_period_s >= self.physics_dt_s):
                raise ConfigError(
                    f"ServoSimConfig.control_period_s: expected a finite value >= physics_dt_s={self.physics_dt_s}, "
                    f"got {self.control_period_s}"
                )
            _substeps(self.control_period_s, self.physics_dt_s, "ServoSimConfig.control_period_s")
        if self.command_timeout_s is not None and not self.command_timeout_s > 0.0:
            raise ConfigError(
                f"ServoSimConfig.command_timeout_s: expected a value > 0 or None, got {self.command_timeout_s}"
            )
        if self.mode not in MODES:
            raise ConfigError(f"ServoSimConfig.mode: expected one of {MODES}, got {self.mode!r}")
        if not self.stop_deceleration_rad_s2 > 0.0:
            raise ConfigError(
                f"ServoSimConfig.stop_deceleration_rad_s2: expected a value > 0, got {self.stop_deceleration_rad_s2}"
            )
        if not self.max_abs_qvel > 0.0:
            raise ConfigError(f"ServoSimConfig.max_abs_qvel: expected a value > 0, got {self.max_abs_qvel}")
        if not (isinstance(self.target_update_steps, int) and self.target_update_steps >= 1):
            raise ConfigError(
                f"ServoSimConfig.target_update_steps: expected an int >= 1, got {self.target_update_steps!r}"
            )
        if self.initial_q_rad is not None:
            object.__setattr__(self, "initial_q_rad", tuple(float(x) for x in self.initial_q_rad))


def _substeps(period_s: float, dt_s: float, where: str) -> int:
    n = round(period_s / dt_s)
    if n < 1 or abs(n * dt_s - period_s) > 1e-9 * max(1.0, period_s):
        raise ConfigError(f"{where}: expected a whole multiple of physics_dt_s={dt_s}, got {period_s}")
    return n


@dataclass
class ServoStats:
    """Counters of a ServoSim (they only grow, except through ``reset_stats``)."""

    ticks: int = 0
    commands: int = 0
    """New commands that were accepted."""
    clipped: int = 0
    """Accepted commands with at least one value clipped to a joint limit."""
    clipped_values: int = 0
    """Single values clipped (positions and velocities)."""
    rejected: int = 0
    """Commands refused (NaN/inf, wrong length, no velocity in velocity mode)."""
    ignored: int = 0
    """Commands that arrived in ``"hold"`` or ``"stop"`` mode."""
    watchdog_holds: int = 0
    resets: int = 0
    last_error: str = ""


def load_model(robot: RobotSpec, physics_dt_s: float = 0.002) -> mujoco.MjModel:
    """Load the robot's MJCF with the time step set to ``physics_dt_s``.

    Raises:
        ConfigError: the model file cannot be loaded (MuJoCo's message is included).
    """
    try:
        model = mujoco.MjModel.from_xml_path(str(robot.mjcf_path))
    except (ValueError, OSError) as exc:
        raise ConfigError(f"cannot load the MJCF of {robot.name} from {robot.mjcf_path}: {exc}") from exc
    model.opt.timestep = physics_dt_s
    return model


# ----------------------------------------------------------------------------------------------- the sim


class ServoSim:
    """A robot arm in MuJoCo driven like its hardware loop; synchronous, no asyncio (see the module docstring).

    Args:
        robot: a RobotSpec or a registered robot name (``"rx200"``, ``"ned2"``).
        config: servo settings; defaults to ``ServoSimConfig()``.
        model: an already-loaded (e.g. perturbed) MjModel of this robot; default: load ``robot.mjcf_path``.
        effects: servo-level imperfections (``uniros_async.sim.imperfections``): they change the model's gains and
            force ranges and the velocity limits here, and every setpoint and arm joint reading; None: none.

    Raises:
        ConfigError: bad config, unknown robot, or a model that lacks the robot's joints or actuators.
    """

    def __init__(
        self,
        robot: RobotSpec | str,
        config: ServoSimConfig | None = None,
        *,
        model: mujoco.MjModel | None = None,
        effects: ServoEffects | None = None,
    ) -> None:
        self.robot = get_robot_spec(robot) if isinstance(robot, str) else robot
        self.config = config or ServoSimConfig()
        cfg, spec = self.config, self.robot
        self.model = model if model is not None else load_model(spec, cfg.physics_dt_s)
        self.model.opt.timestep = cfg.physics_dt_s
        self.data = mujoco.MjData(self.model)
        m = self.model
        period_s = cfg.control_period_s if cfg.control_period_s is not None else spec.hardware_period_s
        self.n_substeps = _substeps(period_s, cfg.physics_dt_s, f"{spec.name} control period")
        self._chunk = cfg.target_update_steps
        if self.n_substeps % self._chunk:
            raise ConfigError(
                f"ServoSimConfig.target_update_steps={self._chunk} must divide the {self.n_substeps} physics steps "
                f"of a {spec.name} control period"
            )
        self.dt_ns = round(cfg.physics_dt_s * 1e9)
        self.period_ns = self.n_substeps * self.dt_ns
        self.n_joints = spec.n_arm_joints
        try:
            self._act_ids = np.array([m.actuator(name).id for name in spec.arm_joint_names])
            jids = [m.joint(name).id for name in spec.joint_state_names]
            self._gripper_act = m.actuator(spec.gripper_actuator).id if spec.gripper_actuator else None
            self._ee_site = m.site(spec.ee_site).id
        except KeyError as exc:
            raise ConfigError(f"the MJCF of {spec.name} lacks a joint, actuator or site the spec names: {exc}") from exc
        self._qadr = np.array([m.jnt_qposadr[j] for j in jids])
        self._vadr = np.array([m.jnt_dofadr[j] for j in jids])
        self._arm_qadr, self._arm_vadr = self._qadr[: self.n_joints], self._vadr[: self.n_joints]
        self._contiguous_acts = bool(np.array_equal(self._act_ids, np.arange(self.n_joints)))
        self.lower = np.asarray(spec.joint_lower_rad, dtype=np.float64)
        self.upper = np.asarray(spec.joint_upper_rad, dtype=np.float64)
        # never command past what the model's actuators accept either
        ctrl_lo, ctrl_hi = m.actuator_ctrlrange[self._act_ids, 0], m.actuator_ctrlrange[self._act_ids, 1]
        limited = m.actuator_ctrllimited[self._act_ids].astype(bool)
        self.lower = np.where(limited, np.maximum(self.lower, ctrl_lo), self.lower)
        self.upper = np.where(limited, np.minimum(self.upper, ctrl_hi), self.upper)
        self.vmax = np.asarray(spec.velocity_limits_rad_s, dtype=np.float64)
        self._vmax0 = self.vmax.copy()
        self._nominal = {name: getattr(m, name).copy() for name in _PERTURBED}
        self.effects = effects
        if effects is not None:
            effects.perturb(m, self._act_ids)
            mujoco.mj_setConst(m, self.data)
            self.vmax = self.vmax * effects.velocity_factor
        prof = spec.servo_profile
        self._profile_kind = prof.kind
        self._accel_time_s = prof.accel_time_s
        if prof.kind == "velocity":
            self._prof_vmax = np.minimum(np.asarray(prof.max_velocity_rad_s), self.vmax)
            self._prof_amax = np.asarray(prof.max_acceleration_rad_s2, dtype=np.float64)
        if self._gripper_act is not None:
            self._gripper_range = m.actuator_ctrlrange[self._gripper_act].copy()
        self._names = tuple(spec.joint_state_names)
        self._home_key = next((k for k in range(m.nkey) if m.key(k).name == "home"), None)
        self.stats = ServoStats()
        self.initial_q = np.asarray(
            cfg.initial_q_rad if cfg.initial_q_rad is not None else spec.home_q_rad, dtype=np.float64
        )
        self._check_pose(self.initial_q, "initial_q_rad")
        self._warn_counts = np.zeros(len(_DIVERGENCE_WARNINGS), dtype=np.int64)
        self._steps = 0
        self._diverged: str | None = None
        self._profile: Profile = Constant(self.initial_q)
        self._goal = self.initial_q.copy()
        self._goal_duration_s = 0.0
        self._mode: str = cfg.mode
        self._last_cmd_ns: int | None = None
        self._last_cmd_duration_ns = 0
        self._episode_ticks = 0
        self.reset()
        self.stats.resets = 0

    def set_effects(
        self, effects: ServoEffects | None, perturb: Callable[[mujoco.MjModel], object] | None = None
    ) -> None:
        """Start the model over from the one this sim was built with, ``perturb`` it (e.g. ``perturb_model``),
        then apply ``effects`` (None: none); for a new episode, before ``reset``."""
        m = self.model
        for name, nominal in self._nominal.items():
            getattr(m, name)[:] = nominal
        if perturb is not None:
            perturb(m)
        self.effects = effects
        if effects is not None:
            effects.perturb(m, self._act_ids)
        mujoco.mj_setConst(m, self.data)
        self.vmax = self._vmax0 * (1.0 if effects is None else effects.velocity_factor)
        if self._profile_kind == "velocity":
            self._prof_vmax = np.minimum(np.asarray(self.robot.servo_profile.max_velocity_rad_s), self.vmax)

    # ---- state

    @property
    def time_ns(self) -> int:
        """Simulated time since the last reset, in ns (an exact multiple of the physics step)."""
        return self._steps * self.dt_ns

    @property
    def mode(self) -> str:
        """The controller mode, one of ``MODES``."""
        return self._mode

    @property
    def target(self) -> np.ndarray:
        """The current servo targets of the arm joints (a copy)."""
        return self._profile.pos.copy()

    @property
    def goal(self) -> np.ndarray:
        """Where the servos are heading (a copy): the last accepted goal, or the held position."""
        return self._goal.copy()

    @property
    def qpos(self) -> np.ndarray:
        """Arm joint positions now (a copy)."""
        return cast(np.ndarray, self.data.qpos[self._arm_qadr].copy())

    def ee_position(self) -> np.ndarray:
        """World position of the end-effector site (m), as of the last physics step."""
        return cast(np.ndarray, self.data.site_xpos[self._ee_site].copy())

    def joint_state(
        self,
        stamp_ns: int | None = None,
        seq: int | None = None,
        *,
        echo: tuple[int | None, int | None] = (None, None),
    ) -> JointState:
        """The joint state now, for ``RobotSpec.joint_state_names``; stamped with sim time unless told. ``echo``:
        its ``command_stamp_ns`` and ``command_age_ns`` (the round-trip echo, ``ServoSimNode``)."""
        d = self.data
        position, velocity = d.qpos[self._qadr], d.qvel[self._vadr]
        if self.effects is not None:
            n = self.n_joints
            position[:n], velocity[:n] = self.effects.measure(position[:n], velocity[:n])
        return JointState(
            header=Header(
                stamp_ns=self.time_ns if stamp_ns is None else stamp_ns, seq=self.stats.ticks if seq is None else seq
            ),
            name=self._names,
            position=position,
            velocity=velocity,
            effort=d.qfrc_actuator[self._vadr],
            command_stamp_ns=echo[0],
            command_age_ns=echo[1],
        )

    # ---- the hardware loop

    def tick(
        self,
        cmd: JointCommand | None = None,
        *,
        stamp_ns: int | None = None,
        echo: tuple[int | None, int | None] = (None, None),
    ) -> JointState:
        """One hardware cycle: step physics one period, read the state, apply ``cmd`` (the newest, or None).

        Args:
            cmd: the newest command if a new one arrived since the last tick, else None.
            stamp_ns: stamp of the returned state; default: the sim time.
            echo: the returned state's ``command_stamp_ns`` and ``command_age_ns`` (see ``JointState``).

        Returns:
            The joint state at this tick (before ``cmd`` acts).

        Raises:
            SimulationError: physics diverged during this period (or earlier, without a reset since).
        """
        if self._diverged is not None:
            raise SimulationError(f"{self.robot.name}: the simulation diverged earlier ({self._diverged}); reset() it")
        if self._episode_ticks > 0:
            self._step_period()
        self._episode_ticks += 1
        state = self.joint_state(stamp_ns, echo=echo)
        self.stats.ticks += 1
        if cmd is not None:
            self.apply(cmd)
        elif self._watchdog_due():
            self.stats.watchdog_holds += 1
            logger.info("%s: no command for %.3f s: holding position", self.robot.name, self.config.command_timeout_s)
            self._hold_here()
            self._last_cmd_ns = None
        return state

    def apply(self, cmd: JointCommand) -> bool:
        """Apply a command now (``tick`` calls this); returns whether it was accepted."""
        if self._mode in ("hold", "stop"):
            self.stats.ignored += 1
            return False
        n = self.n_joints
        pos = np.asarray(cmd.position, dtype=np.float64)
        extra = 1 if self._gripper_act is not None else 0
        if pos.shape not in ((n,), (n + extra,)):
            expected = f"{n}" + (f" or {n + 1} (with the gripper)" if extra else "")
            names = self.robot.arm_joint_names
            return self._reject(f"expected {expected} positions for {names}, got shape {pos.shape}")
        if not np.isfinite(pos).all():
            return self._reject(f"non-finite position(s) {pos.tolist()}")
        if not (math.isfinite(cmd.duration_s) and cmd.duration_s >= 0.0):
            return self._reject(f"duration_s must be finite and >= 0, got {cmd.duration_s}")
        vel = None
        if self._mode == "velocity":
            if cmd.velocity is None:
                return self._reject("velocity mode needs JointCommand.velocity")
            vel = np.asarray(cmd.velocity, dtype=np.float64)
            if vel.shape[0] < n or not np.isfinite(vel).all():
                return self._reject(f"expected {n} finite velocities, got {vel.tolist()}")
            vel = vel[:n]
        arm = pos[:n]
        clipped = np.clip(arm, self.lower, self.upper)
        n_clipped = int(np.count_nonzero(clipped != arm))
        if vel is not None:
            v_clipped = np.clip(vel, -self.vmax, self.vmax)
            n_clipped += int(np.count_nonzero(v_clipped != vel))
            vel = v_clipped
        if pos.shape[0] == n + 1 and self._gripper_act is not None:
            g = float(np.clip(pos[n], *self._gripper_range))
            n_clipped += int(g != pos[n])
            self.data.ctrl[self._gripper_act] = g
        if n_clipped:
            self.stats.clipped += 1
            self.stats.clipped_values += n_clipped
        self.stats.commands += 1
        self._last_cmd_ns = self.time_ns
        self._last_cmd_duration_ns = round(cmd.duration_s * 1e9)
        if vel is not None:
            self._profile = Integrate(self._profile.pos, vel, self.lower, self.upper)
            self._goal = np.where(vel > 0, self.upper, np.where(vel < 0, self.lower, self._profile.pos))
            return True
        self._set_goal(clipped, cmd.duration_s)
        return True

    def _set_goal(self, goal: np.ndarray, duration_s: float) -> None:
        same = np.array_equal(goal, self._goal) and duration_s == self._goal_duration_s
        if same and not isinstance(self._profile, Integrate | Brake):
            return  # an action repeat: the running profile goes on
        self._goal, self._goal_duration_s = goal.copy(), duration_s
        p0, v0 = self._profile.pos, self._profile.vel
        if duration_s > 0.0:
            dist = np.abs(goal - p0)
            accel_s = min(self._accel_time_s, duration_s / 2.0)
            total_s = duration_s
            # stretch the move so that no joint exceeds its velocity limit: peak = dist / (T - Ta)
            need = float(np.max(dist / self.vmax)) + accel_s
            if need > total_s:
                total_s = need
                accel_s = min(accel_s, total_s / 2.0)
            if not dist.any():
                self._profile = Constant(goal)
            else:
                self._profile = TimeSegment(p0, goal, total_s, accel_s)
        elif self._profile_kind == "velocity":
            self._profile = AccelLimited(p0, v0, goal, self._prof_vmax, self._prof_amax)
        else:
            self._profile = VelocityLimited(p0, goal, self.vmax)

    def _reject(self, why: str) -> bool:
        self.stats.rejected += 1
        self.stats.last_error = f"{self.robot.name}: rejected a command: {why}; the arm keeps its current goal"
        if self.stats.rejected <= 10 or self.stats.rejected % 1000 == 0:
            logger.warning("%s (rejection %d)", self.stats.last_error, self.stats.rejected)
        return False

    def _watchdog_due(self) -> bool:
        timeout = self.config.command_timeout_s
        if timeout is None or self._last_cmd_ns is None or self._mode not in ("position", "velocity"):
            return False
        return self.time_ns - self._last_cmd_ns > self._last_cmd_duration_ns + round(timeout * 1e9)

    def _hold_here(self) -> None:
        # Freeze the servo targets where they are now: the motion stops at once. (Re-targeting the measured
        # position instead would let gravity sag add up at every hold.)
        q = self._profile.pos.copy()
        self._profile = Constant(q)
        self._goal, self._goal_duration_s = q.copy(), 0.0

    def _step_period(self) -> None:
        m, d, n, k = self.model, self.data, self.n_substeps, self._chunk
        traj = self._profile.advance(n // k, self.config.physics_dt_s * k)
        if traj is not None and self.effects is not None:
            traj = np.array([self.effects.setpoint(row) for row in traj])
        if traj is None:
            self._set_ctrl(self._profile.pos)
            mujoco.mj_step(m, d, nstep=n)
        else:
            ctrl, step = d.ctrl, mujoco.mj_step
            if self._contiguous_acts:
                nj = self.n_joints
                for row in traj:
                    ctrl[:nj] = row
                    step(m, d, k)
            else:
                ids = self._act_ids
                for row in traj:
                    ctrl[ids] = row
                    step(m, d, k)
        self._steps += n
        self._check_divergence()

    def _set_ctrl(self, q: np.ndarray) -> None:
        if self.effects is not None:
            q = self.effects.setpoint(q)
        if self._contiguous_acts:
            self.data.ctrl[: self.n_joints] = q
        else:
            self.data.ctrl[self._act_ids] = q

    def _check_divergence(self) -> None:
        d = self.data
        counts = d.warning.number[_WARN_IDX]
        vmax = float(np.abs(d.qvel).max(initial=0.0))
        finite = math.isfinite(float(d.qpos.sum()))
        if vmax <= self.config.max_abs_qvel and finite and (counts == self._warn_counts).all():
            return  # the common case, one pass
        if (counts > self._warn_counts).any():
            which = [w.name for w, c, c0 in zip(_DIVERGENCE_WARNINGS, counts, self._warn_counts, strict=True) if c > c0]
            reason = f"MuJoCo warned {which} (it resets the state when the dynamics blow up)"
        elif not (np.isfinite(d.qpos).all() and np.isfinite(d.qvel).all()):
            reason = "non-finite joint positions or velocities"
        else:
            reason = f"a joint velocity above max_abs_qvel={self.config.max_abs_qvel}"
        self._warn_counts = counts.copy()
        self._diverged = reason
        raise SimulationError(
            f"{self.robot.name}: physics diverged at t={self.time_ns / 1e9:.3f} s: {reason}; "
            f"qpos={np.round(d.qpos, 4).tolist()}, max |qvel|={vmax:.3g}. "
            "Check the commands, gains and time step; reset() to continue."
        )

    # ---- modes and reset

    def set_mode(self, mode: str) -> None:
        """Switch the controller mode (see the module docstring).

        Raises:
            ConfigError: ``mode`` is not one of ``MODES``.
        """
        if mode not in MODES:
            raise ConfigError(f"mode: expected one of {MODES}, got {mode!r}")
        if mode == "hold":
            self._hold_here()
        elif mode == "stop":
            self._profile = Brake(
                self._profile.pos, self._profile.vel, self.config.stop_deceleration_rad_s2, self.lower, self.upper
            )
            self._goal = self._profile.pos.copy()
        elif mode != self._mode:  # position <-> velocity: start from where the servos are
            self._profile = Constant(self._profile.pos)
            self._goal = self._profile.pos.copy()
        self._mode = mode
        self._last_cmd_ns = None

    def hold(self) -> None:
        """Hold the current position and ignore commands until another mode is set."""
        self.set_mode("hold")

    def stop(self) -> None:
        """Brake the motion, then hold; commands are ignored until another mode is set."""
        self.set_mode("stop")

    def _check_pose(self, q: np.ndarray, what: str) -> None:
        if q.shape != (self.n_joints,) or not np.isfinite(q).all():
            raise ConfigError(f"{what}: expected {self.n_joints} finite joint positions, got {q.tolist()}")
        bad = [
            (j, float(x))
            for j, x, lo, hi in zip(self.robot.arm_joint_names, q, self.lower, self.upper, strict=True)
            if not lo <= x <= hi
        ]
        if bad:
            raise ConfigError(f"{what}: outside the joint limits: {bad}")

    def reset(self, q: ArrayLike | None = None) -> JointState:
        """Teleport the arm to ``q`` (default: ``initial_q``) at rest, restart sim time at 0, clear divergence.

        Returns:
            The joint state after the reset.

        Raises:
            ConfigError: ``q`` has the wrong length, is not finite, or lies outside the joint limits.
        """
        q_arr = self.initial_q if q is None else np.asarray(q, dtype=np.float64)
        self._check_pose(q_arr, "reset q")
        m, d = self.model, self.data
        if self._home_key is not None:
            mujoco.mj_resetDataKeyframe(m, d, self._home_key)
        else:
            mujoco.mj_resetData(m, d)
        # with calibration offsets the servos read q_arr there
        d.qpos[self._arm_qadr] = q_arr if self.effects is None else q_arr - self.effects.offsets
        d.qvel[:] = 0.0
        if self.effects is not None:
            self.effects.reset(q_arr)
        self._set_ctrl(q_arr)
        mujoco.mj_forward(m, d)
        self._warn_counts = d.warning.number[_WARN_IDX].copy()
        self._steps = 0
        self._profile = Constant(q_arr)
        self._goal, self._goal_duration_s = q_arr.copy(), 0.0
        self._mode = self.config.mode
        self._last_cmd_ns = None
        self._last_cmd_duration_ns = 0
        self._diverged = None
        self._episode_ticks = 0
        self.stats.resets += 1
        return self.joint_state()

    def reset_stats(self) -> None:
        """Zero the counters."""
        self.stats = dataclasses.replace(ServoStats())
