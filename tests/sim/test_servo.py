"""ServoSim, the synchronous servo core: profiles, limits, bad input, watchdog, modes, divergence (real MuJoCo)."""

from __future__ import annotations

import numpy as np
import pytest

from uniros_async.bus.messages import Header, JointCommand
from uniros_async.errors import ConfigError, SimulationError
from uniros_async.robots import get_robot_spec
from uniros_async.sim.servo import ServoSim, ServoSimConfig

GOALS = {
    "rx200": np.array([0.5, 0.3, -0.4, 0.6, 1.0]),
    "ned2": np.array([0.5, -0.3, 0.4, 0.6, -0.5, 1.0]),
}
TOL_RAD = 0.03  # servo steady-state error under gravity (the MJCF targets < 0.015 rad) plus friction


def cmd(q, *, duration_s: float = 0.0, velocity=None) -> JointCommand:  # type: ignore[no-untyped-def]
    return JointCommand(
        header=Header(),
        position=np.asarray(q, dtype=np.float64),
        duration_s=duration_s,
        velocity=None if velocity is None else np.asarray(velocity, dtype=np.float64),
    )


def run_s(sim: ServoSim, seconds: float, command: JointCommand | None = None):  # type: ignore[no-untyped-def]
    state = sim.tick(command)
    for _ in range(round(seconds / (sim.period_ns / 1e9))):
        state = sim.tick()
    return state


@pytest.mark.parametrize("robot", ["rx200", "ned2"])
def test_position_command_reaches_target(robot: str) -> None:
    sim = ServoSim(robot)
    spec = get_robot_spec(robot)
    assert sim.period_ns == round(1e9 / spec.hardware_rate_hz)
    assert sim.n_substeps == {"rx200": 50, "ned2": 20}[robot]
    state = run_s(sim, 2.5, cmd(GOALS[robot]))
    assert state.name == spec.joint_state_names
    assert state.position.shape == state.velocity.shape == state.effort.shape == (len(spec.joint_state_names),)
    err = np.abs(state.position[: spec.n_arm_joints] - GOALS[robot])
    assert err.max() < TOL_RAD, f"{robot} missed its goal by {err}"
    assert np.abs(state.velocity[: spec.n_arm_joints]).max() < 0.05, "settled"
    assert sim.stats.commands == 1 and sim.stats.rejected == 0


def test_tick_reads_before_it_writes_and_stamps_sim_time() -> None:
    sim = ServoSim("rx200")
    first = sim.tick(cmd(GOALS["rx200"]))
    assert first.header.stamp_ns == 0 and np.allclose(first.position[:5], 0.0), "the state at the tick, before cmd"
    second = sim.tick()
    assert second.header.stamp_ns == 100_000_000 and sim.time_ns == 100_000_000
    assert np.abs(second.position[:5]).max() > 0.05, "the command acted during the period"


@pytest.mark.parametrize("robot", ["rx200", "ned2"])
def test_time_based_profile_takes_its_duration(robot: str) -> None:
    sim = ServoSim(robot)
    goal = GOALS[robot] * 0.5
    rate = get_robot_spec(robot).hardware_rate_hz
    sim.tick(cmd(goal, duration_s=1.0))
    half = [sim.tick().position[: len(goal)] for _ in range(round(0.5 * rate))][-1]
    frac = half / goal
    assert np.all((frac > 0.3) & (frac < 0.75)), f"half way through a 1 s move: {frac}"
    for _ in range(round(0.5 * rate)):
        sim.tick(cmd(goal, duration_s=1.0))  # an action repeat does not restart the profile
    state = run_s(sim, 1.0)
    assert np.abs(state.position[: len(goal)] - goal).max() < TOL_RAD


def test_commands_outside_limits_are_clipped_and_counted() -> None:
    sim = ServoSim("rx200")
    far = np.array([10.0, -10.0, 10.0, -10.0, 10.0])
    lower, upper = np.array(sim.robot.joint_lower_rad), np.array(sim.robot.joint_upper_rad)
    sim.tick(cmd(far))
    assert sim.stats.clipped == 1 and sim.stats.clipped_values == 5
    assert np.array_equal(sim.goal, np.clip(far, lower, upper))
    for _ in range(40):
        sim.tick()
        assert np.all(sim.target >= lower) and np.all(sim.target <= upper), "a servo target past a limit"
        q = sim.qpos
        assert np.all(q >= lower - 0.02) and np.all(q <= upper + 0.02)


@pytest.mark.parametrize(
    ("bad", "why"),
    [
        ([0.1, np.nan, 0.0, 0.0, 0.0], "non-finite"),
        ([0.1, 0.2, 0.3], "expected 5 or 6"),
        ([0.1, np.inf, 0.0, 0.0, 0.0], "non-finite"),
    ],
)
def test_bad_commands_are_rejected_and_the_arm_holds(bad, why: str) -> None:  # type: ignore[no-untyped-def]
    sim = ServoSim("rx200")
    run_s(sim, 0.5, cmd([0.2, 0.1, 0.1, 0.0, 0.0]))
    goal_before = sim.goal
    sim.tick(cmd(bad))
    assert sim.stats.rejected == 1
    assert why in sim.stats.last_error and "rx200" in sim.stats.last_error
    assert np.array_equal(sim.goal, goal_before), "a rejected command must not move the goal"
    state = run_s(sim, 0.5)
    assert np.abs(state.position[:5] - goal_before).max() < TOL_RAD


def test_gripper_value_is_optional_and_clipped() -> None:
    sim = ServoSim("rx200")
    run_s(sim, 1.0, cmd([0, 0, 0, 0, 0, 0.5]))  # a gripper target far past its 0.037 m limit
    assert sim.stats.clipped == 1 and sim.stats.rejected == 0
    gripper = sim.model.actuator("gripper").id
    assert sim.data.ctrl[gripper] == pytest.approx(0.037), "the gripper servo target is clipped to its range"
    # (where the fingers get to is the model's business: see the report on the horn joint's friction)


def test_watchdog_holds_when_commands_stop() -> None:
    sim = ServoSim("rx200", ServoSimConfig(command_timeout_s=0.3, mode="velocity"))
    sim.tick(cmd(np.zeros(5), velocity=[0.5, 0, 0, 0, 0]))
    for _ in range(3):
        sim.tick()
    assert sim.stats.watchdog_holds == 0
    for _ in range(3):
        sim.tick()
    assert sim.stats.watchdog_holds == 1, "no command for > 0.3 s: hold"
    held = sim.target.copy()
    state = run_s(sim, 0.5)
    assert np.array_equal(sim.target, held), "the held target stays"
    assert abs(state.velocity[0]) < 0.05
    assert sim.stats.watchdog_holds == 1, "counted once per stale episode"
    sim.tick(cmd(np.zeros(5), velocity=[-0.5, 0, 0, 0, 0]))
    sim.tick()
    assert sim.target[0] < held[0], "a new command resumes"


def test_watchdog_waits_for_the_commanded_duration() -> None:
    sim = ServoSim("rx200", ServoSimConfig(command_timeout_s=0.2))
    sim.tick(cmd(GOALS["rx200"], duration_s=2.0))
    state = run_s(sim, 2.5)
    assert sim.stats.watchdog_holds == 1
    assert np.abs(state.position[:5] - GOALS["rx200"]).max() < TOL_RAD, "the long move was not cut short"


def test_velocity_mode_and_hold_stop_modes() -> None:
    sim = ServoSim("ned2", ServoSimConfig(mode="velocity"))
    sim.tick(cmd(np.zeros(6)))  # no velocity given
    assert sim.stats.rejected == 1 and "velocity mode needs" in sim.stats.last_error
    run_s(sim, 0.4, cmd(np.zeros(6), velocity=[0.5, 0, 0, 0, 0, 0]))
    assert 0.15 < sim.qpos[0] < 0.25
    sim.stop()
    run_s(sim, 0.3)
    stopped = sim.qpos[0]
    sim.tick(cmd(np.zeros(6), velocity=[1.0] * 6))
    assert sim.stats.ignored == 1
    run_s(sim, 0.3)
    assert abs(sim.qpos[0] - stopped) < 0.01 and sim.mode == "stop"
    sim.set_mode("position")
    run_s(sim, 1.5, cmd(np.zeros(6)))
    assert abs(sim.qpos[0]) < TOL_RAD
    sim.hold()
    sim.tick(cmd(GOALS["ned2"]))
    assert sim.stats.ignored == 2 and sim.mode == "hold"
    with pytest.raises(ConfigError, match="mode"):
        sim.set_mode("dance")


def test_reset_teleports_and_validates() -> None:
    sim = ServoSim("ned2")
    run_s(sim, 0.5, cmd(GOALS["ned2"]))
    state = sim.reset([0.1, -0.2, 0.3, 0.0, 0.0, 0.0])
    assert np.allclose(state.position, [0.1, -0.2, 0.3, 0.0, 0.0, 0.0]) and sim.time_ns == 0
    state = run_s(sim, 0.5)
    assert np.allclose(state.position, [0.1, -0.2, 0.3, 0.0, 0.0, 0.0], atol=TOL_RAD), "no stale goal after reset"
    with pytest.raises(ConfigError, match="outside the joint limits"):
        sim.reset([3.0, 0, 0, 0, 0, 0])
    with pytest.raises(ConfigError, match="expected 6"):
        sim.reset([0.0])


def test_divergence_raises_simulation_error_until_reset() -> None:
    sim = ServoSim("rx200")
    sim.tick()
    sim.data.qvel[:] = 1e30
    with pytest.raises(SimulationError, match="diverged"):
        sim.tick()
    with pytest.raises(SimulationError, match="reset"):
        sim.tick()
    sim.reset()
    sim.tick()
    sim.tick()


def test_config_validation_names_the_field() -> None:
    with pytest.raises(ConfigError, match="physics_dt_s"):
        ServoSimConfig(physics_dt_s=0.0)
    with pytest.raises(ConfigError, match="control_period_s.*whole multiple"):
        ServoSimConfig(control_period_s=0.0033)
    with pytest.raises(ConfigError, match="command_timeout_s"):
        ServoSimConfig(command_timeout_s=-1.0)
    with pytest.raises(ConfigError, match="mode"):
        ServoSimConfig(mode="torque")
    with pytest.raises(ConfigError, match="unknown robot"):
        ServoSim("ur5")
    assert ServoSim("rx200", ServoSimConfig(control_period_s=0.02)).n_substeps == 10
