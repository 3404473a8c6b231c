"""Servo maps: the rx200's follows Interbotix's rx200.yaml; maps are registered as robots are, so a user's own
Dynamixel arm is a map in their own package."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from uniros_async.errors import ConfigError
from uniros_async.hardware.dxl.servo_map import (
    ServoConfig,
    ServoGroup,
    ServoMap,
    register_servo_map,
    servo_map,
    servo_map_names,
)

RX200 = servo_map("rx200")


def test_the_rx200_map_is_rx200_yaml() -> None:
    rows = {
        s.id: (s.joint, s.model, s.drive_mode, s.secondary_id, s.min_position, s.max_position) for s in RX200.servos
    }
    assert rows == {
        1: ("waist", "XL430-W250", 0, None, 0, 4095),
        2: ("shoulder", "XM430-W350", 0, None, 819, 3333),
        3: ("shoulder", "XM430-W350", 1, 2, 819, 3333),
        4: ("elbow", "XM430-W350", 1, None, 819, 3106),
        5: ("wrist_angle", "XL430-W250", 1, None, 910, 3447),
        6: ("wrist_rotate", "XL430-W250", 0, None, 0, 4095),
        7: ("gripper", "XL430-W250", 0, None, 0, 4095),
    }
    assert all(s.velocity_limit == 131 and s.return_delay_time == 0 for s in RX200.servos)
    assert RX200.baud == 1_000_000
    arm, gripper = RX200.groups
    assert (arm.operating_mode, arm.profile, arm.profile_velocity, arm.profile_acceleration) == (
        "position",
        "time",
        2000,
        300,
    )
    assert gripper.operating_mode == "pwm"
    # the host's Drive_Mode: the servo's reverse bit and its group's time-profile bit
    assert [RX200.drive_mode(s) for s in RX200.servos] == [4, 4, 5, 5, 5, 4, 0]
    eeprom = RX200.eeprom(RX200.by_id(3))
    assert eeprom["secondary_id"] == 2 and eeprom["operating_mode"] == 3
    assert RX200.eeprom(RX200.by_id(7))["operating_mode"] == 16
    assert RX200.primary("shoulder").id == 2


def test_the_arm_profile_is_a_map_setting() -> None:
    assert (RX200.arm.profile, RX200.arm.profile_velocity, RX200.arm.profile_acceleration) == ("time", 2000, 300)
    none = RX200.with_arm_profile(0)  # each goal at the servos' full speed, as the servo sim moves to a command
    assert (none.arm.profile, none.arm.profile_velocity, none.arm.profile_acceleration) == ("time", 0, 0)
    assert none.groups[1:] == RX200.groups[1:] and none.servos == RX200.servos
    assert none.eeprom(none.by_id(1)) == RX200.eeprom(RX200.by_id(1))  # the profile is RAM: no EEPROM write
    half = RX200.with_arm_profile(500)
    assert (half.arm.profile_velocity, half.arm.profile_acceleration) == (500, 250)  # acceleration <= half
    assert RX200.arm.profile_velocity == 2000  # the registered map is untouched
    for bad in (-1, 40000, 1.5, True):
        with pytest.raises(ConfigError, match=r"profile_ms must be an integer in 0\.\.32767"):
            RX200.with_arm_profile(bad)  # type: ignore[arg-type]


def test_lookups_that_miss_name_the_closest() -> None:
    with pytest.raises(
        ConfigError, match=r"unknown servo map 'rx20' \(did you mean 'rx200'\?\); registered: .*'rx200'"
    ):
        servo_map("rx20")
    with pytest.raises(ConfigError, match=r"servo map 'rx200' has no servo ID 9; IDs: \[1, 2, 3, 4, 5, 6, 7\]"):
        RX200.by_id(9)
    with pytest.raises(ConfigError, match=r"no servo for joint 'wrist'"):
        RX200.primary("wrist")


def test_bad_maps_are_refused_with_what_is_wrong() -> None:
    servo = RX200.servos[0]
    with pytest.raises(ConfigError, match=r"ID 1 is used by 'waist' and 'elbow'"):
        dataclasses.replace(RX200, servos=(*RX200.servos, dataclasses.replace(servo, joint="elbow")))
    with pytest.raises(ConfigError, match=r"shadow ID 8 has secondary_id 6, which must be the ID of the primary servo"):
        dataclasses.replace(
            RX200, servos=(*RX200.servos, ServoConfig(id=8, joint="shoulder", model="XM430-W350", secondary_id=6))
        )
    with pytest.raises(ConfigError, match=r"unknown model 'XM540'"):
        ServoConfig(id=1, joint="waist", model="XM540")
    with pytest.raises(ConfigError, match=r"expected 0 <= min_position < max_position <= 4095"):
        ServoConfig(id=1, joint="waist", model="XL430-W250", min_position=3000, max_position=2000)
    with pytest.raises(ConfigError, match=r"group 'arm' names joint 'hand', which has no primary servo"):
        dataclasses.replace(RX200, groups=(ServoGroup(name="arm", joints=("hand",)),))
    with pytest.raises(ConfigError, match=r"bus_watchdog_ms must be a multiple of 20"):
        dataclasses.replace(RX200, bus_watchdog_ms=90)


def test_register_servo_map_same_again_is_a_no_op_another_is_refused() -> None:
    mine = dataclasses.replace(RX200, name="rx200-test-map")
    register_servo_map(mine)
    register_servo_map(mine)
    assert servo_map("rx200-test-map") is mine
    assert "rx200-test-map" in servo_map_names()
    with pytest.raises(ConfigError, match=r"servo map 'rx200-test-map' is already registered.*override=True"):
        register_servo_map(dataclasses.replace(mine, baud=57_600))
    register_servo_map(dataclasses.replace(mine, baud=57_600), override=True)
    assert servo_map("rx200-test-map").baud == 57_600
    with pytest.raises(ConfigError, match=r"an entry point needs name="):
        register_servo_map("my_pkg.servos:MAP")


@pytest.mark.slow
def test_a_users_own_arm_on_the_virtual_bus_in_an_env() -> None:
    """acme_arms' Acme5, whose servo map lives in a module of the user's (tests/dxl/_acme_servos.py): the vbus and
    the env find it by ``module:name``."""
    import gymnasium as gym

    from ._vbus import MARGIN_MS, running_vbus

    from_module = servo_map("dxl._acme_servos:acme5")
    assert isinstance(from_module, ServoMap) and from_module.ids == (11, 12, 13, 14, 15)
    with running_vbus(
        servos="dxl._acme_servos:acme5", pythonpath=str(Path(__file__).resolve().parents[1] / "extension")
    ) as vbus:
        env = gym.make(
            "acme_arms:acme/Acme5Reach-v0",
            robot=f"dxl://{vbus.path}?map=dxl._acme_servos:acme5&margin_ms={MARGIN_MS}",
            action_cycle_s=0.2,
        )
        try:
            obs, _ = env.reset(seed=0)
            action = np.zeros(env.action_space.shape, dtype=np.float32)
            action[0] = env.action_space.high[0]
            q0 = float(obs[7])
            for _ in range(5):
                obs, *_ = env.step(action)
            assert float(obs[7]) - q0 > 0.02, (q0, obs[7])
        finally:
            env.close()


def test_vbus_cli_without_a_map_name_is_an_argparse_error() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "uniros_async.cli", "robot", "vbus"], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 2 and "servo_map" in done.stderr
