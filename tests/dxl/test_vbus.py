"""The virtual servo bus against unmodified dynamixel-sdk from PyPI: a real ``uniros robot vbus`` process on a real
pty, the rx200's MuJoCo servo sim behind it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator

import dynamixel_sdk as sdk
import pytest

from uniros_async.hardware.dxl.control_table import MODELS, rad_to_ticks
from uniros_async.hardware.dxl.servo_map import servo_map

from ._vbus import MARGIN_MS, Vbus, ping_ok, pty_gone, read, running_vbus, sdk_port

pytestmark = pytest.mark.slow

RX200 = servo_map("rx200")
ARM_IDS = (1, 2, 4, 5, 6)  # the shoulder's shadow (3) follows 2
TORQUE_ENABLE, GOAL_POSITION, PRESENT_POSITION, BUS_WATCHDOG = 64, 116, 132, 98
PROFILE_VELOCITY, HARDWARE_ERROR = 112, 70


@pytest.fixture(scope="module")
def vbus() -> Iterator[Vbus]:
    with running_vbus() as bus:
        yield bus


def test_sdk_pings_and_reads_every_servo_with_its_model(vbus: Vbus) -> None:
    with sdk_port(vbus.path) as (port, ph):
        for servo in RX200.servos:
            model, result, error = ph.ping(port, servo.id)
            assert (result, error) == (sdk.COMM_SUCCESS, 0), (servo.id, ph.getTxRxResult(result))
            assert model == MODELS[servo.model].model_number
            value, result, error = ph.read1ByteTxRx(port, servo.id, 7)  # ID
            assert (value, result, error) == (servo.id, sdk.COMM_SUCCESS, 0)
            limits = [read(ph, port, servo.id, a, 4) for a in (52, 48)]
            assert limits == [servo.min_position, servo.max_position]
            secondary, _, _ = ph.read1ByteTxRx(port, servo.id, 12)
            assert secondary == (2 if servo.id == 3 else 255)
        # a servo that is not on the bus does not answer
        _, result, _ = ph.ping(port, 9)
        assert result == sdk.COMM_RX_TIMEOUT


def test_sdk_writes_and_the_access_rules_hold(vbus: Vbus) -> None:
    with sdk_port(vbus.path) as (port, ph):
        assert ph.write1ByteTxRx(port, 6, TORQUE_ENABLE, 1) == (sdk.COMM_SUCCESS, 0)
        # EEPROM (Drive_Mode, 10) is locked while the torque is on: access error 7
        assert ph.write1ByteTxRx(port, 6, 10, 4) == (sdk.COMM_SUCCESS, 7)
        # Present_Position is read-only: access error 7
        assert ph.write4ByteTxRx(port, 6, PRESENT_POSITION, 100) == (sdk.COMM_SUCCESS, 7)
        # a goal past Max_Position_Limit (the elbow's 3106): data limit error 6
        assert ph.write1ByteTxRx(port, 4, TORQUE_ENABLE, 1) == (sdk.COMM_SUCCESS, 0)
        assert ph.write4ByteTxRx(port, 4, GOAL_POSITION, 3500) == (sdk.COMM_SUCCESS, 6)
        present, _, _ = ph.read4ByteTxRx(port, 4, PRESENT_POSITION)
        assert ph.write4ByteTxRx(port, 4, GOAL_POSITION, present) == (sdk.COMM_SUCCESS, 0)
        assert read(ph, port, 4, GOAL_POSITION, 4) == present
        for servo_id in (4, 6):
            assert ph.write1ByteTxRx(port, servo_id, TORQUE_ENABLE, 0) == (sdk.COMM_SUCCESS, 0)
        # with the torque off, EEPROM takes the write
        assert ph.write1ByteTxRx(port, 6, 10, 4) == (sdk.COMM_SUCCESS, 0)
        assert read(ph, port, 6, 10, 1) == 4


def test_sdk_sync_write_moves_the_arm_and_sync_read_sees_it(vbus: Vbus) -> None:
    goal_rad = {1: 0.4, 2: -0.3, 4: 0.5, 5: -0.4, 6: 0.6}
    with sdk_port(vbus.path) as (port, ph):
        sync_read = sdk.GroupSyncRead(port, ph, PRESENT_POSITION, 4)
        for servo in RX200.servos:
            assert sync_read.addParam(servo.id)
        assert sync_read.txRxPacket() == sdk.COMM_SUCCESS
        start = {s.id: sync_read.getData(s.id, PRESENT_POSITION, 4) for s in RX200.servos}
        # the shadow reports the primary's ticks (its reverse drive mode mirrors its mounting)
        assert abs(start[3] - start[2]) <= 1
        # start-up as the host does it: goal := present, a 300 ms time profile, then torque on
        profile = sdk.GroupSyncWrite(port, ph, PROFILE_VELOCITY, 4)
        goals = sdk.GroupSyncWrite(port, ph, GOAL_POSITION, 4)
        torque = sdk.GroupSyncWrite(port, ph, TORQUE_ENABLE, 1)
        for servo_id in ARM_IDS:
            # Drive_Mode: the time profile bit (torque is off)
            assert ph.write1ByteTxRx(port, servo_id, 10, RX200.drive_mode(RX200.by_id(servo_id)))[1] == 0
            assert profile.addParam(servo_id, (300).to_bytes(4, "little"))
            assert goals.addParam(servo_id, start[servo_id].to_bytes(4, "little"))
            assert torque.addParam(servo_id, b"\x01")
        assert profile.txPacket() == sdk.COMM_SUCCESS
        assert goals.txPacket() == sdk.COMM_SUCCESS
        assert torque.txPacket() == sdk.COMM_SUCCESS
        # the shadow obeyed the writes to ID 2 (Secondary_ID) without answering them
        assert read(ph, port, 3, TORQUE_ENABLE, 1) == 1
        goals.clearParam()
        for servo_id, q in goal_rad.items():
            assert goals.addParam(servo_id, rad_to_ticks(q).to_bytes(4, "little"))
        assert goals.txPacket() == sdk.COMM_SUCCESS
        deadline = time.monotonic() + 5.0
        while True:
            assert sync_read.txRxPacket() == sdk.COMM_SUCCESS
            now = {s.id: sync_read.getData(s.id, PRESENT_POSITION, 4) for s in RX200.servos}
            if all(abs(now[i] - rad_to_ticks(q)) <= 25 for i, q in goal_rad.items()):
                break
            assert time.monotonic() < deadline, f"the arm did not reach its goals: {now}"
            time.sleep(0.02)
        assert abs(now[3] - now[2]) <= 2
        # the contiguous present current/velocity/position block of Interbotix's driver, in one sync read
        block = sdk.GroupSyncRead(port, ph, 126, 10)
        for servo in RX200.servos:
            assert block.addParam(servo.id)
        assert block.txRxPacket() == sdk.COMM_SUCCESS
        for servo in RX200.servos:
            assert block.isAvailable(servo.id, 126, 10)
        # torque off again for the other tests
        torque.clearParam()
        for servo_id in ARM_IDS:
            torque.addParam(servo_id, b"\x00")
        assert torque.txPacket() == sdk.COMM_SUCCESS


def test_faults_on_command(vbus: Vbus) -> None:
    with sdk_port(vbus.path) as (port, ph):
        assert vbus.send("crc 5 1") == "ok crc 5 1"
        assert ph.ping(port, 5)[1] == sdk.COMM_RX_CORRUPT
        assert ping_ok(ph, port, 5)[1] == 0
        assert vbus.send("drop 5") == "ok drop 5"
        assert ph.ping(port, 5)[1] == sdk.COMM_RX_TIMEOUT
        ping_ok(ph, port, 5)
        assert vbus.send("silent 6") == "ok silent 6"
        assert ph.ping(port, 6)[1] == sdk.COMM_RX_TIMEOUT
        assert vbus.send("answer 6") == "ok answer 6"
        ping_ok(ph, port, 6)
        # a hardware error: the alert bit in every status, the bits in Hardware_Error_Status, torque off
        assert ph.write1ByteTxRx(port, 1, TORQUE_ENABLE, 1) == (sdk.COMM_SUCCESS, 0)
        assert vbus.send("error 1 0x20") == "ok error 1 0x20"
        value, result, error = ph.read1ByteTxRx(port, 1, HARDWARE_ERROR)
        assert (value, result, error) == (0x20, sdk.COMM_SUCCESS, 0x80)
        assert read(ph, port, 1, TORQUE_ENABLE, 1) == 0
        assert ph.reboot(port, 1) == (sdk.COMM_SUCCESS, 0)
        assert ph.read1ByteTxRx(port, 1, HARDWARE_ERROR)[:2] == (0, sdk.COMM_SUCCESS)
        # a bus that stops
        assert vbus.send("stop") == "ok stop"
        assert ph.ping(port, 1)[1] == sdk.COMM_RX_TIMEOUT
        assert vbus.send("start") == "ok start"
        ping_ok(ph, port, 1)
        # bad control lines are answered, and the bus goes on
        assert vbus.send("crc 99").startswith("error: 'crc 99': no servo ID 99")
        assert vbus.send("wobble").startswith("error: 'wobble': expected one of")
        assert vbus.send("clear") == "ok clear"
        ping_ok(ph, port, 1)


_HOST = textwrap.dedent(
    """
    import sys, time
    import dynamixel_sdk as sdk
    port = sdk.PortHandler(sys.argv[1]); assert port.openPort(); port.setBaudRate(1000000)
    ph = sdk.PacketHandler(2.0)
    start = ph.read4ByteTxRx(port, 1, 132)[0]
    ph.write1ByteTxRx(port, 1, 98, 5)            # Bus Watchdog 5 x 20 ms = 100 ms
    ph.write4ByteTxRx(port, 1, 116, start)      # goal := present
    ph.write1ByteTxRx(port, 1, 64, 1)           # torque on
    ph.write4ByteTxRx(port, 1, 116, start + 1500)  # a long move of the waist
    print("moving", flush=True)
    while True:                                  # the env loop: it talks to the bus every 10 ms
        ph.read4ByteTxRx(port, 1, 132)
        time.sleep(0.01)
    """
)


def test_watchdog_stops_and_holds_the_servo_after_its_host_is_killed(tmp_path: object) -> None:
    with running_vbus() as vbus:
        host = subprocess.Popen([sys.executable, "-c", _HOST, vbus.path], stdout=subprocess.PIPE, text=True)
        try:
            assert host.stdout is not None and host.stdout.readline().strip() == "moving"
            time.sleep(0.3)  # mid-move
            host.send_signal(signal.SIGKILL)
            killed = time.monotonic()
            host.wait(5)
        finally:
            if host.poll() is None:
                host.kill()
                host.wait()
            assert host.stdout is not None
            host.stdout.close()
        event = vbus.expect(("watchdog id=1",), 2.0)
        tripped = float(event.rsplit("t=", 1)[1])
        # the servo stops within its watchdog time of the host's last instruction (before the kill)
        assert tripped - killed <= 0.100 + 0.015, event
        time.sleep(0.3)  # let the arm come to rest after its stop
        with sdk_port(vbus.path) as (port, ph):
            first = read(ph, port, 1, PRESENT_POSITION, 4)
            time.sleep(0.3)
            second = read(ph, port, 1, PRESENT_POSITION, 4)
            assert abs(second - first) <= 2, "the waist still moves after its watchdog fired"
            assert read(ph, port, 1, BUS_WATCHDOG, 1) == 0xFF  # -1: the watchdog error
            assert read(ph, port, 1, TORQUE_ENABLE, 1) == 1  # held, never dropped
            goal = read(ph, port, 1, GOAL_POSITION, 4)
            assert goal < rad_to_ticks(0.0) + 1500 - 100, "the goal was not replaced by the stop position"
            # goals are refused until the host clears the watchdog error
            assert ph.write4ByteTxRx(port, 1, GOAL_POSITION, second)[1] == 7
            assert ph.write1ByteTxRx(port, 1, BUS_WATCHDOG, 0) == (sdk.COMM_SUCCESS, 0)
            assert ph.write4ByteTxRx(port, 1, GOAL_POSITION, second) == (sdk.COMM_SUCCESS, 0)


def test_vbus_stops_on_sigint_and_leaves_no_pty() -> None:
    with running_vbus("--emulate-real", "--seed", "2") as vbus:
        with sdk_port(vbus.path) as (port, ph):
            ping_ok(ph, port, 1)
        assert vbus.stop() == 0
        assert pty_gone(vbus.path), f"{vbus.path} is still there after the vbus ended"


def test_unknown_servo_map_is_a_clear_error() -> None:
    argv = [sys.executable, "-m", "uniros_async.cli", "robot", "vbus", "rx20"]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=60, env={**os.environ})
    assert done.returncode != 0
    assert "unknown servo map 'rx20' (did you mean 'rx200'?)" in done.stderr


async def test_our_client_fast_sync_reads_bulk_reads_and_bulk_writes_the_virtual_bus(vbus: Vbus) -> None:
    from uniros_async.hardware.dxl.bus import open_dxl_bus

    ids = [s.id for s in RX200.servos]
    async with await open_dxl_bus(vbus.path, margin_s=MARGIN_MS / 1e3) as bus:
        plain = await bus.sync_read(PRESENT_POSITION, 4, ids)
        fast = await bus.fast_sync_read(PRESENT_POSITION, 4, ids)
        assert set(fast) == set(ids)
        for i in ids:
            a, b = (int.from_bytes(x[i], "little", signed=True) for x in (plain, fast))
            assert abs(a - b) <= 3, (i, a, b)
        # bulk: each servo its own register
        got = await bus.bulk_read([(1, 7, 1), (2, 12, 1), (3, 12, 1), (7, 11, 1)])
        assert (got[1], got[2], got[3]) == (b"\x01", b"\xff", b"\x02")
        await bus.bulk_write([(6, 65, b"\x01"), (7, 65, b"\x01")])  # LEDs
        assert await bus.read(6, 65, 1) == b"\x01" and await bus.read(7, 65, 1) == b"\x01"
        await bus.bulk_write([(6, 65, b"\x00"), (7, 65, b"\x00")])
