"""The ROS driver defaults registry, and the ROS 1 bridge's config reading it (no ROS master needed)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from uniros_async.adapters.drivers import register_ros_driver, ros_driver_defaults, ros_drivers
from uniros_async.adapters.ros1_bridge import Ros1BridgeConfig
from uniros_async.errors import ConfigError


def test_the_built_in_arms_have_their_ros1_drivers() -> None:
    rx200 = ros_driver_defaults("ros1", "rx200")
    assert rx200 is not None and rx200.driver == "xs_sdk"
    assert rx200.as_settings() == {
        "joint_states": "/rx200/joint_states",
        "command": "/rx200/commands/joint_group",
        "command_type": "interbotix_xs_msgs/JointGroupCommand",
        "group": "arm",
    }
    ned2 = ros_driver_defaults("ros1", "ned2")
    assert ned2 is not None and ned2.command_type == "trajectory_msgs/JointTrajectory"
    assert {d.robot for d in ros_drivers("ros1")} >= {"rx200", "ned2"}
    assert ros_driver_defaults("ros2", "no-such-arm") is None


def test_the_bridge_config_takes_the_default_driver_or_a_named_one() -> None:
    cfg = Ros1BridgeConfig(robot="rx200")
    assert (cfg.joint_states, cfg.command, cfg.group) == ("/rx200/joint_states", "/rx200/commands/joint_group", "arm")
    register_ros_driver(
        "ros1",
        "rx200",
        driver="test_ros_control",
        joint_states="/joint_states",
        command="/arm_controller/command",
        command_type="std_msgs/Float64MultiArray",
    )
    assert ros_driver_defaults("ros1", "rx200").driver == "xs_sdk"  # type: ignore[union-attr]  # still the default
    other = Ros1BridgeConfig(robot="rx200", driver="test_ros_control", command="/mine")
    assert (other.joint_states, other.command, other.command_type) == (
        "/joint_states",
        "/mine",  # a setting given wins over the driver's
        "std_msgs/Float64MultiArray",
    )
    with pytest.raises(ConfigError, match=r"did you mean 'test_ros_control'\?\); registered: \["):
        Ros1BridgeConfig(robot="rx200", driver="test_ros_contrl")


def test_a_driver_that_is_not_registered_is_named() -> None:
    with pytest.raises(ConfigError, match="no ros1 driver 'nope' is registered for 'ned2'"):
        ros_driver_defaults("ros1", "ned2", "nope")


def test_registration_rules() -> None:
    kw = {"joint_states": "/js", "command": "/cmd", "command_type": "std_msgs/Float64MultiArray"}
    first = register_ros_driver("ros2", "test-arm", driver="a", **kw)
    assert register_ros_driver("ros2", "test-arm", driver="a", **kw) == first
    register_ros_driver("ros2", "test-arm", driver="b", default=True, **kw)
    assert ros_driver_defaults("ros2", "test-arm").driver == "b"  # type: ignore[union-attr]
    with pytest.raises(ConfigError, match="already registered"):
        register_ros_driver("ros2", "test-arm", driver="a", **{**kw, "command": "/other"})
    with pytest.raises(ConfigError, match="ROS version"):
        register_ros_driver("ros3", "test-arm", driver="a", **kw)
    with pytest.raises(ConfigError, match="absolute topic"):
        register_ros_driver("ros2", "test-arm", driver="c", **{**kw, "joint_states": "js"})
    with pytest.raises(ConfigError, match="package/Type"):
        register_ros_driver("ros2", "test-arm", driver="c", **{**kw, "command_type": "Float64MultiArray"})


def test_the_registry_imports_no_ros_code() -> None:
    code = (
        "import sys, uniros_async.adapters.drivers\n"
        "bad = [m for m in sys.modules if m.startswith(('uniros_async.adapters.ros1', 'rospy'))]\n"
        "assert not bad, bad\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 0, out.stderr
