"""Shared fixtures for the robot model and kinematics tests: one spec, MuJoCo model and Kinematics per arm."""

from __future__ import annotations

import mujoco
import pytest

from uniros_async.kinematics import Kinematics
from uniros_async.robots import ROBOT_NAMES, RobotSpec, get_robot_spec


@pytest.fixture(scope="session", params=ROBOT_NAMES)
def spec(request: pytest.FixtureRequest) -> RobotSpec:
    return get_robot_spec(request.param)


@pytest.fixture(scope="session")
def mj_model(spec: RobotSpec) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(spec.mjcf_path))


@pytest.fixture(scope="session")
def kin(spec: RobotSpec) -> Kinematics:
    return Kinematics.from_spec(spec)
