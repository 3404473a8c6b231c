"""``uniros bench dxl``: one servo-bus tick of our asyncio client beside dynamixel-sdk, on the same virtual bus.

A tick is what the arm driver does every env-loop tick: a sync read of the contiguous present block (current or
load, velocity, position: addresses 126..135) and a sync write of goal positions (116), here the positions just
read, so the arm holds still. The bus is ``uniros robot vbus rx200``, a process answering on a pty with the wire
timing of its baud rate and each servo's return delay. Rows, for the arm's 5 primary servos and for all 7:

- ``uniros``: ``DxlBus`` (the tty's fd in the event loop);
- ``dynamixel-sdk``: its GroupSyncRead.txRxPacket and GroupSyncWrite.txPacket (PyPI, unmodified).

The two take turns in blocks, so drift of the host's speed falls on both. Each row reports the p50 and p99 of
the cycle, the process CPU per cycle, and the wire floor: the bytes of the instruction and status packets at
10 bits a byte and the baud rate, plus each status's return delay. Then the event loop while our client runs the
same ticks: the lag of a 1 ms ticker beside it, and the thread CPU of each loop iteration (beside a ticker that
only yields); and the codec alone: building both instruction packets and parsing the status packets of one tick
from memory, ours and dynamixel-sdk's (its PacketHandler on an in-memory port), CPU per tick.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import gc
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from uniros_async.bench.common import report
from uniros_async.stats import summary

__all__ = ["DxlBenchConfig", "main"]

PRESENT_ADDRESS = 126
PRESENT_LENGTH = 10
GOAL_ADDRESS = 116
POSITION_OFFSET = 6  # present position's offset in the present block
_HIST_BINS = 1_000_000  # 1 us bins up to 1 s
_AWAKE = {"pm_qos": "kept polling (PM QoS 0 us)", "pollers": "kept awake by idle-class pollers"}
MARGIN_S = 0.05
"""Our client's timeout margin here: the virtual bus is a process on a shared host, and a late answer should
count as a slow cycle, not fail the run (dynamixel-sdk waits 34 ms past the wire time)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class DxlBenchConfig:
    cycles: int = 2000
    """Ticks per row, in blocks of ``block``."""
    block: int = 200
    servo_map: str = "rx200"
    baud: int | None = None
    """The vbus's baud rate (default: the map's)."""
    json_path: str | None = None
    real_time: bool = True
    """Run the virtual bus's thread and the bench's (both clients') in the real-time class the env loops and the
    servo sims use (``priority.raise_loop_priority``), so other load on the host delays neither."""
    keep_cores_awake: bool = True
    """Keep idle cores from halting (``priority.cores_kept_from_halting``): on a virtual machine, waking a halted
    core for the bus's bytes costs the hypervisor's scheduling delay. dynamixel-sdk's polling keeps its own core
    awake; this gives our client, which sleeps until the bytes come, the same cores. By the kernel's PM QoS limit
    where it can be set (root), else by the latency benchmark's idle-class pollers, which now and then delay the
    kernel worker that carries a pty's bytes (``priority.cores_kept_polling``), as the cycle's p99 shows."""


@contextlib.contextmanager
def _vbus(servo_map: str, baud: int | None, rt: bool = False, extra: Sequence[str] = ()) -> Iterator[str]:
    argv = [sys.executable, "-m", "uniros_async.cli", "robot", "vbus", servo_map, *extra]
    if baud:
        argv += ["--baud", str(baud)]
    proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, text=True)
    drain: threading.Thread | None = None
    try:
        assert proc.stdout is not None
        path = proc.stdout.readline().strip()
        if not path.startswith("/dev/"):
            raise RuntimeError(f"uniros robot vbus printed {path!r} first: expected the pty's path")
        if rt:
            from uniros_async.priority import raise_loop_priority

            raise_loop_priority(thread_id=proc.pid)  # its serving thread is its main thread
        # its event lines (watchdog stops, ...) are read and dropped: a full pipe would stall the servos' answers
        drain = threading.Thread(target=proc.stdout.read, name="vbus stdout", daemon=True)
        drain.start()
        yield path
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if drain is not None:
            drain.join(timeout=5)  # it reads to the end of the exited process's output
        if proc.stdout is not None:
            proc.stdout.close()


def _floor_us(n: int, baud: int, return_delay_s: float) -> float:
    from uniros_async.hardware.dxl.bus import wire_time_s
    from uniros_async.hardware.dxl.protocol import (
        BROADCAST_ID,
        Instruction,
        status_bytes,
        sync_read_params,
        sync_write_params,
    )
    from uniros_async.hardware.dxl.protocol import instruction_bytes as ib

    ids = list(range(1, n + 1))
    goals = {i: (2048).to_bytes(4, "little") for i in ids}
    tx = ib(BROADCAST_ID, Instruction.SYNC_READ, sync_read_params(PRESENT_ADDRESS, PRESENT_LENGTH, ids))
    tx += ib(BROADCAST_ID, Instruction.SYNC_WRITE, sync_write_params(GOAL_ADDRESS, 4, goals))
    rx = n * status_bytes(PRESENT_LENGTH)
    return (wire_time_s(tx + rx, baud) + n * return_delay_s) * 1e6


@contextlib.contextmanager
def _real_time(enabled: bool) -> Iterator[str]:
    """This thread in the env loops' real-time class for the block (then back); yields the class it got."""
    if not enabled or not hasattr(os, "sched_getscheduler"):
        yield "ordinary"
        return
    from uniros_async.priority import raise_loop_priority

    policy, param, nice = os.sched_getscheduler(0), os.sched_getparam(0), os.getpriority(os.PRIO_PROCESS, 0)
    got = raise_loop_priority()
    try:
        yield {"rt": "SCHED_RR", "nice": "nice"}.get(got or "", "ordinary")
    finally:
        with contextlib.suppress(PermissionError):
            os.sched_setscheduler(0, policy, param)
            os.setpriority(os.PRIO_PROCESS, 0, nice)


# ------------------------------------------------------------------------------------------ the clients


class _Ours:
    def __init__(self, path: str, baud: int, return_delay_s: float) -> None:
        self.loop = asyncio.new_event_loop()
        from uniros_async.hardware.dxl.bus import open_dxl_bus

        self.failures = 0
        self.bus = self.loop.run_until_complete(
            open_dxl_bus(path, baud, return_delay_s=return_delay_s, margin_s=MARGIN_S)
        )

    async def _block(self, ids: Sequence[int], n: int, out: list[float]) -> None:
        from uniros_async.errors import DxlError

        bus = self.bus
        for _ in range(n):
            t0 = time.perf_counter()
            try:
                state = await bus.sync_read(PRESENT_ADDRESS, PRESENT_LENGTH, ids)
                await bus.sync_write(GOAL_ADDRESS, 4, {i: state[i][POSITION_OFFSET:] for i in ids})
            except DxlError:
                self.failures += 1
            out.append(time.perf_counter() - t0)

    def block(self, ids: Sequence[int], n: int, out: list[float]) -> None:
        self.loop.run_until_complete(self._block(ids, n, out))

    def lag(self, ids: Sequence[int], n: int, period_s: float) -> tuple[list[float], list[int], list[int]]:
        """Run ``n`` ticks beside a ticker that sleeps ``period_s`` (0: it only yields to the loop).

        Returns the cycles (s) and two histograms in 1 us bins (the last bin holds everything longer): the
        ticker's lag (how late it woke, the host's scheduling included) and the thread CPU time from one of its
        runs to the next (the loop's work in between, the bus's; a process the host deschedules uses no CPU
        meanwhile). With ``period_s`` 0 the ticker runs once per loop iteration, so the second is the CPU of each
        iteration: how long the bus held the loop. Histograms, not lists: appending to a list of millions of
        samples reallocates it, and that copy would be measured as the loop's.
        """
        lags = [0] * _HIST_BINS
        busy = [0] * _HIST_BINS
        cycles: list[float] = []
        top = _HIST_BINS - 1

        async def run() -> None:
            done = asyncio.Event()

            async def ticker() -> None:
                loop = asyncio.get_running_loop()
                while not done.is_set():
                    due = loop.time() + period_s
                    c0 = time.thread_time()
                    await asyncio.sleep(period_s)
                    busy[min(int((time.thread_time() - c0) * 1e6), top)] += 1
                    lags[min(max(int((loop.time() - due) * 1e6), 0), top)] += 1

            async with asyncio.TaskGroup() as tg:
                tg.create_task(ticker())
                try:
                    await self._block(ids, n, cycles)
                finally:
                    done.set()

        self.loop.run_until_complete(run())
        return cycles, lags, busy

    def close(self) -> None:
        self.loop.run_until_complete(self.bus.aclose())
        self.loop.close()


class _Sdk:
    def __init__(self, path: str, baud: int) -> None:
        import dynamixel_sdk as sdk

        self.sdk = sdk
        self.port = sdk.PortHandler(path)
        if not self.port.openPort() or not self.port.setBaudRate(baud):
            raise RuntimeError(f"dynamixel-sdk could not open {path} at {baud} baud")
        self.ph = sdk.PacketHandler(2.0)
        self.groups: dict[tuple[int, ...], tuple[Any, Any]] = {}
        self.failures = 0

    def block(self, ids: Sequence[int], n: int, out: list[float]) -> None:
        sdk = self.sdk
        key = tuple(ids)
        if key not in self.groups:
            gsr = sdk.GroupSyncRead(self.port, self.ph, PRESENT_ADDRESS, PRESENT_LENGTH)
            for i in ids:
                gsr.addParam(i)
            self.groups[key] = (gsr, sdk.GroupSyncWrite(self.port, self.ph, GOAL_ADDRESS, 4))
        gsr, gsw = self.groups[key]
        for _ in range(n):
            t0 = time.perf_counter()
            if gsr.txRxPacket() != sdk.COMM_SUCCESS:
                self.failures += 1
                out.append(time.perf_counter() - t0)
                continue
            gsw.clearParam()
            for i in ids:
                pos = gsr.getData(i, PRESENT_ADDRESS + POSITION_OFFSET, 4)
                gsw.addParam(i, list(pos.to_bytes(4, "little")))
            if gsw.txPacket() != sdk.COMM_SUCCESS:
                self.failures += 1
            out.append(time.perf_counter() - t0)

    def close(self) -> None:
        self.port.closePort()


# ------------------------------------------------------------------------------------------ the codec


class _MemoryPort:
    """dynamixel-sdk's PortHandler surface on bytes in memory: writes are dropped, reads come from ``rx``."""

    def __init__(self) -> None:
        self.is_using = False
        self.rx = b""
        self._pos = 0

    def load(self, rx: bytes) -> None:
        self.rx, self._pos = rx, 0

    def clearPort(self) -> None:  # noqa: N802  (dynamixel-sdk's names)
        pass

    def writePort(self, packet: list[int]) -> int:  # noqa: N802
        return len(packet)

    def readPort(self, length: int) -> bytes:  # noqa: N802
        chunk = self.rx[self._pos : self._pos + length]
        self._pos += len(chunk)
        return chunk

    def setPacketTimeout(self, packet_length: int) -> None:  # noqa: N802
        pass

    def isPacketTimeout(self) -> bool:  # noqa: N802
        return True


def _codec_cpu_us(n: int, ticks: int) -> dict[str, float]:
    """CPU per tick of building the sync read and sync write packets and parsing ``n`` status packets."""
    import dynamixel_sdk as sdk

    from uniros_async.hardware.dxl import protocol as p

    ids = list(range(1, n + 1))
    statuses = b"".join(p.encode_status(i, 0, bytes(6) + (2048 + i).to_bytes(4, "little")) for i in ids)

    parser = p.PacketParser()
    t0 = time.process_time()
    for _ in range(ticks):
        p.encode_instruction(
            p.BROADCAST_ID, p.Instruction.SYNC_READ, p.sync_read_params(PRESENT_ADDRESS, PRESENT_LENGTH, ids)
        )
        got = {pkt.servo_id: pkt.params for pkt in parser.feed(statuses)}
        goals = {i: got[i][POSITION_OFFSET:] for i in ids}
        p.encode_instruction(p.BROADCAST_ID, p.Instruction.SYNC_WRITE, p.sync_write_params(GOAL_ADDRESS, 4, goals))
    ours = (time.process_time() - t0) / ticks * 1e6

    port = _MemoryPort()
    ph = sdk.PacketHandler(2.0)
    gsr = sdk.GroupSyncRead(port, ph, PRESENT_ADDRESS, PRESENT_LENGTH)
    for i in ids:
        gsr.addParam(i)
    gsw = sdk.GroupSyncWrite(port, ph, GOAL_ADDRESS, 4)
    t0 = time.process_time()
    for _ in range(ticks):
        port.load(statuses)
        if gsr.txRxPacket() != sdk.COMM_SUCCESS:
            raise RuntimeError("dynamixel-sdk did not parse the canned status packets")
        gsw.clearParam()
        for i in ids:
            gsw.addParam(i, list(gsr.getData(i, PRESENT_ADDRESS + POSITION_OFFSET, 4).to_bytes(4, "little")))
        gsw.txPacket()
    theirs = (time.process_time() - t0) / ticks * 1e6
    return {"uniros": ours, "dynamixel-sdk": theirs}


# ------------------------------------------------------------------------------------------ the run


def _hist_summary(hist: list[int]) -> dict[str, float]:
    """p50, p99 and max (us) and the count of a histogram of 1 us bins."""
    n = sum(hist)
    out = {"p50": float("nan"), "p99": float("nan"), "max": float("nan"), "count": n}
    if not n:
        return out
    seen = 0
    for us, count in enumerate(hist):
        if not count:
            continue
        if seen < 0.5 * n <= seen + count:
            out["p50"] = float(us)
        if seen < 0.99 * n <= seen + count:
            out["p99"] = float(us)
        seen += count
        out["max"] = float(us)
    return out


def _timed(client: _Ours | _Sdk, ids: Sequence[int], n: int, out: list[float], cpu: list[float]) -> None:
    c0 = time.process_time()
    n0 = len(out)
    client.block(ids, n, out)
    cpu.append((time.process_time() - c0) / max(1, len(out) - n0) * 1e6)


def main(config: DxlBenchConfig, *, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Run the benchmark; returns its JSON records (rows, the loop lag, the codec alone)."""
    from uniros_async.hardware.dxl.control_table import RETURN_DELAY_UNIT_S
    from uniros_async.hardware.dxl.servo_map import servo_map
    from uniros_async.priority import cores_kept_from_halting, freeze_heap

    servos = servo_map(config.servo_map)
    baud = config.baud or servos.baud
    return_delay_s = max(s.return_delay_time for s in servos.servos) * RETURN_DELAY_UNIT_S
    arm_ids = [servos.primary(j).id for j in servos.arm.joints]
    sets = {len(arm_ids): arm_ids, len(servos.ids): list(servos.ids)}
    records: list[dict[str, Any]] = []
    awake: contextlib.AbstractContextManager[str] = (
        cores_kept_from_halting() if config.keep_cores_awake else contextlib.nullcontext("no")
    )
    with (
        awake as kept_awake,
        _vbus(config.servo_map, config.baud, config.real_time) as path,
        _real_time(config.real_time) as klass,
    ):
        ours, theirs = _Ours(path, baud, return_delay_s), _Sdk(path, baud)
        freeze_heap()  # as loop processes do once started: full collections walk only what the ticks make
        try:
            for n, ids in sets.items():
                # warm-up: the vbus's sim, both clients' first packets
                ours.block(ids, 20, [])
                theirs.block(ids, 20, [])
                clients: dict[str, _Ours | _Sdk] = {"uniros": ours, "dynamixel-sdk": theirs}
                failed = {impl: c.failures for impl, c in clients.items()}
                cycles: dict[str, list[float]] = {"uniros": [], "dynamixel-sdk": []}
                cpu: dict[str, list[float]] = {"uniros": [], "dynamixel-sdk": []}
                per_block = min(config.block, config.cycles)
                for _ in range(max(1, config.cycles // per_block)):
                    for impl, client in clients.items():
                        _timed(client, ids, per_block, cycles[impl], cpu[impl])
                floor = _floor_us(n, baud, return_delay_s)
                for impl in ("uniros", "dynamixel-sdk"):
                    s = summary([c * 1e6 for c in cycles[impl]])
                    records.append(
                        {
                            "impl": impl,
                            "servos": n,
                            "p50_us": round(s["p50"], 1),
                            "p99_us": round(s["p99"], 1),
                            "cpu_us": round(summary(cpu[impl])["p50"], 1),
                            "floor_us": round(floor, 1),
                            "cycles": s["count"],
                            "failed_cycles": clients[impl].failures - failed[impl],
                            "baud": baud,
                            "scheduling": klass,
                            "cores_kept_awake": kept_awake,
                        }
                    )
            if ours.bus.stats.retries:
                log(f"note: our client retried {ours.bus.stats.retries} times ({ours.bus.stats})")
            n, ids = max(sets.items())
            cyc, lags, _ = ours.lag(ids, config.cycles, 0.001)
            _, _, held = ours.lag(ids, max(1, config.cycles // 4), 0.0)
            lag, hold = _hist_summary(lags), _hist_summary(held)
            records.append(
                {
                    "case": "event loop lag while the bus runs",
                    "servos": n,
                    "lag_p50_us": round(lag["p50"], 1),
                    "lag_p99_us": round(lag["p99"], 1),
                    "lag_max_us": round(lag["max"], 1),
                    "ticks": lag["count"],
                    "hold_p99_us": round(hold["p99"], 1),
                    "hold_max_us": round(hold["max"], 1),
                    "iterations": hold["count"],
                    "cycle_p50_us": round(summary([c * 1e6 for c in cyc])["p50"], 1),
                }
            )
        finally:
            ours.close()
            theirs.close()
            gc.unfreeze()
    for n in sets:
        codec = _codec_cpu_us(n, 2000)
        for impl, us in codec.items():
            records.append({"case": "codec alone", "impl": impl, "servos": n, "cpu_us": round(us, 1)})

    rows = [r for r in records if "p50_us" in r]
    lines = [
        f"uniros bench dxl: sync read of {PRESENT_LENGTH} bytes + sync write of goal positions per tick, "
        f"{config.servo_map} vbus at {baud} baud, host {os.uname().nodename} ({os.cpu_count()} cores), "
        f"{time.strftime('%Y-%m-%d %H:%M %Z')}, clients and vbus {rows[0]['scheduling'] if rows else '?'}, "
        f"idle cores {_AWAKE.get(rows[0]['cores_kept_awake'] if rows else 'no', 'allowed to halt')}",
        f"{'impl':<14} {'servos':>6} {'p50 us':>9} {'p99 us':>9} {'cpu us':>8} {'floor us':>9} "
        f"{'p50/floor':>9} {'p99/floor':>9} {'failed':>6}",
    ]
    for r in records:
        if "p50_us" in r:
            lines.append(
                f"{r['impl']:<14} {r['servos']:>6} {r['p50_us']:>9.1f} {r['p99_us']:>9.1f} {r['cpu_us']:>8.1f} "
                f"{r['floor_us']:>9.1f} {r['p50_us'] / r['floor_us']:>9.2f} {r['p99_us'] / r['floor_us']:>9.2f} "
                f"{r['failed_cycles']:>6}"
            )
    for r in records:
        if r.get("case", "").startswith("event loop"):
            lines.append(
                f"event loop beside our client ({r['servos']} servos): a 1 ms ticker's lag p50 {r['lag_p50_us']} us, "
                f"p99 {r['lag_p99_us']} us, max {r['lag_max_us']} us ({r['ticks']} ticks); each loop iteration's "
                f"thread CPU (the bus holding the loop) p99 {r['hold_p99_us']} us, max {r['hold_max_us']} us "
                f"({r['iterations']} iterations)"
            )
    lines.append("codec alone, CPU us per tick (build both packets, parse the statuses):")
    for r in records:
        if r.get("case") == "codec alone":
            lines.append(f"  {r['impl']:<14} {r['servos']:>6} servos {r['cpu_us']:>8.1f}")
    report("\n".join(lines), records, config.json_path, log)
    return records
