"""Reach: move the end effector to a goal point, for the ReactorX-200 and the Ned2, standard and goal-conditioned.

Action: joint deltas (``action_mode="delta"``, the default): ``a x delta_coeff`` times half the joint's range
(UniROS's actions are radians over the joint range times ``delta_coeff``; this is the same step for a normalised
action), applied again on every env-loop tick of the action cycle from where the arm was last told to be, as
UniROS's env loop does (a joint velocity; turn-based mode applies a delta once per step). Or target positions of
the arm joints normalised to [-1, 1] over their limits (``action_mode="absolute"``).

Defaults (what ``gym.make(id)`` gives): joint deltas, the dense reward, UniROS's observation and UniROS's goal box.
They were chosen so that the env as made by its id learns with stock SB3 TD3 at the paper's hyperparameters (lr
3e-4, batch 256, tau 0.005, gamma 0.99, [400, 300], Gaussian noise 0.1, learning_starts 1000): with joint deltas,
``configs/defaults_sb3_td3.yaml`` reached 100 %, 100 % and 95 % success over 100 episodes at 10k steps on three
seeds, where absolute targets reached 52-85 % (docs/results.md, "Defaults that learn"). A delta moves the arm a
bounded step from where it is, so early random and noisy actions explore around the arm instead of jumping it
across its range, and the policy only has to learn a direction. The reward, observation and goal box are UniROS's,
unchanged.

Observation (standard env), UniROS's: EE position (3), unit vector from the EE to the goal (3), distance (1), the
joint_states positions (rx200: 8, with gripper and fingers; ned2: 6), the previous action, and the joint_states
velocities (rx200 28 entries, ned2 25). The goal env gives that vector without the goal-dependent entries
(direction, distance: HER relabels ``desired_goal`` only) as ``observation`` (rx200 24, ned2 21), the EE position
as ``achieved_goal`` and the goal as ``desired_goal``.

Goals are uniform in a box, keeping only points the arm can reach (IK succeeds and its solution is safe).
``goal_space="uniros-box"`` (the default) is the UniROS task config's goal space for the arm (rx200: x 0.15-0.25,
y +-0.15, z 0.05-0.25 m; ned2: z 0.15-0.25); ``goal_space="workspace"`` covers the arm's reachable workspace in
front of it: the box rx200 x 0.15-0.40, y -0.40-0.40, z 0.05-0.40 m (the rx200 reaches 0.55 m, its corners at
0.57 m fall out by the IK check), ned2 x 0.15-0.40, y -0.40-0.40, z 0.10-0.45 m (the Ned2 reaches 0.49 m from a
shoulder 0.06 m higher; 90 % of its draws are reachable, 97 % of the rx200's). ``goal_min`` / ``goal_max`` set a
box of one's own.

A draw runs IK, and a point the arm cannot reach runs it from every restart, so the goals are drawn at construction,
before the env loop starts: a pool of ``goal_pool`` reachable goals (1024 by default) drawn with the fixed seed
``GOAL_POOL_SEED``, the same pool in every env of one arm, box and safety config. A reset picks one of them with the
env's seeded generator (``self.np_random``), so a reset's goal follows from the reset's seed and the env loop's
thread runs no IK. ``goal_pool=0`` draws each goal at reset instead (a continuous distribution; the IK then runs on
the loop's thread).

Observation modes (``obs_mode``, envs/pixels.py): ``"state"`` is the vector above; ``"pixels"`` a Dict with the
camera's newest frame (``pixels``); ``"pixels+state"`` both (``pixels``, ``state``). The goal env takes
``"state"`` only (HER relabels its vector goals).

Rewards follow UniROS: sparse +1 on reaching (distance <= tolerance) else -1; dense +20 on reaching, else
-2 x distance - 0.5, plus -2 when the action hits a joint limit and -5 when it could not be executed (unsafe).
Reaching terminates the episode with ``info["is_success"] = True``, at the first env-loop tick that finds the EE
within the tolerance (real-time mode; turn-based: at the end of the step).
"""

from __future__ import annotations

from typing import Any, Literal

import gymnasium as gym
import numpy as np
import pydantic
from pydantic import Field

from uniros_async.bus.messages import JointState
from uniros_async.config import ConfigModel, Float, Vec3, key_error
from uniros_async.envs.base import GoalEnv
from uniros_async.envs.pixels import PixelSource
from uniros_async.envs.robot import TICK_OFFSET_NS
from uniros_async.envs.task import TaskEnv, parse_kwargs
from uniros_async.errors import ConfigError
from uniros_async.tasks.markers import TaskMarkers, reach_markers

__all__ = ["ReachConfig", "ReachEnv", "ReachGoalEnv", "reach_reward"]

GOAL_BOXES = {  # the goal spaces of UniROS's reach task configs (position_goal_min / _max)
    "rx200": ((0.15, -0.15, 0.05), (0.25, 0.15, 0.25)),
    "ned2": ((0.15, -0.15, 0.15), (0.25, 0.15, 0.25)),
}
# boxes around the arm's reachable workspace in front of it; goals in them are kept only where IK reaches them
WORKSPACE_BOXES = {
    "rx200": ((0.15, -0.40, 0.05), (0.40, 0.40, 0.40)),
    "ned2": ((0.15, -0.40, 0.10), (0.40, 0.40, 0.45)),
}
GOAL_SPACES = {"uniros-box": GOAL_BOXES, "workspace": WORKSPACE_BOXES}
GOAL_POOL_SEED = 0
"""The seed the goal pool is drawn with (see the module docstring)."""
_GOAL_POOLS: dict[tuple[Any, ...], np.ndarray] = {}
"""The pools drawn in this process, by arm, model, box, safety config and size (read-only arrays): the envs of one
configuration built in one process draw theirs once."""
_GOAL_POOLS_KEPT = 32
REWARD_TYPES = ("dense", "sparse")
ACTION_MODES = ("absolute", "delta")


class ReachConfig(ConfigModel):
    """The reach task's keyword arguments (besides EnvConfig's), checked when the env is built."""

    reward_type: Literal["dense", "sparse"] = "dense"
    """UniROS's: ``dense`` is +20 on reaching, else -2 x distance - 0.5, with -2 at a joint limit and -5 for an
    action that could not be executed; ``sparse`` is +1 on reaching, else -1."""
    action_mode: Literal["absolute", "delta"] = "delta"
    """Actions are joint deltas (``delta``: with them stock SB3 TD3 learns the task, docs/results.md section 6) or
    joint targets over the joint range (``absolute``)."""
    reach_tolerance: Float = Field(default=0.02, gt=0)
    """Reached when the EE is this close to the goal (m)."""
    goal_space: Literal["uniros-box", "workspace"] = "uniros-box"
    """Where goals are drawn (points the arm can reach only): ``uniros-box``, the arm's box from UniROS's task
    config, or ``workspace``, the arm's whole reachable workspace in front of it (see the module docstring)."""
    goal_min: Vec3 | None = None
    """Lower corner of the goal box (m); unset: ``goal_space``'s."""
    goal_max: Vec3 | None = None
    """Upper corner of the goal box (m); unset: ``goal_space``'s."""
    goal_pool: int = Field(default=1024, ge=0)
    """How many reachable goals are drawn at construction for resets to pick from (see the module docstring); 0:
    each reset draws its goal on the env loop's thread."""
    delta_coeff: Float = Field(default=0.05, gt=0)
    """With ``action_mode="delta"``: an action of 1 moves a joint by this times half its range per env-loop tick."""
    render_mode: Literal["rgb_array"] | None = None
    """``"rgb_array"``: ``render()`` returns an image of the arm and the goal."""

    @pydantic.model_validator(mode="after")
    def _check(self) -> ReachConfig:
        lo, hi = self.goal_min, self.goal_max
        if lo is not None and hi is not None and not all(a <= b for a, b in zip(lo, hi, strict=True)):
            raise key_error("goal_max", f"must be >= goal_min {list(lo)} on every axis, got {list(hi)}")
        return self


def reach_reward(
    achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Any, *, reward_type: str, reach_tolerance: float
) -> np.ndarray:
    """The reach reward per (achieved, desired) pair, a pure function of its arguments (``ReachEnv.batch_reward``
    is this with the env's settings), so an agent can relabel HER goals without asking the env.

    Sparse: +1 where ``|achieved - desired| <= reach_tolerance``, else -1. Dense: +20 there, else
    ``-2 x distance - 0.5``, plus -2 per ``info["joint_limit_hit"]`` and -5 per ``info["not_executable"]``;
    ``info`` is one dict for every pair or an array (or list) of dicts, one per pair; anything else (or an array of
    the wrong size) adds no penalty.

    Raises:
        ConfigError: an unknown ``reward_type``.
    """
    d = np.linalg.norm(np.asarray(achieved_goal) - np.asarray(desired_goal), axis=-1)
    reached = d <= reach_tolerance
    if reward_type == "sparse":
        return np.where(reached, 1.0, -1.0)
    if reward_type != "dense":
        raise ConfigError(f"reward_type must be one of {REWARD_TYPES}, got {reward_type!r}")
    r: np.ndarray = np.where(reached, 20.0, -2.0 * d - 0.5) + _penalties(info, d.shape)
    return r


def _penalties(info: Any, shape: tuple[int, ...]) -> np.ndarray:
    def one(i: Any) -> float:
        if not isinstance(i, dict):
            return 0.0
        return -2.0 * bool(i.get("joint_limit_hit")) - 5.0 * bool(i.get("not_executable"))

    if isinstance(info, dict):
        return np.full(shape, one(info))
    flat = np.asarray([one(i) for i in np.ravel(np.asarray(info, dtype=object))], dtype=np.float64)
    return flat.reshape(shape) if flat.size == int(np.prod(shape)) else np.zeros(shape)


class ReachEnv(TaskEnv):
    """The standard (vector observation) reach task; see the module docstring."""

    TASK_CONFIG = ReachConfig
    TASK_KEYS = ReachConfig.field_names()
    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, arm: str = "rx200", **kwargs: Any) -> None:
        config, settings = parse_kwargs(type(self), kwargs)
        task: ReachConfig = settings  # TASK_CONFIG's instance
        self.task_config = task
        self.reward_type: str = task.reward_type
        self.action_mode: str = task.action_mode
        self.reach_tolerance = task.reach_tolerance
        self.goal_space: str = task.goal_space
        boxes = GOAL_SPACES[self.goal_space]
        box_min, box_max = boxes.get(arm, boxes["rx200"])
        self.goal_min = np.asarray(box_min if task.goal_min is None else task.goal_min, dtype=np.float64)
        self.goal_max = np.asarray(box_max if task.goal_max is None else task.goal_max, dtype=np.float64)
        self.delta_coeff = task.delta_coeff
        self.render_mode = task.render_mode
        if np.any(self.goal_min > self.goal_max):  # one of them given, the other the arm's default
            raise ConfigError(
                f"goal_min/goal_max: min must be <= max on every axis, got {self.goal_min.tolist()} and "
                f"{self.goal_max.tolist()} (the {arm}'s {self.goal_space} box gives the one not set)"
            )
        super().__init__(arm, config)
        self._pixels = PixelSource(config, self.robot_spec) if config.obs_mode != "state" else None
        if self._pixels is not None and isinstance(self, GoalEnv):
            raise ConfigError(
                f"obs_mode={config.obs_mode!r}: the goal-conditioned env takes obs_mode='state' only (HER relabels "
                "its vector goals); use the standard env for pixel observations"
            )
        spec = self.robot_spec
        n = spec.n_arm_joints
        self._lower = np.asarray(spec.joint_lower_rad)
        self._upper = np.asarray(spec.joint_upper_rad)
        self._half_range = (self._upper - self._lower) / 2
        # the same values as Python floats: _action_to_target runs once per action in a worker that wakes cold,
        # where every numpy call costs tens of microseconds and float arithmetic on 5-6 values almost nothing
        self._lower_l: list[float] = self._lower.tolist()
        self._upper_l: list[float] = self._upper.tolist()
        self._span_l: list[float] = (self._upper - self._lower).tolist()
        self._half_range_l: list[float] = self._half_range.tolist()
        self.action_space = gym.spaces.Box(-1.0, 1.0, (n,), np.float32)
        self.observation_space = self._make_observation_space()
        self.goal = np.zeros(3)
        self._prev_action = np.zeros(n, dtype=np.float32)
        self._limit_hit = False
        self._task_markers = TaskMarkers()  # goal, EE and bounds on /<arm>/markers, from the step, never from the tick
        # before the loop starts: the IK of the goals' draws runs on this thread, never on the loop's
        self.goal_pool = self.draw_goal_pool(task.goal_pool)
        self._start()

    def _vector_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Physical bounds of the vector observation: EE within 1 m of the base, a unit direction, distance within
        3.5 m, joint_states positions within +-(pi + 0.1) (fingers in metres fall inside), actions within [-1, 1],
        velocities within +-50 rad/s (loose: the servos' limits are a few rad/s, a contact transient is not)."""
        n_js, n = len(self.robot_spec.joint_state_names), self.robot_spec.n_arm_joints
        hi = np.concatenate(
            [np.full(3, 1.0), np.ones(3), [3.5], np.full(n_js, np.pi + 0.1), np.ones(n), np.full(n_js, 50.0)]
        )
        lo = -hi
        lo[6] = 0.0
        return lo.astype(np.float32), hi.astype(np.float32)

    def _make_observation_space(self) -> gym.Space[Any]:
        lo, hi = self._vector_bounds()
        state = gym.spaces.Box(lo, hi, dtype=np.float32)
        return state if self._pixels is None else self._pixels.space(state)

    # ---- the camera (obs_mode with pixels)

    async def _join(self, domain: Any, transport: str, options: Any) -> None:
        await super()._join(domain, transport, options)
        await self._task_markers.join(self._node)
        if self._pixels is None:
            return
        try:
            rate_hz = self._pixels.camera_rate_hz(self.env_loop_rate_hz)
            phase_s = self._pixels.camera_phase_ns(TICK_OFFSET_NS + self._phase_ns) / 1e9
            await self._pixels.join(
                self._node, self._node_stack, domain, transport, options, self._clock, rate_hz, phase_s
            )
        except BaseException:
            await self._node_stack.aclose()
            raise

    def camera_stats(self) -> dict[str, Any] | None:
        """The sim camera's counters (``frames``, ``skipped``, ``render_median_ms``), or None without one."""
        return None if self._pixels is None else self._pixels.stats()

    async def _areset(self, options: dict[str, Any]) -> tuple[Any, dict[str, Any]]:
        obs, info = await super()._areset(options)
        pixels = self._pixels
        if pixels is None:
            return obs, info
        # a frame of the new episode (its target shown): rendered now in sim time, or the camera's next one
        await pixels.fresh(self._clock.now_ns())
        return pixels.observe(obs.get("state"), info), info

    # ---- hooks

    def _action_to_target(self, action: np.ndarray, q_arm: np.ndarray) -> tuple[np.ndarray, bool]:
        a = action.tolist()  # float32 to Python float is exact: the same float64 arithmetic as numpy's, per element
        if self.action_mode == "absolute":
            target = [lo + (x + 1.0) * 0.5 * span for lo, x, span in zip(self._lower_l, a, self._span_l, strict=True)]
            hit = any(abs(x) >= 0.999 for x in a)
        else:
            dc = self.delta_coeff
            raw = [q + x * dc * h for q, x, h in zip(q_arm.tolist(), a, self._half_range_l, strict=True)]
            target = [min(max(r, lo), hi) for r, lo, hi in zip(raw, self._lower_l, self._upper_l, strict=True)]
            hit = raw != target
        return np.array(target), hit

    @property
    def _relative_action(self) -> bool:
        return self.action_mode == "delta"

    def _on_action(self, action: np.ndarray) -> None:
        self._prev_action = action.astype(np.float32)
        if self._task_markers.due():
            self._publish_markers()

    def _on_reset(self, q_arm: np.ndarray) -> None:
        self._prev_action = np.zeros_like(self._prev_action)
        self._limit_hit = False
        pool = self.goal_pool
        if pool is None:
            self.goal = self.sample_goal(self.np_random)
        else:
            self.goal = pool[int(self.np_random.integers(len(pool)))].copy()
        self._publish_markers()

    def _publish_markers(self) -> None:
        js = self._js.latest()
        ee = None if js is None else self.kin.ee_position(js.position[self._arm_idx])
        bounds = (self.safety.config.workspace_min_m, self.safety.config.workspace_max_m)
        self._task_markers.publish(
            reach_markers(
                self._clock.now_ns(), self.goal, ee, bounds, (self.goal_min, self.goal_max), self.reach_tolerance
            )
        )

    def draw_goal_pool(self, size: int) -> np.ndarray | None:
        """``size`` reachable goals (``sample_goal``) drawn with ``GOAL_POOL_SEED``, as a read-only (size, 3) array;
        None for a size of 0. Drawn once per process for one arm, model, box and safety config.

        Raises:
            ConfigError: the goal box is out of reach (``sample_goal``).
        """
        if size == 0:
            return None
        spec = self.robot_spec
        key = (
            spec.name,
            str(spec.mjcf_path),
            self.goal_min.tobytes(),
            self.goal_max.tobytes(),
            repr(self.safety.config),
            size,
        )
        pool = _GOAL_POOLS.get(key)
        if pool is None:
            rng = np.random.default_rng(GOAL_POOL_SEED)
            pool = np.array([self.sample_goal(rng) for _ in range(size)])
            pool.flags.writeable = False
            if len(_GOAL_POOLS) >= _GOAL_POOLS_KEPT:
                del _GOAL_POOLS[next(iter(_GOAL_POOLS))]
            _GOAL_POOLS[key] = pool
        return pool

    def sample_goal(self, rng: np.random.Generator, max_tries: int = 200) -> np.ndarray:
        """A goal uniform in the goal box that the arm can reach (IK succeeds, EE inside the workspace).

        Raises:
            ConfigError: no reachable point found in ``max_tries`` draws (the box is out of reach).
        """
        for _ in range(max_tries):
            g = rng.uniform(self.goal_min, self.goal_max)
            q, ok = self.kin.ik(g, rng=rng)
            if ok and self.safety.check(q) is None:
                return g
        raise ConfigError(
            f"no reachable goal in the box {self.goal_min.tolist()}..{self.goal_max.tolist()} for "
            f"{self.robot_spec.name} after {max_tries} draws"
        )

    def _vector_obs(self, state: JointState, ee: np.ndarray) -> np.ndarray:
        d = self.goal - ee
        dist = np.linalg.norm(d)
        direction = d / dist if dist > 1e-9 else np.zeros(3)
        return np.concatenate([ee, direction, [dist], state.position, self._prev_action, state.velocity]).astype(
            np.float32
        )

    def _compute_returns(self, state: JointState, q_arm: np.ndarray) -> tuple[Any, float, bool, dict[str, Any]]:
        ee = self.kin.ee_position(q_arm)
        # reward and success from the float32 values the agent sees, so that HER's compute_reward on the
        # observation's achieved/desired goals reproduces the step's reward exactly
        ee32, goal32 = ee.astype(np.float32), self.goal.astype(np.float32)
        d32 = np.linalg.norm(ee32 - goal32, axis=-1)  # float32, the same reduction batch_reward uses
        success = bool(d32 <= self.reach_tolerance)
        limit_hit, not_executable = bool(self._limit_hit), self._target_unsafe is not None or self._projected
        info = {
            "is_success": success,
            "distance": float(d32),
            "joint_limit_hit": limit_hit,
            "not_executable": not_executable,
        }
        # the scalar twin of batch_reward (same float32 arithmetic, ~20x cheaper than broadcasting per tick)
        if self.reward_type == "sparse":
            reward = 1.0 if success else -1.0
        else:
            reward = 20.0 if success else float(-2.0 * d32 - 0.5)
            reward += -2.0 * limit_hit - 5.0 * not_executable
        obs = self._observation(state, ee)
        if self._pixels is not None:
            obs = self._pixels.observe(obs, info)
        return obs, reward, success, info

    def _observation(self, state: JointState, ee: np.ndarray) -> Any:
        return self._vector_obs(state, ee)

    # ---- reward (vectorised: HER relabels batches of goals)

    def batch_reward(self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Any) -> np.ndarray:
        """Reward per (achieved, desired) pair; penalties come from ``info`` (a dict or an array of dicts).

        (Named so on the standard env: SB3 takes any env with ``compute_reward`` for a GoalEnv. ReachGoalEnv
        exposes it as ``compute_reward``.) The arithmetic is ``reach_reward``'s, with this env's settings.
        """
        return reach_reward(
            achieved_goal, desired_goal, info, reward_type=self.reward_type, reach_tolerance=self.reach_tolerance
        )

    def render(self) -> np.ndarray | None:
        """An RGB image of the arm at its newest state with the goal marker (``render_mode="rgb_array"``)."""
        if self.render_mode != "rgb_array":
            return None
        from uniros_async.sim.render import render_rgb

        js = self._js.latest()
        q = None if js is None else js.position[self._arm_idx]
        return render_rgb(self.robot_spec.name, q=q, goal=self.goal)


class ReachGoalEnv(ReachEnv, GoalEnv):
    """The goal-conditioned reach task (dict observation for HER)."""

    def compute_reward(self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Any) -> np.ndarray:
        """Reward per (achieved, desired) pair, vectorised for HER (see ``batch_reward``)."""
        return self.batch_reward(achieved_goal, desired_goal, info)

    def compute_terminated(self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Any) -> np.ndarray:
        """Reaching ends the episode."""
        reached: np.ndarray = (
            np.linalg.norm(np.asarray(achieved_goal) - np.asarray(desired_goal), axis=-1) <= self.reach_tolerance
        )
        return reached

    # The goal env's ``observation`` leaves out the goal-dependent entries of the standard vector (direction to
    # the goal, distance): the goal is ``desired_goal`` alone, so HER, which relabels ``desired_goal``, never pairs a
    # transition with two different goals.
    _GOAL_ENTRIES = slice(3, 7)

    def _make_observation_space(self) -> gym.Space[Any]:
        box3 = gym.spaces.Box(-1.0, 1.0, (3,), np.float32)
        lo, hi = (np.delete(b, np.r_[self._GOAL_ENTRIES]) for b in self._vector_bounds())
        return gym.spaces.Dict(
            {
                "observation": gym.spaces.Box(lo, hi, dtype=np.float32),
                "achieved_goal": box3,
                "desired_goal": box3,
            }
        )

    def _observation(self, state: JointState, ee: np.ndarray) -> Any:
        return {
            "observation": np.delete(self._vector_obs(state, ee), np.r_[self._GOAL_ENTRIES]),
            "achieved_goal": ee.astype(np.float32),
            "desired_goal": self.goal.astype(np.float32),
        }
