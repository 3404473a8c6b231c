"""An arm served on tls:// (``uniros robot serve rx200 --tls``, a real process) and a reach env that steps it by its
domain URI (``robot="tls://..."``), with throw-away certificates (``uniros_async.testing.tls``) on loopback."""

from __future__ import annotations

import asyncio
from pathlib import Path

import gymnasium as gym
import pytest
from _reach import distances_toward_goal

import uniros_async  # noqa: F401  (registers the ids)
from tests.hostile import _served
from uniros_async.bus import open_domain, open_node
from uniros_async.bus.messages import JointState
from uniros_async.errors import ConfigError
from uniros_async.sim import cli
from uniros_async.sim.serve import ServeConfig, open_servo_sim_process
from uniros_async.testing.tls import TlsFiles, write_test_certs

TLS_VARS = ("UNIROS_TLS_CERT", "UNIROS_TLS_KEY", "UNIROS_TLS_CA")


@pytest.fixture(scope="module")
def tls_files(tmp_path_factory: pytest.TempPathFactory) -> TlsFiles:
    return write_test_certs(tmp_path_factory.mktemp("tls"))


@pytest.mark.slow
def test_a_reach_env_steps_an_arm_served_on_tls(
    tls_files: TlsFiles, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the served arm gets its files by flag (and none from the environment), the env by $UNIROS_TLS_*
    flags = ["--tls", "--tls-cert", tls_files.cert_file, "--tls-key", tls_files.key_file, "--tls-ca", tls_files.ca_file]
    proc, line = _served.start_serve(["--port", "0", *flags], tmp_path / "serve.log", unset=TLS_VARS)
    try:
        assert line.startswith("export UNIROS_DOMAIN=tls://127.0.0.1:"), line
        uri = line.removeprefix("export UNIROS_DOMAIN=")
        for var, value in tls_files.environ().items():
            monkeypatch.setenv(var, value)
        distances = distances_toward_goal(uri, 4, action_cycle_s=0.2)
        assert distances[-1] < distances[0] - 0.05, f"the arm served on tls did not move toward the goal: {distances}"
    finally:
        _served.stop_serve(proc)
    assert proc.returncode == 0, (tmp_path / "serve.log").read_text()[-2000:]


@pytest.mark.slow
async def test_a_servo_sim_process_joins_a_tls_domain(tls_files: TlsFiles, monkeypatch: pytest.MonkeyPatch) -> None:
    for var, value in tls_files.environ().items():  # the child inherits them
        monkeypatch.setenv(var, value)
    async with (
        asyncio.timeout(60),
        open_domain("tls://127.0.0.1:0") as domain,
        open_servo_sim_process("ned2", domain=domain, transport="tls"),
        open_node("env", domain=domain, transport="tls") as env,
    ):
        eps = domain._nodes["/ned2/servo_sim"].info["endpoints"]
        assert set(eps) == {"tls"}, eps
        states = await env.create_subscription(JointState, "/ned2/joint_states")
        await states.wait_for_publishers(1, timeout_s=10)
        assert len((await states.receive()).position) == 6


def test_tls_flags_and_settings_are_checked(
    tls_files: TlsFiles, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    for var in TLS_VARS:
        monkeypatch.delenv(var, raising=False)
    assert cli.main(["serve", "rx200", "--tls-ca", tls_files.ca_file]) == 2
    assert "--tls-ca only apply with --tls" in capsys.readouterr().err
    assert cli.main(["serve", "rx200", "--tls", "--ros2", "0"]) == 2
    assert "--ros2 serves no uniros domain" in capsys.readouterr().err
    assert cli.main(["serve", "rx200", "--tls"]) == 2  # no certificate given, none in the environment
    assert "UNIROS_TLS_CERT, UNIROS_TLS_KEY, UNIROS_TLS_CA" in capsys.readouterr().err
    assert ServeConfig(robot="rx200", domain="tls://127.0.0.1:7000").scheme == "tls"
    assert ServeConfig(robot="rx200", tls=True).scheme == "tls"
    with pytest.raises(ConfigError, match="give its tls:// URI as domain"):
        ServeConfig(robot="rx200", domain="tcp://127.0.0.1:7000", tls=True)
    with pytest.raises(ConfigError, match="expected a domain URI tls://HOST:PORT"):
        gym.make("uniros/Rx200Reach-v0", robot="tls://127.0.0.1")
