"""``robot="dxl://..."``: the servos' present currents, loads and temperatures in the env's info, against what the
virtual servos of ``uniros robot vbus`` hold in their registers (read, and warmed, over its control lines)."""

from __future__ import annotations

import time

import gymnasium as gym
import numpy as np
import pytest

import uniros_async
from uniros_async.hardware.dxl.control_table import XM430_W350

from ._vbus import MARGIN_MS, Vbus, running_vbus

pytestmark = pytest.mark.slow

ARM_AND_GRIPPER = {"waist", "shoulder", "elbow", "wrist_angle", "wrist_rotate", "gripper"}
CURRENT_MA_PER_UNIT = (XM430_W350.current_unit_a or 0.0) * 1e3
SERVO_KEYS = ("servo_current_ma", "servo_load_pct", "servo_temperature_c")


def _register(vbus: Vbus, servo_id: int, name: str) -> int:
    answer = vbus.send(f"get {servo_id} {name}")
    assert answer.startswith(f"ok get {servo_id} {name} "), answer
    return int(answer.rsplit(" ", 1)[1])


def _still(env: gym.Env, steps: int = 6) -> dict:
    """Zero actions (joint deltas: hold) until the arm no longer moves; the last step's info."""
    action = np.zeros(env.action_space.shape, dtype=np.float32)
    info: dict = {}
    for _ in range(steps):
        *_, info = env.step(action)
    return info


def test_info_carries_the_servos_currents_loads_and_temperatures_and_they_update() -> None:
    with running_vbus() as vbus:
        env = gym.make(
            "uniros/Rx200Reach-v0",
            robot=f"dxl://{vbus.path}?map=rx200&margin_ms={MARGIN_MS}&profile_ms=0",
            action_cycle_s=0.1,
        )
        try:
            _, info = env.reset(seed=0)
            # the XM430s sense current, the XL430s report load; every arm and gripper servo has a temperature
            assert set(info["servo_current_ma"]) == {"shoulder", "elbow"}, info
            assert set(info["servo_load_pct"]) == {"waist", "wrist_angle", "wrist_rotate", "gripper"}, info
            assert info["servo_temperature_c"] == dict.fromkeys(ARM_AND_GRIPPER, 30.0), info

            # holding at home under gravity: the info's values are the registers' (read right after the step),
            # in mA (2.69 mA a unit on the XM430) and % (0.1 % a unit)
            info = _still(env)
            shoulder = _register(vbus, 2, "present_current") * CURRENT_MA_PER_UNIT
            elbow = _register(vbus, 4, "present_current") * CURRENT_MA_PER_UNIT
            wrist = _register(vbus, 5, "present_load") / 10.0
            assert abs(shoulder) > 5 * CURRENT_MA_PER_UNIT, f"the shoulder carries the arm: {shoulder} mA"
            assert info["servo_current_ma"]["shoulder"] == pytest.approx(shoulder, abs=3 * CURRENT_MA_PER_UNIT)
            assert info["servo_current_ma"]["elbow"] == pytest.approx(elbow, abs=3 * CURRENT_MA_PER_UNIT)
            assert info["servo_load_pct"]["wrist_angle"] == pytest.approx(wrist, abs=0.3)

            # the shoulder lifts: its current follows the load it carries
            action = np.zeros(env.action_space.shape, dtype=np.float32)
            action[1] = env.action_space.low[1]
            currents = [info["servo_current_ma"]["shoulder"]]
            for _ in range(4):
                *_, step_info = env.step(action)
                currents.append(step_info["servo_current_ma"]["shoulder"])
            info = _still(env)
            moved = _register(vbus, 2, "present_current") * CURRENT_MA_PER_UNIT
            assert len(set(currents)) > 2, f"the shoulder's current in info did not change: {currents}"
            assert abs(moved - shoulder) > 3 * CURRENT_MA_PER_UNIT, (shoulder, moved)
            assert info["servo_current_ma"]["shoulder"] == pytest.approx(moved, abs=3 * CURRENT_MA_PER_UNIT)

            # the elbow warms up: the info says so within the temperature's read period (1 s) and a step
            assert vbus.send("temperature 4 55") == "ok temperature 4 55"
            t0 = time.monotonic()
            action = np.zeros(env.action_space.shape, dtype=np.float32)
            while True:
                *_, info = env.step(action)
                if info["servo_temperature_c"]["elbow"] == 55.0:
                    break
                assert time.monotonic() - t0 < 2.0, f"no 55 degC in info within 2 s: {info['servo_temperature_c']}"
            assert info["servo_temperature_c"] == {**dict.fromkeys(ARM_AND_GRIPPER, 30.0), "elbow": 55.0}
            # a reset's info has them too
            _, info = env.reset(seed=1)
            assert info["servo_temperature_c"]["elbow"] == 55.0 and set(info["servo_current_ma"]) == {
                "shoulder",
                "elbow",
            }
        finally:
            env.close()


def test_a_vector_env_gets_them_from_its_bus_arm_only() -> None:
    with running_vbus() as vbus:
        assert vbus.send("temperature 1 41") == "ok temperature 1 41"
        envs = uniros_async.make_vec(
            [
                ("uniros/Rx200Reach-v0", {"robot": f"dxl://{vbus.path}?map=rx200&margin_ms={MARGIN_MS}"}),
                ("uniros/Rx200Reach-v0", {"robot": "sim"}),
            ]
        )
        try:
            _, infos = envs.reset(seed=2)
            _, _, _, _, step_infos = envs.step(np.zeros(envs.action_space.shape, dtype=np.float32))
            for info in (infos, step_infos):
                for key in SERVO_KEYS:  # the bus arm's member has them; the sim's info has no such keys
                    assert info[f"_{key}"].tolist() == [True, False], (key, info[f"_{key}"])
                assert info["servo_temperature_c"]["waist"][0] == 41.0
                assert info["servo_temperature_c"]["gripper"][0] == 30.0
                assert set(info["servo_current_ma"]) == {"shoulder", "elbow", "_shoulder", "_elbow"}
        finally:
            envs.close()
    # a single sim env's info: none of the servo keys
    env = gym.make("uniros/Rx200Reach-v0", robot="sim")
    try:
        _, info = env.reset(seed=0)
        *_, step_info = env.step(np.zeros(env.action_space.shape, dtype=np.float32))
        assert not set(SERVO_KEYS) & (set(info) | set(step_info)), (info, step_info)
    finally:
        env.close()
