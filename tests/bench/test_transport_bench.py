"""``uniros bench transport``: a few samples per case through real processes, the JSON schema, the table, bad
configs. Sizes of figures are the benchmark's job (docs/performance.md), not the test's."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from uniros_async.bench import transport
from uniros_async.errors import ConfigError

KEYS = {"transport", "payload", "rtt_p50_us", "rtt_p90_us", "rtt_p99_us", "throughput_msg_s"}


def test_every_transport_and_payload_gets_a_record_and_a_row(tmp_path: Path) -> None:
    out = tmp_path / "t.json"
    lines: list[str] = []
    kinds = ("memory", "shm", "shm-loan", "tcp", "mp-pipe")
    cfg = transport.TransportBenchConfig(
        transports=kinds, rtt_samples=30, throughput_frames=30, json_path=str(out), progress=False
    )
    records = transport.main(cfg, log=lines.append)
    assert json.loads(out.read_text()) == records
    assert {(r["transport"], r["payload"]) for r in records} == {(k, p) for k in kinds for p in transport.PAYLOADS}
    for r in records:
        assert set(r) == KEYS
        assert 0 < r["rtt_p50_us"] <= r["rtt_p90_us"] <= r["rtt_p99_us"] and r["throughput_msg_s"] > 0
    table = "\n".join(lines)
    for name in ("shm p50 vs fastest peer (mp-pipe)", "shm-loan p50 vs fastest peer (mp-pipe)"):
        assert table.count(name) == len(transport.PAYLOADS)
    assert "shm-loan: both ends write their frames in place" in table  # the row's method, under the table


def test_unknown_transport_or_payload_is_named() -> None:
    with pytest.raises(ConfigError, match="unknown transport.*'udp'.*shm-loan"):
        transport.TransportBenchConfig(transports=("udp",))
    with pytest.raises(ConfigError, match="unknown payload.*'huge'"):
        transport.TransportBenchConfig(payloads=("huge",))


def test_the_loan_echo_answers_in_place_with_the_stamp_only() -> None:
    """The shm-loan row's echo (iceoryx2's method): a loaned frame of the request's size that carries the request's
    8-byte stamp and none of its payload, so neither side copies the payload. A real spawned echo over real shm."""
    import asyncio
    import multiprocessing as mp
    import os

    from uniros_async.bench import _peers
    from uniros_async.transports.base import TransportOptions, connect

    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_peers.serve_uniros, args=("shm://", child, True), daemon=True)
    proc.start()
    try:
        assert parent.poll(30), "echo did not start"
        uri = parent.recv()
        payload = os.urandom(640 * 480 * 3)

        async def main() -> tuple[int, bytes, bytes]:
            t = await connect(uri, TransportOptions())
            try:
                async with asyncio.timeout(10):
                    async with t.loan(len(payload)) as buf:
                        buf[:] = payload
                    reply = await t.receive()
                    out = reply.nbytes, bytes(reply[:8]), bytes(reply[8:])
                    await t.send(_peers.STOP)
                    return out
            finally:
                await t.aclose()

        n, stamp, rest = asyncio.run(main())
        assert n == len(payload) and stamp == payload[:8]
        assert rest != payload[8:]  # the payload itself was not copied back
    finally:
        proc.join(10)
        if proc.is_alive():
            proc.kill()
        parent.close()


@pytest.mark.slow
def test_frame_payloads_beside_the_memcpy_floor_and_iceoryx2() -> None:
    """image and hd frames through shm, shm-loan and iceoryx2's Python binding (a real echo in another process,
    which the client checks answers each frame), with the two floors (one memcpy of the frame; two copies between
    processes) timed in the same run."""
    import os

    kinds = ("memcpy", "copy-pingpong", "shm", "shm-loan", "iceoryx2", "iceoryx2-loan")
    lines: list[str] = []
    cfg = transport.TransportBenchConfig(
        transports=kinds, payloads=("image", "hd"), rtt_samples=20, throughput_frames=20, progress=False
    )

    def iox2_segments() -> set[str]:
        # iceoryx2's machine-wide management file (``*.global_mgmt``) is made by its first node on the machine
        # and kept for every later one: on a fresh machine this run makes it, and it is not a segment left over
        return {n for n in os.listdir("/dev/shm") if n.startswith("iox2_") and not n.endswith(".global_mgmt")}

    before = iox2_segments()
    records = transport.main(cfg, log=lines.append)
    assert {(r["transport"], r["payload"]) for r in records} == {(k, p) for k in kinds for p in ("image", "hd")}
    assert all(r["rtt_p50_us"] > 0 and r["throughput_msg_s"] > 0 for r in records)
    table = "\n".join(lines)
    assert table.count("shm p50 vs one memcpy of the payload") == 2
    assert table.count("shm p50 vs two copies between processes and nothing else") == 2
    assert table.count("shm-loan p50 vs fastest peer") == 2
    assert iox2_segments() == before  # no segment left by the run


def test_each_rows_echo_runs_on_another_core_than_its_client() -> None:
    """The client on one core, the echo process it starts on another (where this process may use two)."""
    import os

    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("one core: the client and its echo share it, and the bench leaves both unpinned")
    before = os.sched_getaffinity(0)
    client_cpus, echo_cpus = transport._cores()
    assert client_cpus and echo_cpus and not client_cpus & echo_cpus
    with transport._on_cores(client_cpus):
        assert os.sched_getaffinity(0) == client_cpus
        with transport._on_cores(echo_cpus):
            client = transport._make_client("shm")
        try:
            assert os.sched_getaffinity(0) == client_cpus
            assert os.sched_getaffinity(client._proc.pid) == echo_cpus  # type: ignore[attr-defined]
            assert len(client.rtt(b"x" * 277, 20)) == 20
        finally:
            client.close()
    assert os.sched_getaffinity(0) == before


def test_the_copy_pingpong_floor_copies_each_frame_there_and_back() -> None:
    """The two-copy floor: a real echo process copies each frame back (the client reads the reply's bytes), is on
    another core than its client where there are two, and is gone when the client closes."""
    import os

    from uniros_async.bench._copy_floor import CopyPingPong

    client_cpus, echo_cpus = transport._cores()
    with transport._on_cores(client_cpus):
        with transport._on_cores(echo_cpus):
            floor = transport._make_client("copy-pingpong")
        assert isinstance(floor, CopyPingPong)
        pid = floor.echo_pid()
        assert pid is not None
        try:
            if echo_cpus is not None:
                assert os.sched_getaffinity(pid) == echo_cpus
            for size in (277, 640 * 480 * 3):
                payload = os.urandom(size)
                assert len(floor.rtt(payload, 5)) == 5
                assert floor.echoed(size) == payload
            with pytest.raises(ValueError, match="exceeds the row's buffers"):
                floor.rtt(b"x" * (max(transport.PAYLOADS.values()) + 1), 1)
        finally:
            floor.close()
    assert not os.path.exists(f"/proc/{pid}") or open(f"/proc/{pid}/stat").read().split()[2] == "Z"


def test_the_copy_pingpong_echo_exits_when_its_client_is_gone() -> None:
    """An echo whose client stops asking (died without the stop word) exits after its idle time."""
    import time

    from uniros_async.bench._copy_floor import CopyPingPong

    floor = CopyPingPong(4096, idle_exit_s=0.5)
    try:
        floor.rtt(b"x" * 100, 3)
        proc = floor._proc
        proc.join(10)
        assert proc.exitcode == 0, "the echo did not exit on its own"
    finally:
        t0 = time.monotonic()
        floor.close()
        assert time.monotonic() - t0 < 5
