"""Each imperfection knob does what it says, measured on the sim (real MuJoCo; the bus-side knobs on a real bus)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from uniros_async.bus import open_domain, open_node, reliable
from uniros_async.bus.messages import Header, JointCommand, JointState
from uniros_async.errors import ConfigError
from uniros_async.sim.imperfections import (
    BACKLASH_RAD,
    KNOBS,
    LIMITS_VELOCITY_FACTOR,
    OFFSET_RAD,
    TICK_RAD,
    VELOCITY_UNIT_RAD_S,
    Imperfections,
)
from uniros_async.sim.node import build_sim, open_servo_sim
from uniros_async.sim.servo import ServoSim, ServoSimConfig, load_model
from uniros_async.sim_clock import SimClock

HOME = np.zeros(5)
CFG = ServoSimConfig(command_timeout_s=None)


def sim_with(knobs: dict[str, float], seed: int = 0, model: object = None) -> ServoSim:
    imp = Imperfections.of(knobs, seed=seed)
    effects = imp.servo_effects(get_spec())
    if model is None:
        sim, _ = build_sim("rx200", CFG, None, imp)
        return sim
    return ServoSim("rx200", CFG, model=model, effects=effects)  # type: ignore[arg-type]


def get_spec():  # type: ignore[no-untyped-def]
    from uniros_async.robots import get_robot_spec

    return get_robot_spec("rx200")


def command(q: np.ndarray) -> JointCommand:
    return JointCommand(header=Header(), position=np.asarray(q, dtype=np.float64))


def settle(sim: ServoSim, goal: np.ndarray, ticks: int = 30) -> JointState:
    state = sim.tick(command(goal))
    for _ in range(ticks):
        state = sim.tick()
    return state


def test_strengths_parse_and_bad_input_is_named() -> None:
    assert Imperfections.of(1.0).strengths == dict.fromkeys(KNOBS, 1.0)
    one = Imperfections.of({"backlash": 2})
    assert one["backlash"] == 2.0 and one["sag"] == 0.0 and not one.is_zero
    assert Imperfections.of(0.0).is_zero and Imperfections.of(0.0).servo_effects(get_spec()) is None
    with pytest.raises(ConfigError, match=r"unknown knob\(s\) \['backlsh'\]; expected some of"):
        Imperfections.of({"backlsh": 1.0})
    with pytest.raises(ConfigError, match=r"imperfections.noise: expected a strength in \[0, 3.0\], got 4"):
        Imperfections.of({"noise": 4})
    with pytest.raises(ConfigError, match="expected a strength"):
        Imperfections.of(float("nan"))


def _waist_hysteresis(strength: float) -> float:
    """Approach waist = 0.3 from below and from above; the width between where the joint stops."""
    sim = sim_with({"backlash": strength})
    goal = np.array([0.3, 0.0, 0.0, 0.0, 0.0])
    settle(sim, goal - [0.2, 0, 0, 0, 0])
    from_below = settle(sim, goal).position[0]
    settle(sim, goal + [0.2, 0, 0, 0, 0])
    from_above = settle(sim, goal).position[0]
    return float(from_above - from_below)


@pytest.mark.parametrize("strength", [1.0, 3.0])
def test_backlash_is_a_hysteresis_of_the_stated_width(strength: float) -> None:
    # the sim's own joint friction leaves a hysteresis too: the play adds its width on top
    extra = _waist_hysteresis(strength) - _waist_hysteresis(0.0)
    assert extra == pytest.approx(strength * BACKLASH_RAD, rel=0.1)


def test_calibration_offsets_are_a_constant_bias_of_the_stated_bound() -> None:
    plain, offset = sim_with({}), sim_with({"offsets": 2.0}, seed=3)
    offsets = offset.effects.offsets  # type: ignore[union-attr]
    assert np.all(np.abs(offsets) <= 2.0 * OFFSET_RAD) and np.abs(offsets).max() > 0.2 * OFFSET_RAD
    for goal in (np.array([0.3, 0.2, -0.3, 0.4, 0.5]), np.array([-0.5, -0.2, 0.4, -0.3, -1.0])):
        reported, reported_plain = settle(offset, goal, 50).position[:5], settle(plain, goal, 50).position[:5]
        # the servos read where they were told; the joints are off by the offsets, the same at every pose (to the
        # joints' friction band and the gravity change of so small a shift)
        assert np.abs(reported - reported_plain).max() < 1e-3
        assert np.abs((offset.qpos - plain.qpos) + offsets).max() < 1e-3


@pytest.mark.parametrize("strength", [1.0, 2.0])
def test_quantization_steps_and_deadband(strength: float) -> None:
    sim = sim_with({"quantization": strength})
    step = strength * TICK_RAD
    goal = np.array([0.31234, 0.1, -0.2, 0.3, 0.4])
    states = [settle(sim, goal, 3) for _ in range(5)]
    pos = np.array([s.position[:5] for s in states])
    vel = np.array([s.velocity[:5] for s in states])
    assert np.abs(pos / step - np.round(pos / step)).max() < 1e-6  # positions in steps of 2 pi / 4096 (x s)
    vstep = strength * VELOCITY_UNIT_RAD_S
    assert np.abs(vel / vstep - np.round(vel / vstep)).max() < 1e-6
    ctrl = sim.data.ctrl[:5]
    assert np.abs(ctrl / step - np.round(ctrl / step)).max() < 1e-6  # the goal register holds whole ticks
    before = ctrl.copy()  # the goal register (it may stay a tick short of the goal: the deadband)
    settle(sim, before + 0.4 * step, 2)  # within the deadband of s ticks: the setpoint stays
    assert np.array_equal(sim.data.ctrl[:5], before)
    settle(sim, before + 3.0 * step, 2)
    assert np.abs(sim.data.ctrl[:5] - before).min() > 2.0 * step


def _shoulder_error(strength: float, payload_kg: float) -> float:
    model = load_model(get_spec(), CFG.physics_dt_s)
    if payload_kg:
        model.body_mass[model.body("gripper_link").id] += payload_kg
    sim = sim_with({"sag": strength}, model=model)
    goal = np.array([0.0, 0.5, -0.6, 0.0, 0.0])  # the arm reaching forward: gravity loads the shoulder
    settle(sim, goal, 60)
    assert sim.data.ncon == 0  # held in the air, nothing but the servo holds it
    return abs(float(goal[1] - sim.qpos[1]))


def test_sag_is_a_steady_state_error_that_grows_with_load_and_strength() -> None:
    errors = {(s, m): _shoulder_error(s, m) for s in (0.0, 1.0) for m in (0.0, 0.2)}
    # a P controller: error = gravity torque / kp, so it grows with the load, and by 1 / kp factor with the sag
    assert errors[(1.0, 0.2)] > errors[(1.0, 0.0)] > 0
    assert errors[(1.0, 0.2)] - errors[(1.0, 0.0)] > 3.0 * (errors[(0.0, 0.2)] - errors[(0.0, 0.0)])
    factor = sim_with({"sag": 1.0}).effects.sag_factors[1]  # type: ignore[union-attr]
    assert 0.15 < factor < 0.3
    assert errors[(1.0, 0.0)] / errors[(0.0, 0.0)] == pytest.approx(1.0 / factor, rel=0.15)


def test_limits_cap_velocity_and_force() -> None:
    peaks = {}
    for s in (0.0, 2.0):
        sim = sim_with({"limits": s})
        sim.tick(command(np.array([2.0, 0.0, 0.0, 0.0, 0.0])))
        peaks[s] = max(abs(sim.tick().velocity[0]) for _ in range(8))
        if s:
            assert sim.model.actuator_forcerange[0, 1] == pytest.approx(1.4 * 0.93**s)
    assert peaks[0.0] > 0.95 * math.pi
    assert peaks[2.0] <= math.pi * LIMITS_VELOCITY_FACTOR**2 * 1.05
    assert peaks[2.0] > math.pi * LIMITS_VELOCITY_FACTOR**2 * 0.9


async def _collect(knobs: dict[str, float], n: int, seed: int = 0) -> tuple[list[tuple[int, JointState]], int]:
    """``n`` joint states of a resting rx200 with ``knobs``, with their arrival times (sim clock, real bus)."""
    clock = SimClock(time_scale=None)
    got: list[tuple[int, JointState]] = []
    async with open_domain("memory://") as domain:
        async with (
            open_servo_sim(
                "rx200",
                domain=domain,
                clock=clock,
                config=CFG,
                imperfections=Imperfections.of(knobs, seed=seed),
            ) as sim_node,
            open_node("env", domain=domain, clock=clock) as env,
        ):
            await env.create_subscription(
                JointState, "/rx200/joint_states", lambda m: got.append((clock.now_ns(), m)), qos=reliable(100)
            )
            while len(got) < n:
                await clock.sleep(1.0)
            repeated = sim_node.repeated_states
    return got[:n], repeated


async def test_state_latency_with_jitter() -> None:
    got, _ = await _collect({"latency": 2.0}, 200)
    ages = np.array([(t - m.header.stamp_ns) / 1e9 for t, m in got])
    # s = 2: 2 x (2.5 ms + U(-1, 1) ms), in order (a late state holds back the next)
    assert ages.mean() == pytest.approx(0.005, abs=0.0006)
    assert ages.min() >= 0.003 - 1e-6 and ages.max() <= 0.007 + 1e-6
    assert ages.std() > 0.0008


@pytest.mark.slow
async def test_lost_and_repeated_states_at_the_stated_rate() -> None:
    """1500 states of sim time, accelerated (about 3 s)."""
    n = 1500
    got, repeated = await _collect({"lost_states": 3.0, "noise": 1.0}, n, seed=5)
    seqs = np.array([m.header.seq for _, m in got])
    sent = int(seqs[-1] - seqs[0] + 1)
    lost = sent - n
    sigma = math.sqrt(0.03 * 0.97 / sent)
    assert abs(lost / sent - 0.03) < 4 * sigma
    # a repeated state carries a new stamp and the values of the state before it (noise makes fresh ones differ)
    same = sum(np.array_equal(a.position, b.position) for (_, a), (_, b) in zip(got, got[1:], strict=False))
    assert abs(same / n - 0.03) < 5 * sigma
    assert same <= repeated


async def test_sensor_noise_of_the_stated_size() -> None:
    got, _ = await _collect({"noise": 2.0}, 400)
    pos = np.array([m.position[:5] for _, m in got[50:]])
    vel = np.array([m.velocity[:5] for _, m in got[50:]])
    assert pos.std(axis=0) == pytest.approx(np.full(5, 2.0 * TICK_RAD), rel=0.2)
    assert vel.std(axis=0) == pytest.approx(np.full(5, 2.0 * VELOCITY_UNIT_RAD_S), rel=0.2)


def test_dynamics_scale_todays_perturbation_ranges() -> None:
    for s in (0.5, 2.0):
        emu = Imperfections.of({"dynamics": s}, seed=1).emulation()
        _, factors = build_sim("rx200", CFG, emu)
        assert np.abs(factors["mass"] - 1).max() <= 0.10 * s and np.abs(factors["mass"] - 1).max() > 0.05 * s
        assert np.abs(factors["damping"] - 1).max() <= 0.30 * s
        assert np.abs(factors["kp"] - 1).max() <= 0.15 * s and np.abs(factors["kp"] - 1).max() > 0.05 * s
    _, factors = build_sim("rx200", CFG, Imperfections.of({"dynamics": 0.0}).emulation())
    assert all(np.array_equal(f, np.ones_like(f)) for f in factors.values())


def test_the_virtual_servo_bus_has_the_servo_side_knobs() -> None:
    from uniros_async.hardware.dxl.servo_map import servo_map
    from uniros_async.hardware.dxl.vbus import VirtualBus

    plain = VirtualBus(servo_map("rx200"))
    offset = VirtualBus(servo_map("rx200"), imperfections=Imperfections.of({"offsets": 3.0, "sag": 1.0}, seed=4))
    for bus in (plain, offset):
        bus.advance(0.0)
        bus.advance(0.05)
    waist = offset.sim.effects.offsets[0]  # type: ignore[union-attr]
    # the waist servo (ID 1) reads home on both buses; on the imperfect one the joint is off by its offset
    assert offset.servos[1].get("present_position") == plain.servos[1].get("present_position")
    assert abs(waist) > 2 * TICK_RAD
    assert plain.sim.qpos[0] - offset.sim.qpos[0] == pytest.approx(waist, abs=1e-4)
    assert offset.sim.model.actuator_gainprm[1, 0] < 0.3 * plain.sim.model.actuator_gainprm[1, 0]  # sag: softer


RANGES = {"sag": (0.0, 2.0), "offsets": (0.5, 3.0), "noise": (0.0, 1.0), "dynamics": (0.0, 2.0), "latency": (0, 2)}


def test_randomization_ranges_are_checked() -> None:
    from uniros_async.sim.imperfections import Randomization

    with pytest.raises(ConfigError, match=r"randomize.sag: expected low <= high, got \[2.0, 1.0\]"):
        Randomization(ranges={"sag": (2.0, 1.0)})
    with pytest.raises(ConfigError, match=r"randomize.sag: expected \[low, high\], got 1.0"):
        Randomization(ranges={"sag": 1.0})  # type: ignore[dict-item]
    with pytest.raises(ConfigError, match=r"randomize: unknown knob\(s\) \['sagg'\]"):
        Randomization(ranges={"sagg": (0.0, 1.0)})


async def test_randomized_per_reset_seeded_and_never_accumulated() -> None:
    from uniros_async.sim.imperfections import Randomization

    async def draws(seed: int) -> list[tuple[dict[str, float], int, np.ndarray, np.ndarray]]:
        out = []
        async with open_domain("memory://") as domain:
            async with open_servo_sim(
                "rx200",
                domain=domain,
                clock=SimClock(time_scale=None),
                config=CFG,
                randomize=Randomization(ranges=RANGES, seed=seed),
            ) as node:
                for _ in range(3):
                    node.reset()
                    imp = node.imperfections
                    assert imp is not None
                    m = node.sim.model
                    out.append((dict(imp.strengths), imp.seed, m.actuator_gainprm[:5, 0].copy(), m.body_mass.copy()))
                    assert node.drawn()["strengths"] == imp.strengths
        return out

    first, again, other = await draws(1), await draws(1), await draws(2)
    for (strengths, seed, gains, masses), (s2, seed2, g2, m2) in zip(first, again, strict=True):
        assert strengths == s2 and seed == seed2 and np.array_equal(gains, g2) and np.array_equal(masses, m2)
        for knob, (lo, hi) in RANGES.items():
            assert lo <= strengths[knob] <= hi
        assert strengths["backlash"] == 0.0
        # the model of this draw is the nominal one perturbed once: the same as a sim built with these strengths
        imp = Imperfections.of(strengths, seed=seed)
        fresh, _ = build_sim("rx200", CFG, imp.emulation(), imp)
        assert np.allclose(fresh.model.actuator_gainprm[:5, 0], gains) and np.allclose(fresh.model.body_mass, masses)
    assert len({tuple(d[0].values()) for d in first}) == 3  # a new draw every episode
    assert [d[0] for d in first] != [d[0] for d in other]


@pytest.mark.slow
def test_env_keys_reach_the_sim() -> None:
    """Two short episodes of a randomized env (about 2 s)."""
    import gymnasium as gym

    kwargs = {"reward_type": "dense", "action_mode": "delta", "robot": "sim", "clock": "sim"}
    env = gym.make("uniros/Rx200Reach-v0", **kwargs, randomize={"sag": [0.0, 3.0], "latency": [1.0, 2.0]})
    try:
        for seed in (0, 1):
            env.reset(seed=seed)
            _, _, _, _, info = env.step(env.action_space.sample())
            assert "is_success" in info
    finally:
        env.close()
    with pytest.raises(ConfigError, match=r"randomize.sag: expected a list, got 2"):
        gym.make("uniros/Rx200Reach-v0", **kwargs, randomize={"sag": 2})
