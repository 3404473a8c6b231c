"""The reach envs: gymnasium/SB3 checkers, reaching a goal, bad input, and the same TaskEnv on other placements."""

from __future__ import annotations

import os
import signal
import time

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import error as gym_error
from gymnasium.utils.env_checker import check_env

import uniros_async  # noqa: F401  (registers the ids)
from uniros_async.errors import ConfigError, RobotError
from uniros_async.tasks.registry import ENV_IDS

pytestmark = pytest.mark.slow

# the built-in ids, and the ids of an arm a user's own package registers from outside uniros_async
# (tests/extension/acme_arms; "module:id" imports it when the test runs)
USER_ENV_IDS = ["acme_arms:acme/Acme5Reach-v0", "acme_arms:acme/Acme5ReachGoal-v0"]
CHECKED_ENV_IDS = [*(i for i in ENV_IDS if i.startswith("uniros/")), *USER_ENV_IDS]


def drive_to_goal(env: gym.Env, seed: int, max_steps: int) -> tuple[float, dict]:  # type: ignore[type-arg]
    """Reset, then repeat the IK action of the goal until the episode ends; returns the last reward and info."""
    env.reset(seed=seed)
    a = ik_action(env)
    for _ in range(max_steps):
        _, reward, terminated, _, info = env.step(a)
        if terminated:
            return float(reward), info
    raise AssertionError(f"no success within {max_steps} steps: {info}")


def ik_action(env: gym.Env) -> np.ndarray:
    """The goal's IK solution as an absolute joint-target action (for envs made with ``action_mode="absolute"``)."""
    u = env.unwrapped
    assert u.action_mode == "absolute", "ik_action is a joint target: make the env with action_mode='absolute'"
    q, ok = u.kin.ik(u.goal)
    assert ok, f"goal {u.goal} unreachable"
    return (2 * (q - u._lower) / (u._upper - u._lower) - 1).astype(np.float32)


@pytest.mark.parametrize("reward_type", ["dense", "sparse"])
@pytest.mark.parametrize("env_id", CHECKED_ENV_IDS)
def test_gymnasium_and_sb3_checkers(env_id: str, reward_type: str) -> None:
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = gym.make(env_id, clock="sim", reward_type=reward_type)
    try:
        check_env(env.unwrapped, skip_render_check=True)
        sb3_check_env(env.unwrapped, warn=True)
    finally:
        env.close()


@pytest.mark.parametrize("env_id", ["uniros/Rx200Reach-v0", "uniros/Ned2ReachGoal-v0"])
def test_ik_action_reaches_the_goal_in_real_time(env_id: str) -> None:
    env = gym.make(env_id, action_cycle_s=0.4, action_mode="absolute")
    try:
        reward, info = drive_to_goal(env, seed=3, max_steps=10)
        assert info["is_success"], info
        u = env.unwrapped
        assert reward == (20.0 if u.reward_type == "dense" else 1.0)
        # action repeat: the loop sent a command on every tick from the first action to the episode's end
        t = u.timing
        ticks = [k for k in t.tick_ns if t.action_ns[0] < k <= t.command_ns[-1]]
        assert len(ticks) >= 3 and set(ticks) <= set(t.command_ns), (ticks, list(t.command_ns))
        assert len(u.timing.action_latency_ns) >= 1
    finally:
        env.close()


def test_action_targets_are_the_numpy_formula_bit_for_bit() -> None:
    """_action_to_target works on Python floats (cheaper in a cold worker); it must give numpy's values exactly."""
    env = gym.make("uniros/Rx200Reach-v0", clock="sim")
    try:
        u = env.unwrapped
        rng = np.random.default_rng(0)
        for mode in ("absolute", "delta"):
            u.action_mode = mode
            for _ in range(500):
                a = rng.uniform(-1.2, 1.2, u.action_space.shape).astype(np.float32)
                a[rng.integers(len(a))] = rng.choice([-1.0, 1.0, 0.999, -0.999, 0.5])
                q = rng.uniform(u._lower, u._upper)
                target, hit = u._action_to_target(a, q)
                a64 = a.astype(np.float64)
                if mode == "absolute":
                    ref = u._lower + (a64 + 1.0) * 0.5 * (u._upper - u._lower)
                    ref_hit = bool(np.any(np.abs(a64) >= 0.999))
                else:
                    raw = q + a64 * u.delta_coeff * u._half_range
                    ref = np.clip(raw, u._lower, u._upper)
                    ref_hit = bool(np.any(raw != ref))
                assert target.dtype == np.float64 and np.array_equal(target, ref) and hit == ref_hit, (mode, a, q)
    finally:
        env.close()


def test_sim_clock_episode_is_faster_than_real_time() -> None:
    env = gym.make("uniros/Rx200Reach-v0", clock="sim")
    try:
        env.reset(seed=0)
        t0 = time.monotonic()
        for _ in range(100):
            env.step(env.action_space.sample())
        wall_s = time.monotonic() - t0
        sim_s = (env.unwrapped.timing.step_ns[-1] - env.unwrapped.timing.step_ns[0]) / 1e9
    finally:
        env.close()
    assert sim_s == pytest.approx(99 * 0.8, rel=1e-6), "action cycles keep their meaning in sim time"
    print(f"100 steps of 0.8 s sim time in {wall_s:.2f} s of wall time ({80 / wall_s:.0f}x real time)")
    assert wall_s < 10.0  # the < 1 s figure is a benchmark's claim; this guards against falling back to real time


def test_bad_actions_and_call_order() -> None:
    env = gym.make("uniros/Rx200Reach-v0", action_cycle_s=0.2)
    u = env.unwrapped
    try:
        with pytest.raises(gym_error.ResetNeeded):
            env.step(env.action_space.sample())
        env.reset(seed=1)
        for bad, match in (
            (np.zeros(4, np.float32), r"shape \(5,\)"),
            (np.full(5, np.nan, np.float32), "NaN"),
            (np.full(5, 3.0, np.float32), "outside the action space"),
            ("left", "numbers of shape"),
        ):
            with pytest.raises(gym_error.InvalidAction, match=match):
                env.step(bad)
        # still usable after bad input
        obs, *_ = env.step(np.zeros(5, np.float32))
        assert obs.shape == (28,)
    finally:
        env.close()
    env.close()  # idempotent
    with pytest.raises(gym_error.ClosedEnvironmentError):
        u.step(np.zeros(5, np.float32))


def test_unsafe_action_is_not_sent() -> None:
    env = gym.make("uniros/Rx200Reach-v0", action_cycle_s=0.2, clock="sim", action_mode="absolute")
    u = env.unwrapped
    try:
        env.reset(seed=0)
        # shoulder and elbow far forward: the gripper would go through the table
        lo, hi = u._lower, u._upper
        q = np.array([0.0, 1.9, 1.5, 1.5, 0.0])
        a = (2 * (q - lo) / (hi - lo) - 1).astype(np.float32)
        assert u.safety.check(q) is not None
        sent_before = len(u.timing.command_ns)
        obs, reward, terminated, truncated, info = env.step(a)
        assert "unsafe_reason" in info and info["not_executable"]
        assert reward <= -5.0
        assert u.kin.table_clearance_m(obs[7:12].astype(np.float64)) > 0
        assert len(u.timing.action_latency_ns) == 0, "an unsafe action is never sent"
        assert len(u.timing.command_ns) == sent_before + 1  # the one hold command
    finally:
        env.close()


def test_unknown_kwargs_are_a_clear_error() -> None:
    with pytest.raises(ConfigError, match=r"^ReachEnv: colour: unknown keyword argument; valid: .*action_cycle_s"):
        gym.make("uniros/Rx200Reach-v0", colour="red")
    with pytest.raises(ConfigError, match=r"^ReachEnv: reward_type: expected one of 'dense', 'sparse', got 'shaped'$"):
        gym.make("uniros/Rx200Reach-v0", reward_type="shaped")


def test_same_task_on_the_emulated_real_arm_over_tcp() -> None:
    env = gym.make("uniros/Rx200Reach-v0", robot="emulated-real", action_cycle_s=0.4, action_mode="absolute")
    try:
        _, info = drive_to_goal(env, seed=5, max_steps=12)
        assert info["is_success"], info
    finally:
        env.close()


def test_accelerated_emulated_real_arm_differs_from_the_nominal_sim() -> None:
    """robot="emulated-real" with clock="sim": the emulation model in sim time, in process (for training)."""
    finals = {}
    for robot in ("sim", "emulated-real"):
        env = gym.make("uniros/Rx200Reach-v0", robot=robot, clock="sim", emulation_seed=3, action_mode="absolute")
        try:
            _, info = drive_to_goal(env, seed=5, max_steps=12)
            assert info["is_success"], (robot, info)
            finals[robot] = info["distance"]
        finally:
            env.close()
    # the same seed, goal and actions: the perturbed, noisy arm ends elsewhere than the nominal one
    assert finals["sim"] != finals["emulated-real"], finals
    with pytest.raises(ConfigError, match="clock='sim' needs robot='sim' or 'emulated-real'"):
        gym.make("uniros/Rx200Reach-v0", robot="sim-process", clock="sim")


def test_a_robot_that_stops_publishing_is_reported() -> None:
    env = gym.make("uniros/Ned2Reach-v0", robot="sim-process", action_cycle_s=0.2, robot_timeout_s=0.5)
    try:
        env.reset(seed=0)
        env.step(np.zeros(6, np.float32))
        os.kill(env.unwrapped.robot_process.pid, signal.SIGKILL)
        with pytest.raises(RobotError, match="joint_states"):
            for _ in range(10):
                env.step(np.zeros(6, np.float32))
    finally:
        env.close()


def test_turn_based_baseline_returns_fresh_observations() -> None:
    env = gym.make("uniros/Rx200Reach-v0", turn_based=True, action_mode="absolute")
    try:
        u = env.unwrapped
        assert u.config.clock == "sim", "turn-based mode pauses the world, so it runs on the sim clock"
        env.reset(seed=0)
        for _ in range(3):
            env.step(ik_action(env))
        assert list(u.timing.observation_age_ns) == [0, 0, 0]
        steps = list(u.timing.step_ns)
        assert all(b - a == 800_000_000 for a, b in zip(steps, steps[1:], strict=False))
    finally:
        env.close()


@pytest.mark.parametrize("latency", [0.0, 0.3])
def test_modelled_agent_latency_in_sim_time(latency: float) -> None:
    env = gym.make("uniros/Ned2Reach-v0", clock="sim", agent_latency_s=latency)
    try:
        u = env.unwrapped
        env.reset(seed=0)
        for _ in range(3):
            env.step(np.zeros(6, np.float32))
        steps, actions = list(u.timing.step_ns), list(u.timing.action_ns)
        # the action reaches the loop exactly `latency` of sim time after the previous step returned,
        # and the cycles keep their length
        assert [a - s for s, a in zip(steps, actions[1:], strict=False)] == [round(latency * 1e9)] * 2
        assert all(b - a == 800_000_000 for a, b in zip(steps, steps[1:], strict=False))
    finally:
        env.close()


@pytest.mark.parametrize(
    ("phase_ns", "cycle_phase"), [(0, 0.0), (3_000_000, 0.0), (60_000_000, 0.0), (0, 0.5), (3_000_000, 0.33)]
)
@pytest.mark.parametrize("env_id", ["uniros/Rx200Reach-v0", "uniros/Ned2Reach-v0"])
def test_loops_and_deadlines_sit_on_the_clock_grid(env_id: str, phase_ns: int, cycle_phase: float) -> None:
    """Env-loop ticks fall TICK_OFFSET (plus the env's loop phase) after the grid of their period (where the servo
    publishes), and steps return TICK_ALIGN after a tick on the grid of the action cycle: the same instants for
    every arm and process of one phase. The phase is capped at a quarter of the loop period. ``action_cycle_phase``
    moves the steps on by that fraction of the cycle, in whole loop periods, so they still follow a tick."""
    from uniros_async.envs.robot import TICK_ALIGN_NS, TICK_OFFSET_NS
    from uniros_async.envs.runtime import deferred_start

    with deferred_start():
        env = gym.make(env_id, clock="sim", action_cycle_phase=cycle_phase)
    try:
        u = env.unwrapped
        u.loop_phase_ns = phase_ns
        u.start_thread()
        env.reset(seed=0)
        for _ in range(3):
            env.step(np.zeros(env.action_space.shape, np.float32))
        period = round(1e9 / u.env_loop_rate_hz)
        phase = min(phase_ns, period // 4)  # 60 ms: 25 ms at 10 Hz, 10 ms at 25 Hz
        # 0.5 of 800 ms: 400 ms on both arms; 0.33: 264 ms, down to 200 ms at 10 Hz and 240 ms at 25 Hz
        offset = {0.0: 0, 0.5: 400_000_000, 0.33: 200_000_000 if period == 100_000_000 else 240_000_000}[cycle_phase]
        assert {t % period for t in u.timing.tick_ns} == {TICK_OFFSET_NS + phase}
        assert {s % 800_000_000 for s in u.timing.step_ns} == {TICK_OFFSET_NS + TICK_ALIGN_NS + phase + offset}
        # the returns the agent gets were built at the tick just before: TICK_ALIGN old
        assert set(u.timing.observation_age_ns) == {TICK_ALIGN_NS}
    finally:
        env.close()


@pytest.mark.parametrize("phase_ns", [0, 3_000_000])
def test_wall_clock_members_meet_on_one_deadline_after_a_reset(phase_ns: int) -> None:
    """On a wall clock, the first step after a reset and a late step take the same rule at the moment the
    action arrives, so a vector env's member that just reset returns with the ones that waited for it. Members
    of different loop phases (worker ranks) decide on the same grid point, each returning at its phase after it."""
    from uniros_async.envs.robot import TICK_ALIGN_NS, TICK_OFFSET_NS

    env = gym.make("uniros/Rx200Reach-v0", clock="wall")
    try:
        u = env.unwrapped
        env.reset(seed=0)
        u.loop_phase_ns = phase_ns  # only the deadline rule is exercised here (the loop keeps its start)
        cycle = 800_000_000
        grid = 100 * cycle + TICK_OFFSET_NS + TICK_ALIGN_NS  # a point of the action-cycle grid
        overruns = u.timing.step_overruns

        def deadline(now: int, *, first: bool, previous: int = grid - cycle + phase_ns) -> int:
            """The member's deadline, relative to its phase (so the same figures hold for every phase)."""
            u._first_step, u._deadline_ns = first, previous
            return int(u._step_deadline(now)) - phase_ns

        # the action came 300 ms before the grid point: the member that kept its deadline and the one that just
        # reset (its deadline from the reset is ignored) both return there
        assert deadline(grid - 300_000_000, first=False) == grid
        assert deadline(grid - 300_000_000, first=True, previous=0) == grid
        assert u.timing.step_overruns == overruns
        # 50 ms before it (the reset took 750 ms of the cycle): less than cycle / 8 to act, both take the next one
        assert deadline(grid - 50_000_000, first=False) == grid + cycle
        assert deadline(grid - 50_000_000, first=True, previous=0) == grid + cycle
        assert u.timing.step_overruns == overruns + 1  # the member whose cycle it was overran; the first step not
        # a reset that took longer than a cycle: past the regular deadline, the same rule again
        assert deadline(grid + 20_000_000, first=False) == grid + cycle
        assert deadline(grid + 20_000_000, first=True, previous=0) == grid + cycle
        # near the cut-off (cycle / 8 before the grid point), members that got their actions 1 ms apart decide
        # from the instant the agent sent the step (set by the worker), not from their own arrival times, and
        # from the grid point, not from their phase after it (0.5 ms before the cut-off: a 3 ms phase would
        # have put a member on the other side of it)
        sent = grid - cycle // 8 - 500_000
        assert deadline(sent + 1_000_000, first=False) == grid + cycle  # alone, past the cut-off: the next one
        for first in (False, True):
            u.step_reference_ns = sent
            assert deadline(sent + 1_000_000, first=first, previous=grid - cycle + phase_ns if not first else 0) == grid
            assert u.step_reference_ns is None  # used once
        u.step_reference_ns = grid - cycle // 8 + 500_000  # 0.5 ms after the cut-off: the next point, any phase
        assert deadline(grid - cycle // 8 + 600_000, first=False) == grid + cycle
    finally:
        env.close()


def test_wall_clock_turn_based_is_a_loopless_real_arm_baseline() -> None:
    """turn_based=True with clock="wall": one command per step, no env loop, returns from the newest state."""
    env = gym.make("uniros/Rx200Reach-v0", turn_based=True, clock="wall", action_cycle_s=0.4, action_mode="absolute")
    try:
        u = env.unwrapped
        assert u.config.clock == "wall"
        _, info = drive_to_goal(env, seed=5, max_steps=12)
        assert info["is_success"], info
        t = u.timing_snapshot()
        assert t["tick_ns"] == [], "no env loop"
        assert len(t["command_ns"]) == len(t["step_ns"]), "one command per step, none repeated"
        # the state used is whatever the 10 Hz servo published last: between 0 and one period (+ slack) old
        assert all(0 <= a < 100_000_000 + 20_000_000 for a in t["observation_age_ns"])
    finally:
        env.close()


def test_goal_env_observation_holds_no_goal() -> None:
    """HER relabels desired_goal only: the observation vector must not carry the goal (goal - EE, distance)."""
    env = gym.make("uniros/Rx200ReachGoal-v0", clock="sim")
    std = gym.make("uniros/Rx200Reach-v0", clock="sim")
    try:
        obs, _ = env.reset(seed=4)
        vec, _ = std.reset(seed=4)
        assert obs["observation"].shape == (vec.shape[0] - 4,)
        np.testing.assert_array_equal(obs["observation"], np.delete(vec, [3, 4, 5, 6]))
        np.testing.assert_array_equal(obs["observation"][:3], obs["achieved_goal"])
        env.unwrapped.goal = env.unwrapped.goal + 0.05  # another goal: the observation vector does not change
        obs2, *_ = env.step(np.zeros(env.action_space.shape, np.float32))
        std_obs, *_ = std.step(np.zeros(std.action_space.shape, np.float32))
        np.testing.assert_allclose(obs2["observation"], np.delete(std_obs, [3, 4, 5, 6]), atol=1e-6)
    finally:
        env.close()
        std.close()


def test_goal_reached_mid_cycle_ends_the_episode_at_that_tick() -> None:
    # a long action cycle: the IK target is reached well before the step's deadline; the tick that finds the EE
    # within tolerance ends the episode there (UniROS's real-time envs), not the end of the cycle
    env = gym.make("uniros/Rx200Reach-v0", clock="sim", action_cycle_s=3.0, action_mode="absolute")
    u = env.unwrapped
    try:
        env.reset(seed=3)
        _, reward, terminated, _, info = env.step(ik_action(env))
        assert terminated and info["is_success"] and reward == 20.0
        end_tick_ns = u._cache[0]
        assert u.timing.step_ns[-1] - end_tick_ns > 0.5e9, "the success tick came long before the deadline"
        assert u.timing.command_ns[-1] == end_tick_ns, "the arm was told to hold at that tick, nothing sent after"
        ticks_after = [t for t in u.timing.tick_ns if t > end_tick_ns]
        assert len(ticks_after) >= 5, "the loop kept ticking (and sending nothing) until the deadline"
    finally:
        env.close()


@pytest.mark.parametrize("turn_based", [False, True])
def test_delta_action_is_applied_on_every_tick_in_real_time(turn_based: bool) -> None:
    # delta mode: real time applies the delta again on each of the cycle's 8 ticks (a joint velocity);
    # the turn-based baseline applies it once per step
    env = gym.make("uniros/Rx200Reach-v0", clock="sim", action_mode="delta", delta_coeff=0.05, turn_based=turn_based)
    try:
        obs, _ = env.reset(seed=0)
        q0 = obs[7:12].copy()
        a = np.array([0.1, 0, 0, 0, 0], np.float32)  # waist: 0.1 x 0.05 x pi = 0.0157 rad per application
        for _ in range(2):
            obs, *_ = env.step(a)
        moved = float(obs[7] - q0[0])
    finally:
        env.close()
    if turn_based:
        assert 0.025 < moved < 0.04, moved  # two applications
    else:
        assert 0.2 < moved < 0.3, moved  # ~16 applications (the servo lags the first ticks)


def test_reset_after_success_moves_an_arm_home_that_cannot_be_teleported() -> None:
    # the emulated arm walks home; while it does, the old goal is still set and may be passed again: that must not
    # end an episode (the arm would hold where it is and never settle home)
    env = gym.make(
        "uniros/Rx200Reach-v0", robot="emulated-real", clock="sim", action_cycle_s=0.8, action_mode="absolute"
    )
    u = env.unwrapped
    try:
        for seed in (3, 4):
            _, info = drive_to_goal(env, seed=seed, max_steps=12)
            assert info["is_success"] and u._ended
            obs, _ = env.reset(seed=seed + 10)
            assert not u._ended
            assert np.max(np.abs(obs[7:12] - u.home_q)) < u.config.settle_tol_rad
    finally:
        env.close()


@pytest.mark.parametrize("action_mode", ["absolute", "delta"])
def test_unsafe_action_projected_sends_its_safe_part(action_mode: str) -> None:
    # unsafe_action="project": a target through the table is not refused whole; the joints that can move safely
    # do (here the waist and wrist), the arm never goes below the margin, and the step says so
    env = gym.make(
        "uniros/Rx200Reach-v0", clock="sim", action_cycle_s=0.8, action_mode=action_mode, unsafe_action="project"
    )
    u = env.unwrapped
    try:
        obs, _ = env.reset(seed=0)
        q0 = obs[7:12].copy()
        if action_mode == "absolute":
            q = np.array([0.5, 1.9, 1.5, 1.5, 0.8])  # shoulder and elbow through the table, waist and wrist fine
            assert u.safety.check(q) is not None
            a = (2 * (q - u._lower) / (u._upper - u._lower) - 1).astype(np.float32)
        else:
            a = np.array([0.5, 1.0, 1.0, 1.0, 0.5], np.float32)  # forward and down, every tick
        moved = []
        for _ in range(6):
            obs, reward, terminated, _, info = env.step(a)
            q_now = obs[7:12].astype(np.float64)
            assert u.kin.table_clearance_m(q_now) > 0, "never below the table"
            moved.append(float(np.max(np.abs(q_now - q0))))
            if info.get("action_projected"):
                break
        assert info["action_projected"] and info["not_executable"] and "unsafe_reason" not in info
        assert reward <= -5.0  # the dense reward still charges an action that could not be executed as given
        assert abs(obs[7] - q0[0]) > 0.2, "the waist (a safe joint) moved although the whole target was unsafe"
    finally:
        env.close()


def test_unsafe_action_setting_is_checked() -> None:
    with pytest.raises(ConfigError, match=r"unsafe_action: expected one of 'hold', 'project', got 'clip'"):
        gym.make("uniros/Rx200Reach-v0", unsafe_action="clip")


def test_a_hold_never_commands_past_a_joint_limit() -> None:
    """The arm holds where it measures itself; sensor noise or overshoot can put a joint a hair past a limit it sits
    at, and the hold target is then that limit (a real driver may refuse a command past it)."""
    env = gym.make("uniros/Rx200Reach-v0", clock="sim")
    try:
        u = env.unwrapped
        lo, hi = u.safety.lower, u.safety.upper
        measured = np.array([hi[0] + 3e-3, lo[1] - 1e-4, 0.2, hi[3] + 1e-6, 0.0])
        hold = u._hold_target(measured)
        np.testing.assert_array_equal(hold, [hi[0], lo[1], 0.2, hi[3], 0.0])
        assert u.safety.check(hold) is None or "limit" not in u.safety.check(hold)
    finally:
        env.close()


def test_registered_defaults_are_joint_deltas_and_uniros_goal_box() -> None:
    """``gym.make(id)`` gives joint-delta actions, the dense reward and UniROS's goal box (the defaults that learn,
    docs/results.md); UniROS's absolute joint targets stay one keyword away."""
    from uniros_async.tasks.reach import GOAL_BOXES

    for env_id, arm in (("uniros/Rx200Reach-v0", "rx200"), ("uniros/Ned2Reach-v0", "ned2")):
        env = gym.make(env_id, clock="sim")
        try:
            u = env.unwrapped
            assert (u.action_mode, u.reward_type, u.goal_space) == ("delta", "dense", "uniros-box")
            np.testing.assert_array_equal(u.goal_min, GOAL_BOXES[arm][0])
            np.testing.assert_array_equal(u.goal_max, GOAL_BOXES[arm][1])
        finally:
            env.close()
    env = gym.make("uniros/Rx200Reach-v0", clock="sim", action_mode="absolute")
    try:
        assert env.unwrapped.action_mode == "absolute"
    finally:
        env.close()


@pytest.mark.parametrize("env_id", ["uniros/Rx200Reach-v0", "uniros/Ned2ReachGoal-v0"])
def test_workspace_goals_cover_the_reachable_workspace(env_id: str) -> None:
    """``goal_space="workspace"``: goals spread over the whole workspace box (far beyond UniROS's box), each one
    the arm can reach (its IK solution is safe and puts the EE on the goal)."""
    from uniros_async.tasks.reach import GOAL_BOXES, WORKSPACE_BOXES

    arm = "rx200" if "Rx200" in env_id else "ned2"
    env = gym.make(env_id, clock="sim", goal_space="workspace")
    try:
        u = env.unwrapped
        np.testing.assert_array_equal(u.goal_min, WORKSPACE_BOXES[arm][0])
        np.testing.assert_array_equal(u.goal_max, WORKSPACE_BOXES[arm][1])
        rng = np.random.default_rng(0)
        goals = np.array([u.sample_goal(rng) for _ in range(60)])
        assert np.all(goals >= u.goal_min) and np.all(goals <= u.goal_max)
        uniros_max = np.asarray(GOAL_BOXES[arm][1])
        assert np.any(goals[:, 0] > uniros_max[0] + 0.05) and np.any(np.abs(goals[:, 1]) > uniros_max[1] + 0.1)
        for g in goals[:10]:
            q, ok = u.kin.ik(g, rng=rng)
            assert ok and u.safety.check(q) is None
            assert np.linalg.norm(u.kin.ee_position(q) - g) < 1e-3
        env.reset(seed=1)
        assert np.all(u.goal >= u.goal_min) and np.all(u.goal <= u.goal_max)
    finally:
        env.close()


def test_goal_space_and_an_unreachable_box_are_clear_errors() -> None:
    with pytest.raises(ConfigError, match=r"goal_space: expected one of 'uniros-box', 'workspace', got 'room'"):
        gym.make("uniros/Rx200Reach-v0", clock="sim", goal_space="room")
    env = gym.make("uniros/Rx200Reach-v0", clock="sim", goal_min=[2.0, 2.0, 2.0], goal_max=[2.1, 2.1, 2.1], goal_pool=0)
    try:
        with pytest.raises(ConfigError, match="no reachable goal in the box"):
            env.unwrapped.sample_goal(np.random.default_rng(0), max_tries=5)
    finally:
        env.close()
