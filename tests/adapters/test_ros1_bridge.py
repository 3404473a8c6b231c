"""The ROS 1 bridge against a real rosmaster and a real rospy node in the driver's place.

No physical arm is attached here, so ``ros1_fake_arm.py`` (real rospy, run by the system Python) stands in for the
arm's ROS 1 driver: it publishes sensor_msgs/JointState at the hardware rate, moves toward the commands it gets and
prints each command it received as a JSON line, which these tests check. Everything on our side is the real code:
the bridge, our asyncio ROS 1 client, the bus, and in the last tests a real-time env and the ``uniros`` CLI.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from _reach import distances_toward_goal
from _ros_helpers import check_cli_bridge, check_mixed_vec, command_line, joint_command, moved_commands, robot_error

from uniros_async.bench.ros1_peers import kill_process, rospy_process, wait_for_line
from uniros_async.bus import open_domain, open_node
from uniros_async.bus.messages import Data, Empty, Header, JointCommand, JointState, Trigger
from uniros_async.errors import ConfigError, RobotError
from uniros_async.robots import get_robot_spec
from uniros_async.testing.tls import write_test_certs

FAKE_ARM = Path(__file__).with_name("ros1_fake_arm.py")
ROOT = Path(__file__).resolve().parents[2]


def _md5() -> str:
    from uniros_async.adapters.ros1 import msgs

    return msgs.JointGroupCommand._md5sum


@pytest.fixture
def fake_arm(ros_master: str, tmp_path: Path) -> Iterator[Callable[..., subprocess.Popen[str]]]:
    """Starts the stand-in driver for a robot with its default ROS 1 driver's topics (``adapters.drivers``), or
    others."""
    from uniros_async.adapters.drivers import ros_driver_defaults

    with contextlib.ExitStack() as stack:

        def start(robot: str, *, drop_joint: str = "", **topics: str) -> subprocess.Popen[str]:
            spec = get_robot_spec(robot)
            defaults = ros_driver_defaults("ros1", robot)
            assert defaults is not None
            t = {**defaults.as_settings(), **topics}
            proc = stack.enter_context(
                rospy_process(
                    FAKE_ARM,
                    "--joints",
                    ",".join(spec.joint_state_names),
                    "--arm",
                    str(len(spec.arm_joint_names)),
                    "--joint-states",
                    t["joint_states"],
                    "--command",
                    t["command"],
                    "--command-type",
                    t["command_type"],
                    "--rate",
                    str(spec.hardware_rate_hz),
                    "--md5",
                    _md5(),
                    "--drop-joint",
                    drop_joint,
                    master_uri=ros_master,
                    tmp_path=tmp_path,
                )
            )
            wait_for_line(proc, "ready", timeout_s=30.0)
            return proc

        yield start


async def test_rx200_states_and_interbotix_commands(ros_master: str, fake_arm: Any) -> None:
    from uniros_async.adapters.ros1_bridge import Ros1BridgeConfig, open_ros1_bridge

    arm = fake_arm("rx200")
    spec = get_robot_spec("rx200")
    cfg = Ros1BridgeConfig(robot="rx200", master_uri=ros_master)
    async with (
        open_domain("memory://") as dom,
        open_ros1_bridge(cfg, domain=dom) as bridge,
        open_node("env", domain=dom, namespace="/rx200") as env,
    ):
        js = await env.create_subscription(JointState, "joint_states")
        cmd = await env.create_publisher(JointCommand, "command")
        await cmd.wait_for_subscribers(1, timeout_s=5.0)
        first = await asyncio.wait_for(js.receive(), 5.0)
        assert first.name == spec.joint_state_names
        np.testing.assert_allclose(first.position, 0.0)

        target = [0.3, -0.2, 0.25, 0.1, -0.15]
        cmd.publish(joint_command(target))
        got = await command_line(arm)
        assert got["type"] == "interbotix_xs_msgs/JointGroupCommand"
        assert got["group"] == "arm"
        np.testing.assert_allclose(got["positions"], target, atol=1e-6)  # float32 on the wire

        # the stand-in moves at 1 rad/s at 10 Hz: within 1 s every joint is there, and we see it in our order
        deadline = time.monotonic() + 5.0
        while True:
            state = await asyncio.wait_for(js.receive(), 5.0)
            if np.allclose(state.position[:5], target, atol=1e-4) or time.monotonic() > deadline:
                break
        np.testing.assert_allclose(state.position[:5], target, atol=1e-4)
        assert state.header.seq > first.header.seq
        assert bridge.stats.commands_out == 1 and bridge.stats.states_in >= 5


async def test_unsafe_and_malformed_commands_are_not_sent(ros_master: str, fake_arm: Any) -> None:
    from uniros_async.adapters.ros1_bridge import Ros1BridgeConfig, open_ros1_bridge

    arm = fake_arm("rx200")
    cfg = Ros1BridgeConfig(robot="rx200", master_uri=ros_master)
    async with (
        open_domain("memory://") as dom,
        open_ros1_bridge(cfg, domain=dom),
        open_node("env", domain=dom, namespace="/rx200") as env,
    ):
        cmd = await env.create_publisher(JointCommand, "command")
        stats = env.create_client(Empty, Data, "stats")
        hold = env.create_client(Empty, Trigger, "hold")
        await cmd.wait_for_subscribers(1, timeout_s=5.0)
        cmd.publish(joint_command([0.0, 2.5, 0.0, 0.0, 0.0]))  # shoulder beyond +113 deg
        await asyncio.sleep(0.05)
        cmd.publish(joint_command([0.1, 0.2]))  # two values for five joints
        await asyncio.sleep(0.05)
        cmd.publish(joint_command([0.0, 0.1, 0.0, 0.0, math.nan]))
        await asyncio.sleep(0.05)
        cmd.publish(joint_command([0.05, 0.0, 0.0, 0.0, 0.0]))
        got = await command_line(arm)  # the first command the driver sees is the last, valid one
        np.testing.assert_allclose(got["positions"], [0.05, 0.0, 0.0, 0.0, 0.0], atol=1e-6)
        elbow_max = get_robot_spec("rx200").joint_upper_rad[2]
        cmd.publish(
            joint_command([0.05, 0.0, elbow_max + 0.01, 0.0, 0.0])
        )  # a hair past: clamped to the limit, as servos do
        got = await command_line(arm)
        np.testing.assert_allclose(got["positions"], [0.05, 0.0, elbow_max, 0.0, 0.0], atol=1e-6)
        counts = (await stats.call(Empty(), timeout_s=5.0)).value
        assert counts["commands_rejected"] == 3 and counts["commands_out"] == 2 and counts["commands_clamped"] == 1
        reply = await hold.call(Empty(), timeout_s=5.0)
        assert reply.success, reply.message
        held = await command_line(arm)  # hold: the newest measured position, between home and that target
        assert len(held["positions"]) == 5 and abs(held["positions"][0]) < 0.06 and held["positions"][2] < 1.63


async def test_ned2_joint_trajectory_commands(ros_master: str, fake_arm: Any) -> None:
    from uniros_async.adapters.ros1_bridge import Ros1BridgeConfig, open_ros1_bridge

    arm = fake_arm("ned2")
    cfg = Ros1BridgeConfig(robot="ned2", master_uri=ros_master)
    async with (
        open_domain("memory://") as dom,
        open_ros1_bridge(cfg, domain=dom),
        open_node("env", domain=dom, namespace="/ned2") as env,
    ):
        cmd = await env.create_publisher(JointCommand, "command")
        await cmd.wait_for_subscribers(1, timeout_s=5.0)
        cmd.publish(joint_command([0.1, 0.2, -0.3, 0.0, 0.1, 0.0]))
        got = await command_line(arm)
        assert got["type"] == "trajectory_msgs/JointTrajectory"
        assert got["joint_names"] == ["joint_1", "joint_2", "joint_3", "joint_4", "joint_5", "joint_6"]
        np.testing.assert_allclose(got["positions"], [0.1, 0.2, -0.3, 0.0, 0.1, 0.0])
        assert got["time_from_start_s"] == pytest.approx(0.04)  # one 25 Hz period: as soon as the servos can
        cmd.publish(joint_command([0.0] * 6, duration_s=1.5))
        got = await command_line(arm)
        assert got["time_from_start_s"] == pytest.approx(1.5)


async def test_float64_multi_array_and_a_missing_finger(ros_master: str, fake_arm: Any) -> None:
    from uniros_async.adapters.ros1_bridge import Ros1BridgeConfig, open_ros1_bridge

    topics = {"command": "/arm_controller/command", "command_type": "std_msgs/Float64MultiArray"}
    arm = fake_arm("rx200", drop_joint="left_finger", **topics)
    cfg = Ros1BridgeConfig(robot="rx200", master_uri=ros_master, **topics)
    async with (
        open_domain("memory://") as dom,
        open_ros1_bridge(cfg, domain=dom),
        open_node("env", domain=dom, namespace="/rx200") as env,
    ):
        js = await env.create_subscription(JointState, "joint_states")
        state = await asyncio.wait_for(js.receive(), 5.0)
        assert state.name[6] == "left_finger" and state.position[6] == 0.0  # absent: reads 0.0
        cmd = await env.create_publisher(JointCommand, "command")
        await cmd.wait_for_subscribers(1, timeout_s=5.0)
        cmd.publish(joint_command([0.0, 0.1, 0.2, 0.3, 0.4]))
        got = await command_line(arm)
        assert got["type"] == "std_msgs/Float64MultiArray"
        np.testing.assert_allclose(got["positions"], [0.0, 0.1, 0.2, 0.3, 0.4])


async def test_missing_arm_joint_or_silent_driver_is_a_clear_error(ros_master: str, fake_arm: Any) -> None:
    from uniros_async.adapters.ros1_bridge import Ros1BridgeConfig, open_ros1_bridge

    fake_arm("rx200", drop_joint="elbow")
    cfg = Ros1BridgeConfig(robot="rx200", master_uri=ros_master, state_timeout_s=1.5)
    async with open_domain("memory://") as dom:
        with pytest.raises((RobotError, BaseExceptionGroup)) as err:
            async with open_ros1_bridge(cfg, domain=dom):
                pass
        text = robot_error(err.value)
        assert "/rx200/joint_states" in text and "within 1.5 s" in text
        # nothing is published on the other robot's topic: the same clear error, naming that topic
        cfg2 = Ros1BridgeConfig(robot="ned2", master_uri=ros_master, state_timeout_s=0.5)
        with pytest.raises((RobotError, BaseExceptionGroup)) as err:
            async with open_ros1_bridge(cfg2, domain=dom):
                pass
        assert "/joint_states" in robot_error(err.value) and "driver running" in robot_error(err.value)


def test_bad_settings_are_refused_before_anything_starts() -> None:
    from uniros_async.adapters.ros1_bridge import Ros1BridgeConfig, parse_ros1_uri

    with pytest.raises(ConfigError, match="command_type must be one of"):
        Ros1BridgeConfig(robot="rx200", command_type="std_msgs/String")
    with pytest.raises(ConfigError, match="absolute ROS topic"):
        Ros1BridgeConfig(robot="rx200", joint_states="joint_states")
    with pytest.raises(ConfigError, match="rx200"):  # the error lists the known robots
        Ros1BridgeConfig(robot="ur5")
    assert parse_ros1_uri("ros1://10.0.0.2:11311") == "http://10.0.0.2:11311/"
    for bad in ("ros1://host", "ros1://:11311", "http://host:11311", "ros1://host:99999"):
        with pytest.raises(ConfigError, match="ros1://HOST:PORT"):
            parse_ros1_uri(bad)
    import gymnasium as gym

    import uniros_async  # noqa: F401

    with pytest.raises(ConfigError, match="unknown setting"):
        gym.make("uniros/Rx200Reach-v0", robot="ros1://127.0.0.1:11311", ros1={"topic": "/x"})
    with pytest.raises(ConfigError, match="only to robot='ros1"):
        gym.make("uniros/Rx200Reach-v0", robot="sim", ros1={"command": "/x"})


def test_bad_max_command_age_is_refused() -> None:
    from uniros_async.adapters.ros1_bridge import Ros1BridgeConfig

    with pytest.raises(ConfigError, match="max_command_age_s must be > 0"):
        Ros1BridgeConfig(robot="rx200", max_command_age_s=0.0)


def test_a_state_that_waited_on_the_way_is_stamped_as_old_and_stale_states_stop_commands() -> None:
    """The bridge's translation alone (no ROS peer: its two callbacks are called directly): a joint state that took
    longer than the quickest to arrive is stamped that much before its arrival, whatever the offset between the
    driver's clock and ours; while the newest state is older than ``max_command_age_s`` no command is sent."""
    from uniros_async.adapters.ros1 import msgs
    from uniros_async.adapters.ros1_bridge import Ros1Bridge, Ros1BridgeConfig

    out: list[JointState] = []
    sent: list[Any] = []
    bridge = Ros1Bridge(Ros1BridgeConfig(robot="rx200", max_command_age_s=0.5), out.append, time.monotonic_ns)
    bridge._send = sent.append  # in place of the command publisher that run_commands opens
    spec = get_robot_spec("rx200")
    offset = 12_345_678_901  # the driver's clock runs this far behind ours: it cancels out

    def state(waited_s: float) -> None:
        stamp = time.time_ns() - offset - round((0.002 + waited_s) * 1e9)  # 2 ms on the way, plus what it waited
        names = list(spec.joint_state_names)
        zeros = np.zeros(len(names))
        header = msgs.RosHeader(seq=0, stamp_ns=stamp, frame_id="")
        bridge.on_ros_state(msgs.JointState(header=header, name=names, position=zeros, velocity=zeros, effort=zeros))

    for _ in range(5):
        state(0.0)
        assert abs(time.monotonic_ns() - out[-1].header.stamp_ns) < 0.05e9  # as fresh as it is
    state(2.0)  # one that sat 2 s in a buffer
    assert 1.95e9 < time.monotonic_ns() - out[-1].header.stamp_ns < 2.1e9
    unstamped = msgs.JointState(header=msgs.RosHeader(), name=list(spec.joint_state_names),
                                position=np.zeros(len(spec.joint_state_names)), velocity=[], effort=[])  # fmt: skip
    bridge.on_ros_state(unstamped)  # a driver that does not stamp: counted from its arrival
    assert abs(time.monotonic_ns() - out[-1].header.stamp_ns) < 0.05e9

    q = np.zeros(len(spec.arm_joint_names))
    bridge.on_command(JointCommand(header=Header(), position=q))
    assert len(sent) == 1
    bridge.last_state_ns = time.monotonic_ns() - round(0.6e9)  # the newest state 0.6 s old: stale
    bridge.on_command(JointCommand(header=Header(), position=q))
    assert len(sent) == 1 and bridge.stats.commands_stale == 1
    assert not bridge.srv_hold(Empty()).success and "s old" in bridge.srv_hold(Empty()).message
    assert len(sent) == 1


def test_a_command_meets_no_closed_publisher_and_never_ends_the_bridge() -> None:
    """While the command publisher is replaced, its node closes, which can take seconds while the master is cut off.
    ``run_commands`` lets go of the publisher before it closes, and a command that meets a closed publisher anyway
    counts as stale instead of raising in the command topic's callback (whose error would end the bridge and the
    env with it). The bridge's own code; the publisher's context is a stand-in that holds its exit open, as closing
    a ROS node does while the master does not answer, and the closed publication is the real class, closed."""
    from uniros_async.adapters.ros1 import msgs
    from uniros_async.adapters.ros1.topics import Ros1Publisher, _Publication
    from uniros_async.adapters.ros1_bridge import Ros1Bridge, Ros1BridgeConfig

    spec = get_robot_spec("rx200")
    bridge = Ros1Bridge(Ros1BridgeConfig(robot="rx200", max_command_age_s=0.5), lambda msg: None, time.monotonic_ns)
    names = list(spec.joint_state_names)
    zeros = np.zeros(len(names))
    header = msgs.RosHeader(seq=0, stamp_ns=time.time_ns(), frame_id="")
    bridge.on_ros_state(msgs.JointState(header=header, name=names, position=zeros, velocity=zeros, effort=zeros))
    q = np.zeros(len(spec.arm_joint_names))

    closed = _Publication(None, "/rx200/commands/joint_group", msgs.JointGroupCommand, False, 1)  # type: ignore[arg-type]
    closed.closed = True
    bridge._send = Ros1Publisher(closed, msgs.JointGroupCommand).publish
    bridge.on_command(JointCommand(header=Header(), position=q))  # does not raise
    assert bridge.stats.commands_stale == 1 and bridge.stats.commands_out == 0

    async def main() -> list[object]:
        seen: list[object] = []
        closing = asyncio.Event()
        sent: list[Any] = []

        @contextlib.asynccontextmanager
        async def open_publisher(generation: int) -> Any:
            pub = Ros1Publisher(_Publication(None, "/c", msgs.JointGroupCommand, False, 1), msgs.JointGroupCommand)  # type: ignore[arg-type]
            pub.publish = sent.append  # type: ignore[method-assign]
            try:
                yield pub
            finally:
                closing.set()
                seen.append(bridge._send)  # what a command arriving while the node closes would be sent with
                await asyncio.sleep(0.05)

        async def watch_once(pub: Any) -> None:
            await asyncio.sleep(0.01)  # a connection was reset: replace the publisher

        bridge._watch = watch_once  # type: ignore[method-assign]
        ready: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        task = asyncio.create_task(bridge.run_commands(open_publisher, ready))
        await ready
        await closing.wait()
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        return seen

    assert asyncio.run(main())[0] is None


@pytest.mark.slow
def test_real_time_env_drives_the_ros_arm(ros_master: str, fake_arm: Any) -> None:
    """The same TaskEnv as on the sim, on the ROS 1 arm: reset walks it home, and one step's env loop re-sends
    the action at the hardware rate (action repeat), every command reaching the driver."""
    import gymnasium as gym

    import uniros_async  # noqa: F401

    arm = fake_arm("rx200")
    port = ros_master.rstrip("/").rsplit(":", 1)[1]
    env = gym.make(
        "uniros/Rx200Reach-v0", robot=f"ros1://127.0.0.1:{port}", reward_type="dense", action_mode="absolute"
    )
    try:
        obs, info = env.reset(seed=0)
        assert np.all(np.isfinite(obs))
        action = np.array([0.2, 0.1, 0.1, 0.1, 0.0], dtype=np.float32)  # an absolute target clear of the table
        env.step(action)  # the first step after a reset ends on the action-cycle grid: 0.1 to 0.9 s
        t0 = time.monotonic()
        obs, reward, terminated, truncated, info = env.step(action)
        assert 0.7 < time.monotonic() - t0 < 1.5  # one 0.8 s action cycle in real time (not two, not none)
        assert np.all(np.isfinite(obs)) and math.isfinite(reward)
        assert "unsafe_reason" not in info, info
    finally:
        env.close()
    n, lines = moved_commands(arm, gap_s=0.5)
    assert n >= 9, lines  # the action re-sent tick after tick: 10 Hz over the two steps (>= 0.9 s)


@pytest.mark.slow
def test_cli_bridge_serves_a_domain_until_sigint(ros_master: str, fake_arm: Any) -> None:
    fake_arm("rx200")
    check_cli_bridge("--ros-master", ros_master, host="127.0.0.2")  # the node listens where the domain does


def test_cli_bridge_reports_an_unreachable_master() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "uniros_async.cli", "robot", "bridge", "rx200", "--ros-master", "http://127.0.0.1:9/"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2, proc.stderr
    assert "http://127.0.0.1:9/" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.slow
def test_a_reach_env_steps_an_arm_bridged_on_tls(
    ros_master: str, fake_arm: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``uniros robot bridge rx200 --tls`` (a real process, its files by flag and none from the environment) serves
    the ROS 1 arm's domain on tls://; a reach env (its files by ``$UNIROS_TLS_*``) joins it by ``robot="tls://..."``
    and steps the arm toward a goal; the bridge's node offers its topics on tls only."""

    import uniros_async  # noqa: F401

    arm = fake_arm("rx200")
    tls = write_test_certs(tmp_path / "tls")
    env_vars = {k: v for k, v in os.environ.items() if k not in tls.environ()}
    env_vars["PYTHONPATH"] = os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])
    log = tmp_path / "bridge.log"
    flags = ["--tls", "--tls-cert", tls.cert_file, "--tls-key", tls.key_file, "--tls-ca", tls.ca_file]
    with open(log, "w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "uniros_async.cli", "robot", "bridge", "rx200", "--ros-master", ros_master, *flags],
            stdout=subprocess.PIPE,
            stderr=err,
            stdin=subprocess.DEVNULL,
            text=True,
            env=env_vars,
        )
    try:
        try:
            line = wait_for_line(proc, "export UNIROS_DOMAIN=", timeout_s=60.0)
        except (TimeoutError, RuntimeError) as exc:
            raise AssertionError(f"the bridge did not start ({exc}); its log:\n{log.read_text()[-2000:]}") from exc
        assert line.startswith("export UNIROS_DOMAIN=tls://127.0.0.1:"), line
        uri = line.removeprefix("export UNIROS_DOMAIN=")
        for var, value in tls.environ().items():
            monkeypatch.setenv(var, value)

        async def bridge_endpoints() -> dict[str, str]:
            async with asyncio.timeout(30), open_node("probe", domain=uri) as probe:
                info = await probe._registry.request("lookup_service", name="/rx200/stats")
                return dict(info["endpoints"])

        endpoints = asyncio.run(bridge_endpoints())
        assert set(endpoints) == {"tls"} and endpoints["tls"].startswith("tls://127.0.0.1:"), endpoints

        distances = distances_toward_goal(uri, 3)
        assert distances[-1] < distances[0] - 0.05, f"the arm bridged on tls did not move toward the goal: {distances}"
        n, lines = moved_commands(arm, gap_s=0.5)
        assert n >= 5, lines  # the env loop's commands reached the ROS driver through the tls domain and the bridge
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=15.0) == 0, log.read_text()[-2000:]
    finally:
        kill_process(proc)


def test_cli_bridge_tls_flags_are_checked(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """The bridge's ``--tls`` flags are serve's, checked the same way before any ROS master is reached."""
    from uniros_async.sim import cli

    for var in ("UNIROS_TLS_CERT", "UNIROS_TLS_KEY", "UNIROS_TLS_CA"):
        monkeypatch.delenv(var, raising=False)
    unreachable = ["--ros-master", "http://127.0.0.1:9/"]
    assert cli.main(["bridge", "rx200", *unreachable, "--tls-cert", "a.pem", "--tls-key", "a.key"]) == 2
    assert "--tls-cert, --tls-key only apply with --tls" in capsys.readouterr().err
    # no certificate given, none in the environment: refused before the ROS 1 master or a ROS 2 domain is reached
    for ros in (unreachable, ["--ros2", "0"]):
        assert cli.main(["bridge", "rx200", *ros, "--tls"]) == 2
        err = capsys.readouterr().err
        assert "UNIROS_TLS_CERT, UNIROS_TLS_KEY, UNIROS_TLS_CA" in err and "127.0.0.1:9" not in err, err
    # files that do not exist: named, the bridge not started
    missing = ["--tls-cert", "nowhere.pem", "--tls-key", "nowhere.key", "--tls-ca", "nowhere-ca.pem"]
    assert cli.main(["bridge", "rx200", *unreachable, "--tls", *missing]) == 2
    assert "nowhere" in capsys.readouterr().err


@pytest.mark.slow
def test_make_vec_mixes_a_ros_arm_with_a_sim_arm(ros_master: str, fake_arm: Any) -> None:
    """One vector env, two worker processes: the rx200 behind ROS 1 (the bridge runs in its worker) and a sim rx200."""
    arm = fake_arm("rx200")
    port = ros_master.rstrip("/").rsplit(":", 1)[1]
    check_mixed_vec(f"ros1://127.0.0.1:{port}")
    n, lines = moved_commands(arm, gap_s=0.5)
    assert n >= 9, lines


def test_ros_host_follows_ros_ip_then_ros_hostname(monkeypatch: pytest.MonkeyPatch) -> None:
    from uniros_async.adapters.ros1_bridge import Ros1BridgeConfig

    monkeypatch.delenv("ROS_IP", raising=False)
    monkeypatch.delenv("ROS_HOSTNAME", raising=False)
    assert Ros1BridgeConfig(robot="rx200").ros_host == "127.0.0.1"
    monkeypatch.setenv("ROS_HOSTNAME", "trainer.lab")
    assert Ros1BridgeConfig(robot="rx200").ros_host == "trainer.lab"
    monkeypatch.setenv("ROS_IP", "10.1.2.3")
    assert Ros1BridgeConfig(robot="rx200").ros_host == "10.1.2.3"
    assert Ros1BridgeConfig(robot="rx200", ros_host="192.168.1.20").ros_host == "192.168.1.20"


async def test_two_bridges_to_one_arm_do_not_unseat_each_other(ros_master: str, fake_arm: Any) -> None:
    """A training and an evaluation env on one arm each run a bridge: both keep their ROS registrations."""
    from uniros_async.adapters.ros1_bridge import Ros1BridgeConfig, open_ros1_bridge

    fake_arm("rx200")
    cfg = Ros1BridgeConfig(robot="rx200", master_uri=ros_master)
    async with (
        open_domain("memory://") as dom1,
        open_domain("memory://") as dom2,
        open_ros1_bridge(cfg, domain=dom1) as first,
        open_ros1_bridge(cfg, domain=dom2) as second,
    ):
        n1, n2 = first.stats.states_in, second.stats.states_in
        await asyncio.sleep(0.5)  # 10 Hz: both still receive the driver's joint states
        assert first.stats.states_in >= n1 + 3 and second.stats.states_in >= n2 + 3
        import xmlrpc.client

        def system_state() -> Any:
            with xmlrpc.client.ServerProxy(ros_master) as master:
                return master.getSystemState("/probe")

        state = await asyncio.to_thread(system_state)
        subscribers = dict((topic, nodes) for topic, nodes in state[2][1])["/rx200/joint_states"]
        assert len([n for n in subscribers if n.startswith("/uniros_ros1_bridge_rx200")]) == 2, subscribers
