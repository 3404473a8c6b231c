"""DxlBus on real ptys: against a small in-test responder built on protocol.py (fast), and against the virtual
servo bus process, ``uniros robot vbus rx200`` (slow)."""

from __future__ import annotations

import asyncio
import os
import pty
import select
import threading
import time
import tty
from collections.abc import Iterator

import pytest

from uniros_async.errors import ConfigError, DxlCrcError, DxlPortError, DxlStatusError, DxlTimeoutError, RobotError
from uniros_async.hardware.dxl import protocol as p
from uniros_async.hardware.dxl.bus import DxlBus, open_dxl_bus
from uniros_async.hardware.dxl.protocol import Instruction

from ._vbus import running_vbus

SLACK_S = 0.5
"""The bus's timeout margin against the responder: a thread of this process, so a loaded host can hold it up (the
margin bounds only calls that fail; a bad CRC is retried as soon as it is seen)."""


class Responder:
    """Servos on the master end of a pty: a register memory per id, answering from a thread.

    ``corrupt[id]`` status packets of ``id`` go out with a bad CRC, ``silent`` ids never answer, ``errors[id]``
    is the error byte ``id`` answers with, ``held[id]`` holds the second half of ``id``'s next status packet back for
    that many seconds (for an instruction only ``id`` answers), and ``once`` ids answer one instruction only.
    """

    def __init__(self, ids: list[int], model: int = 1020) -> None:
        self.master, self.slave = pty.openpty()
        tty.setraw(self.master)
        self.path = os.ttyname(self.slave)
        self.mem = {i: bytearray(700) for i in ids}
        for i, m in self.mem.items():
            m[0:2] = model.to_bytes(2, "little")
            m[6] = 46
            m[7] = i
            m[132:136] = (2000 + i).to_bytes(4, "little")
        self.corrupt: dict[int, int] = {}
        self.silent: set[int] = set()
        self.errors: dict[int, int] = {}
        self.held: dict[int, float] = {}
        self.once: set[int] = set()
        self.received: list[p.Packet] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        os.close(self.slave)
        os.close(self.master)

    def _status(self, servo_id: int, params: bytes) -> bytes:
        wire = bytearray(p.encode_status(servo_id, self.errors.get(servo_id, 0), params))
        if self.corrupt.get(servo_id, 0) > 0:
            self.corrupt[servo_id] -= 1
            wire[-1] ^= 0xFF
        if servo_id in self.once:
            self.silent.add(servo_id)
        hold = self.held.pop(servo_id, 0.0)
        if hold:
            half = len(wire) // 2
            os.write(self.master, bytes(wire[:half]))
            time.sleep(hold)
            return bytes(wire[half:])
        return bytes(wire)

    def _answer(self, pkt: p.Packet) -> bytes:
        out = b""
        prm = pkt.params
        if pkt.instruction == Instruction.SYNC_READ or pkt.instruction == Instruction.FAST_SYNC_READ:
            address, length = prm[0] | prm[1] << 8, prm[2] | prm[3] << 8
            ids = [i for i in prm[4:] if i in self.mem and i not in self.silent]
            if pkt.instruction == Instruction.FAST_SYNC_READ:
                return p.encode_fast_sync_read_status(
                    [(i, 0, bytes(self.mem[i][address : address + length])) for i in ids]
                )
            for i in ids:
                out += self._status(i, bytes(self.mem[i][address : address + length]))
            return out
        if pkt.instruction == Instruction.SYNC_WRITE:
            address, length = prm[0] | prm[1] << 8, prm[2] | prm[3] << 8
            for k in range(4, len(prm), length + 1):
                if prm[k] in self.mem:
                    self.mem[prm[k]][address : address + length] = prm[k + 1 : k + 1 + length]
            return b""
        if pkt.instruction == Instruction.BULK_READ:
            for k in range(0, len(prm), 5):
                i, address, length = prm[k], prm[k + 1] | prm[k + 2] << 8, prm[k + 3] | prm[k + 4] << 8
                if i in self.mem and i not in self.silent:
                    out += self._status(i, bytes(self.mem[i][address : address + length]))
            return out
        if pkt.instruction == Instruction.BULK_WRITE:
            k = 0
            while k < len(prm):
                i, address, length = prm[k], prm[k + 1] | prm[k + 2] << 8, prm[k + 3] | prm[k + 4] << 8
                self.mem[i][address : address + length] = prm[k + 5 : k + 5 + length]
                k += 5 + length
            return b""
        i = pkt.servo_id
        if i not in self.mem or i in self.silent:
            return b""
        if pkt.instruction == Instruction.PING:
            return self._status(i, bytes(self.mem[i][0:2]) + bytes((self.mem[i][6],)))
        if pkt.instruction == Instruction.READ:
            address, length = prm[0] | prm[1] << 8, prm[2] | prm[3] << 8
            return self._status(i, bytes(self.mem[i][address : address + length]))
        if pkt.instruction == Instruction.WRITE:
            address = prm[0] | prm[1] << 8
            self.mem[i][address : address + len(prm) - 2] = prm[2:]
            return self._status(i, b"")
        if pkt.instruction == Instruction.REBOOT:
            return self._status(i, b"")
        return b""

    def _run(self) -> None:
        parser = p.PacketParser()
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.05)
            if not ready:
                continue
            try:
                data = os.read(self.master, 4096)
            except OSError:
                continue
            for pkt in parser.feed(data):
                if pkt.is_status:
                    continue
                self.received.append(pkt)
                answer = self._answer(pkt)
                if answer:
                    os.write(self.master, answer)


@pytest.fixture
def responder() -> Iterator[Responder]:
    r = Responder([1, 2, 3, 4, 5])
    try:
        yield r
    finally:
        r.close()


async def test_every_instruction_against_the_responder(responder: Responder) -> None:
    async with await open_dxl_bus(responder.path, 1_000_000, margin_s=SLACK_S) as bus:
        assert await bus.ping(3) == (1020, 46)
        assert await bus.read(2, 132, 4) == (2002).to_bytes(4, "little")
        await bus.write(2, 116, (2100).to_bytes(4, "little"))
        assert responder.mem[2][116:120] == (2100).to_bytes(4, "little")
        assert await bus.sync_read(132, 4, [5, 1, 3]) == {i: (2000 + i).to_bytes(4, "little") for i in (5, 1, 3)}
        assert await bus.fast_sync_read(132, 4, [1, 2, 3, 4, 5]) == {
            i: (2000 + i).to_bytes(4, "little") for i in (1, 2, 3, 4, 5)
        }
        await bus.sync_write(116, 4, {1: b"\x01\x02\x03\x04", 4: b"\xff\xff\xfd\x00"})
        await bus.bulk_write([(5, 64, b"\x01"), (1, 65, b"\x01")])
        assert await bus.bulk_read([(4, 116, 4), (5, 64, 1), (1, 65, 1)]) == {
            4: b"\xff\xff\xfd\x00",
            5: b"\x01",
            1: b"\x01",
        }
        assert responder.mem[1][116:120] == b"\x01\x02\x03\x04"
        await bus.reboot(4)
        assert [pkt.instruction for pkt in responder.received][-1] == Instruction.REBOOT
        assert bus.stats.crc_errors == 0 and bus.stats.retries == 0


async def test_bad_crc_is_counted_and_retried_within_the_call(responder: Responder) -> None:
    responder.corrupt[3] = 1
    async with await open_dxl_bus(responder.path, 1_000_000, margin_s=SLACK_S) as bus:
        data = await bus.sync_read(132, 4, [1, 2, 3, 4, 5])
        assert data[3] == (2003).to_bytes(4, "little")
        assert bus.stats.crc_errors == 1 and bus.stats.retries == 1
        # the retry asked only the servo whose status was lost
        last = responder.received[-1]
        assert last.instruction == Instruction.SYNC_READ and list(last.params[4:]) == [3]
        # a servo whose every status is corrupted: DxlCrcError (a RobotError) naming it, after the retries
        responder.corrupt[2] = 10
        with pytest.raises(DxlCrcError, match=r"servo\(s\) \[2\]") as info:
            await bus.read(2, 132, 4)
        assert isinstance(info.value, RobotError) and info.value.servo_id == 2
        assert bus.stats.crc_errors_in_a_row == 1


async def test_a_status_held_up_past_the_timeout_is_still_the_answer(responder: Responder) -> None:
    # servo 3 answers once, and the second half of its status comes after the first attempt's timeout: the retry
    # must not throw away the half that came, nor the parser's place in it
    responder.once.add(3)
    responder.held[3] = 0.15
    async with await open_dxl_bus(responder.path, 1_000_000, margin_s=0.1, retries=2) as bus:
        assert await bus.read(3, 132, 4) == (2003).to_bytes(4, "little")
        assert bus.stats.retries >= 1 and bus.stats.crc_errors == 0
        assert 3 in responder.silent  # the retry got no second answer: the held one was used


async def test_a_silent_servo_times_out_naming_it_and_the_loop_keeps_running(responder: Responder) -> None:
    responder.silent.add(4)
    ticks = 0

    async def ticker() -> None:
        nonlocal ticks
        while True:
            await asyncio.sleep(0.001)
            ticks += 1

    async with await open_dxl_bus(responder.path, 1_000_000, margin_s=0.1, retries=1) as bus:
        async with asyncio.TaskGroup() as tg:
            task = tg.create_task(ticker())
            t0 = time.perf_counter()
            with pytest.raises(DxlTimeoutError, match=r"servo\(s\) \[4\] did not answer.*baud.*power.*IDs"):
                await bus.sync_read(132, 4, [1, 4, 5])
            elapsed = time.perf_counter() - t0
            task.cancel()
        # two attempts of about the margin each: bounded by the timeout, and the loop ran throughout
        assert 0.15 < elapsed < 1.5, elapsed
        assert ticks >= 10, f"the loop ticked {ticks} times in {elapsed:.3f} s: the bus blocked it"
        assert bus.stats.timeouts == 2
        # the bus goes on with the servos that answer
        assert await bus.ping(5) == (1020, 46)
        with pytest.raises(DxlTimeoutError, match=r"fast sync read of servos \[1, 4, 5\].*silent"):
            await bus.fast_sync_read(132, 4, [1, 4, 5])


async def test_a_status_error_is_raised_with_its_meaning(responder: Responder) -> None:
    responder.errors[2] = 0x07
    responder.errors[5] = 0x80
    async with await open_dxl_bus(responder.path, 1_000_000, margin_s=SLACK_S) as bus:
        with pytest.raises(DxlStatusError, match=r"servo 2 .*0x07 \(access error\)") as info:
            await bus.write(2, 132, b"\x00\x00\x00\x00")
        assert info.value.error == 0x07
        # the alert bit alone is a hardware error for the caller to read, not a failed transaction
        await bus.read(5, 132, 4)
        assert bus.alerts[5] is True


async def test_port_errors_name_the_port() -> None:
    with pytest.raises(DxlPortError, match="/dev/ttyNOPE0: no such device"):
        await open_dxl_bus("/dev/ttyNOPE0")
    with pytest.raises(DxlPortError, match="/dev/null is not a tty"):
        await open_dxl_bus("/dev/null")
    with pytest.raises(ConfigError, match="baud rate 1234567"):
        await open_dxl_bus("/dev/null", 1_234_567)
    bus = DxlBus("/dev/null")
    with pytest.raises(DxlPortError, match="closed"):
        await bus.ping(1)


@pytest.mark.slow
@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to run the check as another user")
def test_eacces_says_which_group_the_user_needs() -> None:
    # a real EACCES: a tty owned by root with mode 600, opened by user nobody in a forked child
    master, slave = pty.openpty()
    rd, wr = os.pipe()
    try:
        path = os.ttyname(slave)
        os.chmod(path, 0o600)
        pid = os.fork()
        if pid == 0:  # the child: drop to nobody, try to open, report the message
            message = b"opened"
            try:
                os.setgroups([])
                os.setgid(65534)
                os.setuid(65534)
                asyncio.run(open_dxl_bus(path))
            except DxlPortError as exc:
                message = str(exc).encode()
            finally:
                os.write(wr, message)
                os._exit(0)
        os.close(wr)
        wr = -1
        message = b""
        while chunk := os.read(rd, 4096):
            message += chunk
        _, status = os.waitpid(pid, 0)
    finally:
        for fd in (slave, master, rd, wr):
            if fd >= 0:
                os.close(fd)
    text = message.decode()
    assert os.waitstatus_to_exitcode(status) == 0
    assert f"cannot open the Dynamixel port {path}: permission denied" in text, text
    assert "dialout" in text


# ------------------------------------------------------------------------------------ the virtual bus


@pytest.mark.slow
async def test_against_the_virtual_bus() -> None:
    from uniros_async.hardware.dxl.control_table import XL430_W250, XM430_W350, model_by_number

    with running_vbus() as vb:
        path = vb.path
        async with await open_dxl_bus(path, 1_000_000, margin_s=0.2) as bus:
            models = {i: model_by_number((await bus.ping(i))[0]) for i in range(1, 8)}
            assert {t.name for t in models.values()} == {XL430_W250.name, XM430_W350.name}
            ids = [1, 2, 3, 4, 5, 6, 7]
            state = await bus.sync_read(126, 10, ids)
            assert all(len(v) == 10 for v in state.values())
            fast = await bus.fast_sync_read(132, 4, ids)
            assert set(fast) == set(ids)
            # a bad CRC from servo 4 is counted and retried within the call
            assert vb.send("crc 4 1").startswith("ok")
            before = bus.stats.crc_errors
            assert set(await bus.sync_read(126, 10, ids)) == set(ids)
            assert bus.stats.crc_errors == before + 1
            # a silent servo: DxlTimeoutError naming it
            assert vb.send("silent 6").startswith("ok")
            with pytest.raises(DxlTimeoutError, match=r"\[6\]"):
                await bus.read(6, 132, 4)


async def test_a_port_that_takes_no_bytes_is_a_port_error_and_the_loop_runs_on() -> None:
    # a pty whose other end never reads: its buffer fills, the write waits in the loop (add_writer), then fails
    master, slave = pty.openpty()
    tty.setraw(master)
    try:
        async with await open_dxl_bus(os.ttyname(slave), 1_000_000, margin_s=0.01) as bus:
            writes = [(i, 116, bytes(600)) for i in range(1, 100)]  # 60 kB a packet
            ticks = 0

            async def ticker() -> None:
                nonlocal ticks
                while True:
                    await asyncio.sleep(0.001)
                    ticks += 1

            async with asyncio.TaskGroup() as tg:
                task = tg.create_task(ticker())
                with pytest.raises(DxlPortError, match="stalled"):
                    for _ in range(10):  # the pty's buffers hold some; one of these fills them
                        await bus.bulk_write(writes)
                task.cancel()
            assert ticks >= 5
    finally:
        os.close(slave)
        os.close(master)
