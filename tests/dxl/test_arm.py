"""The arm on its bus (DxlArm) against the virtual servo bus: start-up, a tick, errors, clamping, shutdown."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterator

import numpy as np
import pytest

from uniros_async.errors import ConfigError, DxlCrcError, RobotError
from uniros_async.hardware.dxl.arm import LIMIT_CLAMP_RAD, DxlArm
from uniros_async.hardware.dxl.bus import open_dxl_bus
from uniros_async.hardware.dxl.control_table import rad_to_ticks, ticks_to_rad
from uniros_async.hardware.dxl.placement import parse_dxl_uri
from uniros_async.hardware.dxl.servo_map import servo_map

from ._vbus import MARGIN_MS, Vbus, read, running_vbus, sdk_port

pytestmark = pytest.mark.slow

RX200 = servo_map("rx200")
SLACK = dataclasses.replace(RX200, bus_watchdog_ms=500)
"""The rx200's map with a 500 ms Bus Watchdog: these tests tick the arm from the test's own process, which is not
real-time, and a loaded host may pause it past 100 ms. The watchdog's own tests use the rx200's map."""


@pytest.fixture
def vbus() -> Iterator[Vbus]:
    with running_vbus() as bus:
        yield bus


def _present(path: str, ids: tuple[int, ...] = (1, 2, 3, 4, 5, 6, 7)) -> dict[int, tuple[int, int, int]]:
    """(present position, goal position, torque enable) of each servo, read with dynamixel-sdk."""
    with sdk_port(path) as (port, ph):
        return {i: (read(ph, port, i, 132, 4), read(ph, port, i, 116, 4), read(ph, port, i, 64, 1)) for i in ids}


async def test_start_holds_every_servo_where_it_is_then_ticks_and_holds_at_shutdown(vbus: Vbus) -> None:
    await _sleep(0.5)  # the sim's arm settles under gravity first
    before = _present(vbus.path)
    assert all(torque == 0 for _, _, torque in before.values())
    async with await open_dxl_bus(vbus.path, margin_s=MARGIN_MS / 1e3) as bus:
        arm = DxlArm(bus, SLACK)
        await arm.start()
        n0 = bus.stats.transactions
        state = await arm.read_state(0)
        assert bus.stats.transactions == n0 + 1  # the whole arm's state in one transaction
        q0 = state.joint_state.position[:5]
        for servo, q in zip(arm.arm_servos, q0, strict=True):
            assert abs(rad_to_ticks(float(q)) - before[servo.id][0]) <= 3, "an arm servo moved at start-up"
        assert set(state.current_a) == {"shoulder", "elbow"}  # the XM430s sense current
        goal = np.array([0.3, -0.2, 0.3, 0.2, -0.3])
        for _ in range(200):  # the 2 s time profile of rx200 modes.yaml, ticked every ~20 ms
            await arm.write_goals(goal)
            state = await arm.read_state(0)
            if np.max(np.abs(state.joint_state.position[:5] - goal)) < 0.02:
                break
            await _sleep(0.02)
        assert np.max(np.abs(state.joint_state.position[:5] - goal)) < 0.02, state.joint_state.position
        await arm.close()
    after = _present(vbus.path)
    for servo_id, (present, goal_ticks, torque) in after.items():
        if servo_id != 7:
            assert torque == 1, f"servo {servo_id}: torque dropped at shutdown"
            assert abs(goal_ticks - present) <= 3, f"servo {servo_id}: not holding where it is"


async def test_a_wrong_model_and_a_silent_servo_are_named(vbus: Vbus) -> None:
    wrong = dataclasses.replace(
        RX200,
        servos=tuple(dataclasses.replace(s, model="XL430-W250") if s.id == 4 else s for s in RX200.servos),
    )
    async with await open_dxl_bus(vbus.path, margin_s=MARGIN_MS / 1e3) as bus:
        with pytest.raises(
            RobotError, match=r"servo ID 4 \(elbow\) is model number 1020 \(XM430-W350\), expected 1060 \(XL430-W250\)"
        ):
            await DxlArm(bus, wrong).start()
        assert vbus.send("silent 5") == "ok silent 5"
        with pytest.raises(
            RobotError, match=r"servo ID 5 \(wrist_angle\) does not answer.*baud rate \(1000000\).*power.*ID"
        ):
            await DxlArm(bus, SLACK).start()
    # nothing was moved or torqued by the refused start-ups
    assert all(torque == 0 for _, _, torque in _present(vbus.path, (1, 2, 3, 4, 6, 7)).values())


async def test_hardware_error_is_a_robot_error_naming_joint_id_and_bits_and_the_arm_holds(vbus: Vbus) -> None:
    async with await open_dxl_bus(vbus.path, margin_s=MARGIN_MS / 1e3) as bus:
        arm = DxlArm(bus, SLACK)
        await arm.start()
        for _ in range(6):  # the waist moves, ticked at 20 Hz
            await arm.write_goals(np.array([0.6, 0.0, 0.0, 0.0, 0.0]))
            await arm.read_state(0)
            await _sleep(0.02)
        assert vbus.send("error 4 0x20") == "ok error 4 0x20"
        with pytest.raises(RobotError, match=r"joint 'elbow' \(servo ID 4\): overload \(0x20\).*the arm holds"):
            await arm.read_state(0)
    held = _present(vbus.path, (1,))[1]
    assert abs(held[1] - held[0]) <= 3, "the waist's goal is not where it is: the arm does not hold"


async def test_a_servo_that_stops_answering_and_bad_crcs(vbus: Vbus) -> None:
    async with await open_dxl_bus(vbus.path, margin_s=MARGIN_MS / 1e3) as bus:
        arm = DxlArm(bus, SLACK, max_crc_errors=2)
        await arm.start()
        await arm.read_state(0)
        assert vbus.send("crc 2 1") == "ok crc 2 1"
        await arm.read_state(0)  # one bad CRC: retried within the call
        assert bus.stats.crc_errors >= 1
        assert vbus.send("crc 2 -1") == "ok crc 2 -1"
        with pytest.raises(DxlCrcError):
            await arm.read_state(0)
        with pytest.raises(RobotError, match=r"2 ticks in a row with bad status CRCs"):
            await arm.read_state(0)
        assert vbus.send("clear") == "ok clear"
        await arm.read_state(0)
        assert vbus.send("silent 6") == "ok silent 6"
        with pytest.raises(RobotError, match=r"joint 'wrist_rotate' \(servo ID 6\) does not answer"):
            await arm.read_state(0)


async def test_goals_past_a_limit_are_clamped_or_refused_as_the_bridges_do_and_said_once(
    vbus: Vbus, caplog: pytest.LogCaptureFixture
) -> None:
    elbow_max = ticks_to_rad(3106)  # rx200.yaml's elbow limit
    async with await open_dxl_bus(vbus.path, margin_s=MARGIN_MS / 1e3) as bus:
        arm = DxlArm(bus, SLACK)
        await arm.start()
        with caplog.at_level(logging.WARNING, logger="uniros_async.hardware.dxl.arm"):
            for _ in range(3):  # a hair past the limit: clamped to it, as the bridges and the servo sim clip it
                await arm.write_goals(np.array([0.0, 0.0, elbow_max + 0.04, 0.0, 0.0]))
            assert _present(vbus.path, (4,))[4][1] == 3106  # the goal on the wire is the limit's ticks
            for _ in range(3):  # far past it: refused, and the arm keeps the goal it had
                await arm.write_goals(np.array([0.3, 0.0, 2.5, 0.0, 0.0]))
        clamped = [r.getMessage() for r in caplog.records if "clamped" in r.getMessage()]
        refused = [r.getMessage() for r in caplog.records if "not sent" in r.getMessage()]
        assert len(clamped) == 1 and "elbow" in clamped[0]
        assert len(refused) == 1 and "beyond the joint limits (by more than 0.05 rad)" in refused[0]
        assert "'elbow': '2.5000 not in [" in refused[0]
        assert (arm.clamped, arm.refused) == (3, 3)
        goals = _present(vbus.path, (1, 4))
        assert goals[4][1] == 3106 and goals[1][1] == 2048  # the waist's 0.3 rad went with the refused goal
        await arm.close()


def test_the_clamp_margin_is_the_ros_bridges() -> None:
    from uniros_async.adapters._bridge import LIMIT_CLAMP_RAD as BRIDGES

    assert LIMIT_CLAMP_RAD == BRIDGES


async def test_shutdown_rest_moves_to_the_rest_pose_before_torque_off(vbus: Vbus) -> None:
    async with await open_dxl_bus(vbus.path, margin_s=MARGIN_MS / 1e3) as bus:
        arm = DxlArm(bus, SLACK, shutdown="rest")
        await arm.start()
        await arm.close(timeout_s=8.0)
    rest = (0.0, -1.80, 1.55, 0.8, 0.0)  # rx200.yaml's sleep_positions
    after = _present(vbus.path, (1, 2, 4, 5, 6))
    for servo_id, q in zip((1, 2, 4, 5, 6), rest, strict=True):
        present, _, torque = after[servo_id]
        assert torque == 0
        assert abs(present - rad_to_ticks(q)) <= 25, (servo_id, present, q)


def test_dxl_uri_forms_and_errors() -> None:
    uri = parse_dxl_uri("dxl:///dev/pts/4?baud=57600&map=rx200&rate=25&shutdown=rest")
    assert (uri.path, uri.baud, uri.map_name, uri.rate_hz, uri.shutdown) == ("/dev/pts/4", 57600, "rx200", 25.0, "rest")
    assert parse_dxl_uri("dxl:///dev/ttyUSB0").baud is None
    with pytest.raises(ConfigError, match=r"unknown query key\(s\) \['speed'\]"):
        parse_dxl_uri("dxl:///dev/ttyUSB0?speed=1")
    with pytest.raises(ConfigError, match="expected a serial device path"):
        parse_dxl_uri("dxl://host/dev/ttyUSB0")
    with pytest.raises(ConfigError, match="shutdown must be 'hold' or 'rest'"):
        parse_dxl_uri("dxl:///dev/ttyUSB0?shutdown=drop")
    assert parse_dxl_uri("dxl:///dev/ttyUSB0?profile_ms=0").profile_ms == 0
    assert parse_dxl_uri("dxl:///dev/ttyUSB0").profile_ms is None  # the map's
    for bad in ("-5", "fast", "40000"):
        with pytest.raises(ConfigError, match=rf"profile_ms must be an integer in 0\.\.32767 .*got '{bad}'"):
            parse_dxl_uri(f"dxl:///dev/ttyUSB0?profile_ms={bad}")


async def test_the_map_profile_sets_how_fast_a_goal_is_reached(vbus: Vbus) -> None:
    """Interbotix's 2 s time profile spreads each goal over 2 s (renewed every tick, the arm crawls); with the
    profile at 0 the servos run to each goal at full speed, as the servo sim the policies trained on does."""
    reached = {}
    for profile_ms in (2000, 0):
        async with await open_dxl_bus(vbus.path, margin_s=MARGIN_MS / 1e3) as bus:
            arm = DxlArm(bus, SLACK.with_arm_profile(profile_ms))
            await arm.start()
            with sdk_port(vbus.path) as (port, ph):
                assert read(ph, port, 1, 112, 4) == profile_ms  # Profile_Velocity: ms with a time profile
            q0 = (await arm.read_state(0)).joint_state.position[:5]
            goal = q0 + np.array([0.3, 0.0, 0.0, 0.0, 0.0])
            for _ in range(12):  # 0.6 s of 20 Hz ticks
                await arm.write_goals(goal)
                await _sleep(0.05)
            q = (await arm.read_state(0)).joint_state.position[:5]
            reached[profile_ms] = float(q[0] - q0[0])
            await arm.close()
    assert reached[0] > 0.25, reached  # there within 0.6 s
    assert reached[2000] < 0.15, reached  # a third of the way or less


async def test_a_bus_silent_past_the_watchdog_is_a_robot_error(vbus: Vbus) -> None:
    async with await open_dxl_bus(vbus.path, margin_s=MARGIN_MS / 1e3) as bus:
        arm = DxlArm(bus, RX200)
        await arm.start()
        await _sleep(0.25)  # before the first command: the watchdog's stop held the servos where start-up put them
        await arm.read_state(0)  # armed again, no error
        state = await arm.read_state(0)
        await arm.write_goals(state.joint_state.position[:5])
        await _sleep(0.25)  # this host stalls while it commands the arm: the servos' 100 ms watchdog stops them
        with pytest.raises(RobotError, match=r"the bus was silent for \d+ ms, longer than the servos' Bus Watchdog"):
            await arm.read_state(0)
    assert vbus.expect(("watchdog id=1",), 2.0)


async def test_servos_stopped_by_their_watchdog_are_found_even_when_the_host_saw_no_silence(vbus: Vbus) -> None:
    async with await open_dxl_bus(vbus.path, margin_s=MARGIN_MS / 1e3) as bus:
        arm = DxlArm(bus, RX200)
        await arm.start()
        await _sleep(0.25)  # before the first command the stop held the servos where start-up put them: armed again
        await arm.check_watchdogs()
        with sdk_port(vbus.path) as (port, ph):
            assert read(ph, port, 1, 98, 1) == 5  # 100 ms in 20 ms units, armed again
        state = await arm.read_state(0)
        await arm.write_goals(state.joint_state.position[:5])
        # the host's packets held up past the watchdog (here: none sent), seen by the servos and not by the host
        await _sleep(0.25)
        with pytest.raises(RobotError, match=r"'waist' \(servo ID 1\).*stopped on the Bus Watchdog \(100 ms\)"):
            await arm.check_watchdogs()
    assert vbus.expect(("watchdog id=1",), 2.0)


def test_the_bus_loop_keeps_two_ticks_per_watchdog_window() -> None:
    from uniros_async.hardware.dxl.placement import _rate

    assert _rate(None, 100, 10.0) == 20.0  # a 10 Hz env loop: the bus ticks at 20 Hz for a 100 ms watchdog
    assert _rate(None, 100, 100.0) == 100.0
    assert _rate(50.0, 100, 10.0) == 50.0
    with pytest.raises(ConfigError, match=r"dxl rate=10 Hz: the servos' bus watchdog is 100 ms, so the bus loop needs"):
        _rate(10.0, 100, 10.0)


def test_open_error_names_the_tty() -> None:
    import asyncio

    from uniros_async.errors import DxlPortError

    async def main() -> None:
        await open_dxl_bus("/dev/ttyNOPE9")

    with pytest.raises(DxlPortError, match="/dev/ttyNOPE9"):
        asyncio.run(main())


async def _sleep(s: float) -> None:
    import asyncio

    await asyncio.sleep(s)


async def test_the_arms_node_serves_its_stats_with_current_and_temperature(vbus: Vbus) -> None:
    import asyncio

    from uniros_async.bus import open_domain, open_node
    from uniros_async.bus.messages import Data, Empty, JointState
    from uniros_async.hardware.dxl.placement import open_dxl_arm
    from uniros_async.robots import get_robot_spec

    async with (
        open_domain("memory://") as domain,
        open_dxl_arm(
            vbus.path, get_robot_spec("rx200"), SLACK, domain=domain, rate_hz=50, margin_s=MARGIN_MS / 1e3
        ) as arm_node,
        open_node("probe", domain=domain, namespace="/rx200") as probe,
    ):
        states = await probe.create_subscription(JointState, "joint_states")
        await asyncio.sleep(0.5)
        stats = (await probe.create_client(Empty, Data, "stats").call(Empty())).value
        assert stats["rate_hz"] == 50 and stats["ticks"] >= 15 and stats["error"] == ""
        assert set(stats["temperature_c"]) == {"waist", "shoulder", "elbow", "wrist_angle", "wrist_rotate", "gripper"}
        assert all(t == 30.0 for t in stats["temperature_c"].values())  # what the virtual servos report
        assert set(stats["current_a"]) == {"shoulder", "elbow"}
        assert stats["cycle_p50_us"] is not None and stats["cycle_p50_us"] > 0
        latest = states.latest()
        assert latest is not None and latest.name == get_robot_spec("rx200").joint_state_names
        assert arm_node.ticks >= 15
