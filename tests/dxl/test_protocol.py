"""Protocol 2.0 packets: byte-equal to dynamixel-sdk's, round trips with stuffing and CRC, the stream parser, the
fast sync read answer, and the control tables."""

from __future__ import annotations

import contextlib
import os
import pty
import random
import select
import time
import tty
from collections.abc import Callable, Iterator
from typing import Any

import dynamixel_sdk as sdk
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from uniros_async.errors import CodecError, ConfigError, DxlCrcError
from uniros_async.hardware.dxl import control_table as ct
from uniros_async.hardware.dxl import protocol as p
from uniros_async.hardware.dxl.protocol import Instruction

# ------------------------------------------------------------------------------ dynamixel-sdk, on a pty


@pytest.fixture
def sdk_port() -> Iterator[tuple[Any, Any, int]]:
    """dynamixel-sdk's PortHandler on a pty's slave end; the test reads what it sends from the master."""
    master, slave = pty.openpty()
    tty.setraw(master)
    port = sdk.PortHandler(os.ttyname(slave))
    assert port.openPort()
    try:
        yield port, sdk.PacketHandler(2.0), master
    finally:
        port.closePort()
        os.close(slave)
        os.close(master)


def _sent(port: Any, master: int, action: Callable[[], object]) -> bytes:
    """Run ``action`` (dynamixel-sdk sending one packet) and return the bytes of the packet that came out of the pty."""
    action()
    port.is_using = False  # a *Tx call leaves the port busy until its Rx call, which these tests do not make
    out = b""
    parser = p.PacketParser()
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline:
        ready, _, _ = select.select([master], [], [], 0.05)
        if ready:
            chunk = os.read(master, 4096)
            out += chunk
            if parser.feed(chunk):
                break
    # nothing more than the one packet
    ready, _, _ = select.select([master], [], [], 0.01)
    if ready:
        out += os.read(master, 4096)
    return out


def test_packets_are_byte_equal_to_dynamixel_sdk(sdk_port: tuple[Any, Any, int]) -> None:
    port, ph, master = sdk_port
    cases: list[tuple[str, Callable[[], object], bytes]] = []

    cases.append(("ping", lambda: ph.ping(port, 7), p.encode_instruction(7, Instruction.PING)))
    cases.append(
        (
            "read",
            lambda: ph.readTx(port, 3, 132, 4),
            p.encode_instruction(3, Instruction.READ, p.read_params(132, 4)),
        )
    )
    cases.append(
        (
            "write",
            lambda: ph.write4ByteTxOnly(port, 2, 116, 2048),
            p.encode_instruction(2, Instruction.WRITE, p.write_params(116, (2048).to_bytes(4, "little"))),
        )
    )
    # data that holds the header pattern FF FF FD: stuffed by both
    cases.append(
        (
            "write (stuffed)",
            lambda: ph.write4ByteTxOnly(port, 2, 116, 0x00FDFFFF),
            p.encode_instruction(2, Instruction.WRITE, p.write_params(116, b"\xff\xff\xfd\x00")),
        )
    )
    cases.append(("reboot", lambda: ph.reboot(port, 5), p.encode_instruction(5, Instruction.REBOOT)))

    ids = [1, 2, 3, 4, 5, 6, 7]
    sync_read = sdk.GroupSyncRead(port, ph, 126, 10)
    for i in ids:
        sync_read.addParam(i)
    cases.append(
        (
            "sync read",
            sync_read.txPacket,
            p.encode_instruction(p.BROADCAST_ID, Instruction.SYNC_READ, p.sync_read_params(126, 10, ids)),
        )
    )
    cases.append(
        (
            "fast sync read",
            sync_read.fastSyncReadTxPacket,
            p.encode_instruction(p.BROADCAST_ID, Instruction.FAST_SYNC_READ, p.sync_read_params(126, 10, ids)),
        )
    )
    goals = {i: (2048 + 37 * i).to_bytes(4, "little") for i in ids}
    sync_write = sdk.GroupSyncWrite(port, ph, 116, 4)
    for i, data in goals.items():
        sync_write.addParam(i, list(data))
    cases.append(
        (
            "sync write",
            sync_write.txPacket,
            p.encode_instruction(p.BROADCAST_ID, Instruction.SYNC_WRITE, p.sync_write_params(116, 4, goals)),
        )
    )
    reads = [(1, 132, 4), (2, 126, 10), (7, 146, 1)]
    bulk_read = sdk.GroupBulkRead(port, ph)
    for servo_id, address, length in reads:
        bulk_read.addParam(servo_id, address, length)
    cases.append(
        (
            "bulk read",
            bulk_read.txPacket,
            p.encode_instruction(p.BROADCAST_ID, Instruction.BULK_READ, p.bulk_read_params(reads)),
        )
    )
    writes = [(1, 116, (1000).to_bytes(4, "little")), (2, 64, b"\x01"), (3, 102, (300).to_bytes(2, "little"))]
    bulk_write = sdk.GroupBulkWrite(port, ph)
    for servo_id, address, data in writes:
        bulk_write.addParam(servo_id, address, len(data), list(data))
    cases.append(
        (
            "bulk write",
            bulk_write.txPacket,
            p.encode_instruction(p.BROADCAST_ID, Instruction.BULK_WRITE, p.bulk_write_params(writes)),
        )
    )

    for name, action, ours in cases:
        theirs = _sent(port, master, action)
        if "stuffed" in name:
            # dynamixel-sdk 4.1's Python txPacket drops addStuffing's result when the packet grows, so it sends
            # FF FF FD unstuffed; ours follows the spec. Both parse to the same instruction.
            assert len(ours) == len(theirs) + 1 and theirs != ours, name
            assert p.PacketParser(raise_on_crc=True).feed(theirs) == p.PacketParser().feed(ours), name
            continue
        assert theirs == ours, f"{name}: dynamixel-sdk sent {theirs.hex(' ')}, we encode {ours.hex(' ')}"
        assert p.instruction_bytes(ours[4], ours[7], p.PacketParser().feed(ours)[0].params) == len(ours), name


def test_the_e_manual_examples_encode_as_printed() -> None:
    # ROBOTIS e-manual, Protocol 2.0, "Instruction Details": ping, read and write of ID 1, and their status packets
    assert p.encode_instruction(1, Instruction.PING).hex() == "fffffd0001030001194e"
    assert p.encode_status(1, 0, bytes.fromhex("060426")).hex() == "fffffd0001070055000604 26655d".replace(" ", "")
    assert p.encode_instruction(1, Instruction.READ, p.read_params(132, 4)).hex() == "fffffd0001070002840004001d15"
    assert p.encode_instruction(1, Instruction.WRITE, p.write_params(116, (512).to_bytes(4, "little"))).hex() == (
        "fffffd0001090003740000020000ca89"
    )


@given(st.binary(max_size=300))
@settings(max_examples=200, deadline=None)
def test_crc_matches_dynamixel_sdk(data: bytes) -> None:
    assert p.crc16(data) == sdk.Protocol2PacketHandler().updateCRC(0, list(data), len(data))
    # continued CRCs compose
    half = len(data) // 2
    assert p.crc16(data[half:], p.crc16(data[:half])) == p.crc16(data)


# ------------------------------------------------------------------------------------------ round trips

_header_heavy = st.lists(st.sampled_from([b"\xff", b"\xfd", b"\x00", b"\xff\xff\xfd", b"\x55"]), max_size=40).map(
    b"".join
)
_params = st.one_of(st.binary(max_size=200), _header_heavy)
_ids = st.integers(0, p.MAX_ID)


def _chunks(data: bytes, rng: random.Random) -> Iterator[bytes]:
    i = 0
    while i < len(data):
        n = rng.randint(1, 17)
        yield data[i : i + n]
        i += n


@given(_ids | st.just(p.BROADCAST_ID), st.sampled_from(list(Instruction)), _params, st.integers(0, 2**32 - 1))
@settings(max_examples=200, deadline=None)
def test_instruction_round_trip_in_any_chunks(servo_id: int, inst: Instruction, params: bytes, seed: int) -> None:
    if inst == Instruction.STATUS:
        return  # a status packet has an error byte; the next test covers it
    wire = p.encode_instruction(servo_id, inst, params)
    assert b"\xff\xff\xfd\x00" not in wire[4:], "stuffing left a header inside the packet"
    parser = p.PacketParser(raise_on_crc=True)
    got = [pkt for chunk in _chunks(wire, random.Random(seed)) for pkt in parser.feed(chunk)]
    assert got == [p.Packet(servo_id, inst, params, None)]
    assert got[0].raw == wire and parser.buffered == 0 and parser.skipped_bytes == 0


@given(_ids, st.integers(0, 255), _params, st.binary(max_size=30), st.integers(0, 2**32 - 1))
@settings(max_examples=200, deadline=None)
def test_status_round_trip_after_noise(servo_id: int, error: int, params: bytes, noise: bytes, seed: int) -> None:
    # noise that cannot itself hold a header, then two packets back to back
    noise = noise.replace(b"\xff", b"\x00")
    first = p.encode_status(servo_id, error, params)
    second = p.encode_status((servo_id + 1) % (p.MAX_ID + 1), 0, params[::-1])
    parser = p.PacketParser()
    got = [pkt for chunk in _chunks(noise + first + second, random.Random(seed)) for pkt in parser.feed(chunk)]
    assert [(g.servo_id, g.error, g.params) for g in got] == [
        (servo_id, error, params),
        ((servo_id + 1) % (p.MAX_ID + 1), 0, params[::-1]),
    ]
    assert parser.skipped_bytes == len(noise) and parser.crc_errors == 0


@given(st.binary(max_size=300))
@settings(max_examples=200, deadline=None)
def test_unstuff_inverts_stuff_and_agrees_with_dynamixel_sdk(body: bytes) -> None:
    stuffed = p.stuff(body)
    assert p.unstuff(stuffed) == body
    # dynamixel-sdk's addStuffing on the same instruction packet gives the same length and bytes
    handler = sdk.Protocol2PacketHandler()
    packet = [0xFF, 0xFF, 0xFD, 0x00, 1, (len(body) + 3) & 0xFF, (len(body) + 3) >> 8, 0x03, *body, 0, 0]
    theirs = handler.addStuffing(packet)
    assert bytes(theirs[8:-2]) == p.stuff(b"\x03" + body)[1:]


def test_a_bad_crc_is_counted_named_and_the_stream_goes_on() -> None:
    good = p.encode_status(4, 0, b"\x01\x02\x03\x04")
    bad = bytearray(p.encode_status(5, 0, b"\x01\x02\x03\x04"))
    bad[-1] ^= 0x55
    parser = p.PacketParser()
    assert [pkt.servo_id for pkt in parser.feed(bytes(bad) + good)] == [4]
    assert parser.crc_errors == 1 and parser.last_crc_error is not None
    assert parser.last_crc_error.servo_id == 5 and "servo 5" in str(parser.last_crc_error)

    strict = p.PacketParser(raise_on_crc=True)
    with pytest.raises(DxlCrcError, match="servo 5") as info:
        strict.feed(good + bytes(bad) + good)
    assert info.value.servo_id == 5
    # the packet completed before the bad one, and the one after, come with the next feed
    assert [pkt.servo_id for pkt in strict.feed(b"")] == [4, 4]


def test_parser_skips_what_cannot_start_a_packet() -> None:
    good = p.encode_status(1, 0, b"\x10")
    junk = [
        b"\xff\xff\xfd\x01\x01\x04\x00\x55\x00",  # reserved byte not 0
        b"\xff\xff\xfd\x00\xfd\x04\x00",  # id 0xFD
        b"\xff\xff\xfd\x00\x01\xff\xff",  # length beyond the parser's maximum
        b"\xff\xff\xfd\x00\x01\x03\x00\x55",  # a status packet with no room for its error byte
    ]
    for j in junk:
        parser = p.PacketParser()
        assert parser.feed(j + good) == [p.Packet(1, Instruction.STATUS, b"\x10", 0)], j.hex(" ")


# ------------------------------------------------------------------------------------------ fast reads


def test_fast_sync_read_answer_round_trip_and_sdk_layout() -> None:
    slots = [(1, 0, bytes(range(10))), (2, 0x80, b"\xff\xff\xfd\x00" * 2 + b"\x01\x02"), (7, 0, bytes(10))]
    wire = p.encode_fast_sync_read_status(slots)
    # the length field counts instruction + every slot (error, id, data, CRC), as dynamixel-sdk expects
    assert wire[5] | (wire[6] << 8) == 1 + 3 * (10 + 4)
    (pkt,) = p.PacketParser(raise_on_crc=True).feed(wire)
    assert pkt.servo_id == p.BROADCAST_ID and pkt.error == 0
    got = p.parse_fast_sync_read(pkt, 10)
    assert [(s.servo_id, s.error, s.data) for s in got] == slots
    # dynamixel-sdk reads the same layout: ERR, ID, data, CRC per servo from the error byte on
    raw = list(wire)
    start = 8
    for servo_id, _error, data in slots:
        assert raw[start + 1] == servo_id and bytes(raw[start + 2 : start + 12]) == data
        start += 14


def test_fast_sync_read_slot_crc_names_its_servo() -> None:
    wire = bytearray(p.encode_fast_sync_read_status([(1, 0, bytes(4)), (2, 0, bytes(4)), (3, 0, bytes(4))]))
    wire[8 + 8 + 6] ^= 0x01  # the second slot's CRC, as a servo that got it wrong would send it
    crc = p.crc16(wire[:-2])  # the last servo's CRC covers the bytes before it, as sent
    wire[-2:] = bytes((crc & 0xFF, crc >> 8))
    (pkt,) = p.PacketParser(raise_on_crc=True).feed(bytes(wire))
    with pytest.raises(DxlCrcError, match="servo 2") as info:
        p.parse_fast_sync_read(pkt, 4)
    assert info.value.servo_id == 2
    with pytest.raises(CodecError, match="multiple of 9"):
        p.parse_fast_sync_read(pkt, 5)


# ------------------------------------------------------------------------------------------ bad input


def test_builders_refuse_bad_input_with_what_was_expected() -> None:
    with pytest.raises(ConfigError, match=r"servo id 253 .*expected 0\.\.252"):
        p.encode_instruction(253, Instruction.PING)
    with pytest.raises(ConfigError, match="expected 4"):
        p.sync_write_params(116, 4, {1: b"\x00\x00"})
    with pytest.raises(ConfigError, match="repeat"):
        p.sync_read_params(132, 4, [1, 1])
    with pytest.raises(ConfigError, match="twice"):
        p.bulk_read_params([(1, 132, 4), (1, 128, 4)])
    with pytest.raises(ConfigError, match="address 70000"):
        p.read_params(70000, 4)
    assert p.describe_status_error(0x84) == "data range error, hardware alert"


# --------------------------------------------------------------------------------------- control tables


def test_control_tables_hold_the_e_manual_facts() -> None:
    xm, xl, x3 = ct.model_by_number(1020), ct.model_by_number(1060), ct.model_by_number(1200)
    assert (xm.name, xl.name, x3.name) == ("XM430-W350", "XL430-W250", "XL330-M288")
    assert ct.MODELS["XM430-W350"] is xm
    for table in (xm, xl, x3):
        pos = table.register("present_position")
        assert (pos.address, pos.size, pos.access, pos.area, pos.signed) == (132, 4, "R", "RAM", True)
        assert table.register("goal_position").address == 116
        assert table.register("torque_enable").address == 64
        assert table.register("bus_watchdog").address == 98
        assert table.register("secondary_id").area == "EEPROM"
        # registers never overlap
        spans = sorted((r.address, r.address + r.size) for r in table.registers.values())
        assert all(a_end <= b_start for (_, a_end), (b_start, _) in zip(spans, spans[1:], strict=False))
    # the tick's read: present current (or load) .. present position, contiguous, 10 bytes
    assert xm.span("present_current", "present_position") == (126, 10)
    assert xl.span("present_load", "present_position") == (126, 10)
    assert "present_current" not in xl and xl.current_unit_a is None
    assert xm.current_unit_a == pytest.approx(2.69e-3) and x3.current_unit_a == pytest.approx(1e-3)
    assert x3.register("baud_rate").max == 6 and xm.register("baud_rate").max == 7
    with pytest.raises(ConfigError, match="has no register 'present_currnt'"):
        xm.register("present_currnt")
    with pytest.raises(ConfigError, match="model number 9999"):
        ct.model_by_number(9999)


def test_register_encoding_and_unit_conversions() -> None:
    xm = ct.XM430_W350
    assert xm.register("goal_position").encode(-5) == (-5).to_bytes(4, "little", signed=True)
    assert xm.register("present_velocity").decode((-3).to_bytes(4, "little", signed=True)) == -3
    with pytest.raises(ConfigError, match="read-only"):
        xm.register("present_position").encode(1)
    with pytest.raises(ConfigError, match=r"expected 0\.\.1"):
        xm.register("torque_enable").encode(2)
    assert ct.ticks_to_rad(2048) == 0.0 and ct.ticks_to_rad(3072) == pytest.approx(3.141592653589793 / 2)
    assert ct.rad_to_ticks(ct.ticks_to_rad(1234)) == 1234
    assert ct.velocity_to_rad_s(1) == pytest.approx(0.229 * 2 * 3.141592653589793 / 60)
    assert ct.rad_s_to_velocity(ct.velocity_to_rad_s(-77)) == -77
    assert ct.current_to_amps(100, xm) == pytest.approx(0.269)
    with pytest.raises(ConfigError, match="XL430-W250 has no current"):
        ct.current_to_amps(1, ct.XL430_W250)
    assert ct.voltage_to_volts(120) == pytest.approx(12.0)
    assert ct.baud_code(1_000_000) == 3
    with pytest.raises(ConfigError, match="baud rate 4500000"):
        ct.baud_code(4_500_000, ct.XL330_M288)


@contextlib.contextmanager
def _restore_models() -> Iterator[None]:
    saved = dict(ct.MODELS)
    try:
        yield
    finally:
        ct.MODELS.clear()
        ct.MODELS.update(saved)


def test_a_users_model_registers_and_clashes_are_refused() -> None:
    with _restore_models():
        mine = ct.ControlTable("MY-SERVO", 4242, dict(ct.XM430_W350.registers), 1e-3)
        ct.register_model(mine)
        assert ct.model_by_number(4242) is mine
        with pytest.raises(ConfigError, match="clashes with XM430-W350"):
            ct.register_model(ct.ControlTable("OTHER", 1020, {}, None))
    assert "MY-SERVO" not in ct.MODELS


def test_docs_list_every_register_as_the_tables_hold_it() -> None:
    import re
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[2] / "docs" / "dynamixel.md").read_text()
    for table in (ct.XL430_W250, ct.XM430_W350, ct.XL330_M288):
        section = doc.split(f"### {table.name} (model number {table.model_number})")[1].split("\n\n", 2)[1]
        rows = {}
        for line in section.splitlines()[2:]:
            cells = [c.strip() for c in line.strip("|").split("|")]
            rows[cells[2]] = cells
        expected = {name: reg for name, reg in table.registers.items() if not name.startswith("indirect_")}
        assert set(rows) == set(expected), table.name
        for name, reg in expected.items():
            address, size, _, access, area, unit, rng, default = rows[name]
            lo_hi = "" if reg.min is None and reg.max is None else f"{reg.min} .. {reg.max}"
            assert (int(address), int(size), access, area, unit, rng) == (
                reg.address,
                reg.size,
                reg.access,
                reg.area,
                reg.unit,
                lo_hi,
            ), f"{table.name} {name}"
            assert default == ("" if reg.default is None else str(reg.default)), f"{table.name} {name}"
    assert re.search(r"XM430-W350.*2\.69 mA", doc)
