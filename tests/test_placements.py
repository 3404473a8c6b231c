"""The placement registry: lookups, registration rules, config checks, and envs importing no adapter."""

from __future__ import annotations

import contextlib
import subprocess
import sys
from collections.abc import AsyncIterator

import pytest

import uniros_async
from uniros_async.envs.config import EnvConfig
from uniros_async.errors import ConfigError
from uniros_async.placements import (
    ArmLink,
    PlacementRequest,
    placement_names,
    placement_spec,
    register_placement,
)


def test_the_built_in_placements_are_registered() -> None:
    assert {"sim", "sim-process", "emulated-real", "tcp://", "ros1://", "ros2://"} <= set(placement_names())
    assert placement_spec("sim").can_teleport and placement_spec("sim-process").can_teleport
    assert not placement_spec("emulated-real").can_teleport
    assert placement_spec("tcp://127.0.0.1:7000").name == "tcp://"
    assert placement_spec("ros1://robot-pc:11311").name == "ros1://"
    assert uniros_async.register_placement is register_placement


@pytest.mark.parametrize(
    ("robot", "closest"),
    [
        ("simm", "sim"),
        ("sim_process", "sim-process"),
        ("tpc://127.0.0.1:1", "tcp://"),
        ("ros11://h:1", "ros1://"),
        ("rso2://0", "ros2://"),
    ],
)
def test_an_unknown_placement_names_the_closest_and_the_registered(robot: str, closest: str) -> None:
    with pytest.raises(ConfigError, match=rf"did you mean {closest!r}\?\); registered: \[.*'sim'") as info:
        placement_spec(robot)
    assert repr(robot) in str(info.value)
    with pytest.raises(ConfigError, match=rf"did you mean {closest!r}"):
        EnvConfig(robot=robot)


def test_a_placement_checks_its_own_uri() -> None:
    with pytest.raises(ConfigError, match="tcp://HOST:PORT"):
        EnvConfig(robot="tcp://127.0.0.1")
    with pytest.raises(ConfigError, match="ros1://HOST:PORT"):
        EnvConfig(robot="ros1://robot-pc")
    with pytest.raises(ConfigError, match=r"ros1: unknown setting\(s\) \['topic'\]"):
        EnvConfig(robot="ros1://127.0.0.1:11311", ros1={"topic": "/x"})
    with pytest.raises(ConfigError, match="clock='sim' needs"):
        EnvConfig(robot="tcp://127.0.0.1:7000", clock="sim")
    assert EnvConfig(robot="ros1://127.0.0.1:11311", ros1={"driver": "xs_sdk"}).robot.startswith("ros1://")


@contextlib.asynccontextmanager
async def _open_nowhere(request: PlacementRequest) -> AsyncIterator[ArmLink]:
    yield ArmLink(domain=request.uri, transport="tcp")


def _check_port(robot: str, config: EnvConfig) -> None:
    if not robot.rpartition(":")[2].isdigit():
        raise ConfigError(f"{robot!r}: no port")


def test_registering_is_idempotent_and_refuses_a_silent_replacement() -> None:
    spec = register_placement("test-nowhere://", _open_nowhere, check=_check_port, description="tests")
    assert register_placement("test-nowhere://", _open_nowhere, check=_check_port, description="tests") == spec
    assert placement_spec("test-nowhere://h:1") is spec
    assert EnvConfig(robot="test-nowhere://h:1").robot == "test-nowhere://h:1"
    with pytest.raises(ConfigError, match="no port"):
        EnvConfig(robot="test-nowhere://h")
    with pytest.raises(ConfigError, match="already registered"):
        register_placement("test-nowhere://", "somewhere.else:open_it")
    replaced = register_placement("test-nowhere://", "somewhere.else:open_it", override=True)
    with pytest.raises(ConfigError, match="cannot import 'somewhere.else'"):
        replaced.factory()
    register_placement("test-nowhere://", _open_nowhere, override=True)


@pytest.mark.parametrize("name", ["", "a://b", "Bad Scheme://", " sim", "1x://"])
def test_a_malformed_placement_name_is_refused(name: str) -> None:
    with pytest.raises(ConfigError, match="placement"):
        register_placement(name, _open_nowhere)


def test_envs_import_no_adapter_and_no_sim() -> None:
    """The env layer knows the placement registry, never an adapter or the sim: ros1:// and sim are registered by
    entry point, and the sim's factories load when a sim placement is opened."""
    code = (
        "import sys, uniros_async.envs.robot, uniros_async.envs.config\n"
        "from uniros_async.envs.config import EnvConfig\n"
        "from uniros_async.placements import placement_spec\n"
        "EnvConfig(robot='sim'); EnvConfig(robot='tcp://127.0.0.1:7000')\n"
        "bad = [m for m in sys.modules if m.startswith(('uniros_async.adapters', 'uniros_async.sim.'))]\n"
        "assert not bad, bad\n"
        "from uniros_async.sim.placement import open_sim\n"
        "assert placement_spec('sim').factory() is open_sim\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr
