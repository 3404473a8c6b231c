"""register_robot: specs and entry points from user code, lookups read at call time, refusals and close matches."""

from __future__ import annotations

import dataclasses

import pytest

import uniros_async
import uniros_async.robots as robots
from uniros_async.errors import ConfigError
from uniros_async.robots import get_robot_spec, register_robot, robot_names
from uniros_async.robots.rx200 import RX200


def test_a_spec_registered_by_user_code_is_found_everywhere_by_name() -> None:
    spec = dataclasses.replace(RX200, name="test_rx200_copy")
    register_robot(spec)
    register_robot(spec)  # again: nothing happens
    assert get_robot_spec("test_rx200_copy") is spec
    assert "test_rx200_copy" in robot_names() and "test_rx200_copy" in robots.ROBOT_NAMES  # read now, not frozen
    assert uniros_async.register_robot is register_robot
    with pytest.raises(ConfigError, match="already registered"):
        register_robot(dataclasses.replace(spec, hardware_rate_hz=20.0))
    other = dataclasses.replace(spec, hardware_rate_hz=20.0)
    register_robot(other, override=True)
    assert get_robot_spec("test_rx200_copy") is other


def test_an_entry_point_is_imported_on_first_lookup() -> None:
    register_robot("uniros_async.robots.rx200.config:RX200", name="rx200")  # what is registered already: a no-op
    register_robot(RX200)  # the spec that entry point names: also a no-op
    register_robot(f"{__name__}:_LATE", name="test_late")
    assert get_robot_spec("test_late") is _LATE
    register_robot(f"{__name__}:_LATE", name="test_misnamed")
    with pytest.raises(ConfigError, match="is the spec of 'test_late'"):
        get_robot_spec("test_misnamed")
    register_robot("no_such_module_here:ARM", name="test_missing")
    with pytest.raises(ConfigError, match="cannot load 'no_such_module_here:ARM'"):
        get_robot_spec("test_missing")


_LATE = dataclasses.replace(RX200, name="test_late")


@pytest.mark.parametrize(
    ("args", "kwargs", "match"),
    [
        (("some.module:ARM",), {}, "needs name="),
        (("no-colon",), {"name": "x"}, "'module:attribute'"),
        ((RX200,), {"name": "other"}, "differs from the spec's name"),
        ((42,), {}, "expected a RobotSpec"),
        ((dataclasses.replace(RX200, name="a/b"),), {}, "plain word"),
    ],
)
def test_malformed_registrations_are_refused(args: tuple[object, ...], kwargs: dict[str, str], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        register_robot(*args, **kwargs)  # type: ignore[arg-type]


def test_lookups_that_miss_name_the_closest_robot() -> None:
    with pytest.raises(ConfigError, match=r"unknown robot 'ned' \(did you mean 'ned2'\?\); registered: \[.*'ned2'"):
        get_robot_spec("ned")
    with pytest.raises(ConfigError, match=r"cannot import 'no_such_module_here', which should register it"):
        get_robot_spec("no_such_module_here:arm")
    with pytest.raises(ConfigError, match="unknown robot 'no_such_arm'"):
        get_robot_spec("uniros_async.robots:no_such_arm")  # the module imports but registers no such arm
