"""Shared fixtures for the robot model and kinematics tests: one spec, MuJoCo model and Kinematics per arm.

The arms are the registered ones and ``acme5``, which a user's own package (tests/extension/acme_arms) registers
from outside uniros_async: it must pass every test the built-in arms pass."""

from __future__ import annotations

import mujoco
import pytest

from uniros_async.kinematics import Kinematics
from uniros_async.robots import ROBOT_NAMES, RobotSpec, get_robot_spec

USER_ROBOT = "acme_arms:acme5"  # imported when the fixture runs, not at collection
ROBOTS = [*sorted(set(ROBOT_NAMES) - {"acme5"}), USER_ROBOT]


@pytest.fixture(scope="session", params=ROBOTS)
def spec(request: pytest.FixtureRequest) -> RobotSpec:
    return get_robot_spec(request.param)


@pytest.fixture(scope="session")
def mj_model(spec: RobotSpec) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(spec.mjcf_path))


@pytest.fixture(scope="session")
def kin(spec: RobotSpec) -> Kinematics:
    return Kinematics.from_spec(spec)
