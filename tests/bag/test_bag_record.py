"""``uniros bag record|info|play`` as real processes on a real domain: every message type recorded, listed, played
on the wall clock and on the sim clock and read back equal; a SIGKILLed recording reads up to its last chunk; a
topic that does not exist names the closest; a full disk (a 1 MiB tmpfs mounted in a mount namespace the test
creates with ``unshare --mount``) stops the recording with a clear error and leaves a readable file."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import sys
from collections import defaultdict
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from _bag_messages import assert_same, one_of_each

from uniros_async.bag import BagDamagedError, BagMessage, BagReader
from uniros_async.bus import messages as m
from uniros_async.bus import open_domain, open_node, reliable

pytestmark = pytest.mark.slow

PERIOD_S = 0.04


@contextlib.asynccontextmanager
async def publishing(
    uri: str, make: Callable[[int], list[tuple[str, Any]]] = one_of_each
) -> AsyncIterator[dict[str, list[Any]]]:
    """Publish ``make(i)`` every PERIOD_S from a node of the domain ``uri`` for the block; yields what was published,
    per topic, in order."""
    published: dict[str, list[Any]] = defaultdict(list)
    async with open_node("source", domain=uri) as node:
        pubs = {t: await node.create_publisher(type(msg), t, qos=reliable(100)) for t, msg in make(0)}

        async def run() -> None:
            i = 0
            while True:
                for topic, msg in make(i):
                    pubs[topic].publish(msg)
                    published[topic].append(msg)
                i += 1
                await asyncio.sleep(PERIOD_S)

        async with asyncio.TaskGroup() as tg:
            task = tg.create_task(run())
            try:
                yield published
            finally:
                task.cancel()


async def uniros(*args: str, timeout_s: float = 60.0) -> tuple[int, str, str]:
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "uniros_async.cli", *args, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE
    )
    try:
        async with asyncio.timeout(timeout_s):
            out, err = await proc.communicate()
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    assert proc.returncode is not None
    return proc.returncode, out.decode(), err.decode()


def assert_run_of(got: list[Any], published: list[Any]) -> None:
    """``got`` is a contiguous run of ``published``: nothing lost, nothing reordered, every field equal."""
    assert got, "nothing recorded"
    first = next(i for i, p in enumerate(published) if _same(p, got[0]))
    for k, msg in enumerate(got):
        assert_same(msg, published[first + k])


def _same(a: Any, b: Any) -> bool:
    try:
        assert_same(a, b)
    except AssertionError:
        return False
    return True


def by_topic(msgs: list[BagMessage]) -> dict[str, list[Any]]:
    out: dict[str, list[Any]] = defaultdict(list)
    for bm in msgs:
        out[bm.topic].append(bm.message)
    return out


class Played(defaultdict[str, list[Any]]):
    """Messages per topic, in arrival order, with an event set on each arrival."""

    def __init__(self) -> None:
        super().__init__(list)
        self.arrived = asyncio.Event()

    async def wait_for(self, expected: dict[str, list[Any]], timeout_s: float = 20.0) -> None:
        """Wait until every topic holds as many messages as ``expected``: the player's process can exit while its last
        messages are still on their way to this process's subscriptions. On a timeout it returns, and the caller's
        count assertions name the topic that fell short."""
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout_s):
                while any(len(self[t]) < len(msgs) for t, msgs in expected.items()):
                    self.arrived.clear()
                    await self.arrived.wait()


async def collect(uri: str, topics: dict[str, type], into: Played) -> Any:
    """A node of ``uri`` that appends every message of ``topics`` to ``into`` (an async context manager)."""

    def appender(topic: str) -> Callable[[Any], None]:
        def on(msg: Any) -> None:
            into[topic].append(msg)
            into.arrived.set()

        return on

    @contextlib.asynccontextmanager
    async def cm() -> AsyncIterator[None]:
        async with open_node("collector", domain=uri) as node:
            for topic, cls in topics.items():
                await node.create_subscription(cls, topic, appender(topic), qos=reliable(10_000))
            yield

    return cm()


async def test_record_info_and_play_on_both_clocks_round_trip_every_type(tmp_path: Path) -> None:
    bag = tmp_path / "a.mcap"
    async with open_domain() as domain, publishing(domain.uri) as published:
        rc, out, err = await uniros("bag", "record", "-o", str(bag), "--domain", domain.uri, "--duration", "2")
    assert rc == 0, err
    assert "# recording 12 topic(s)" in out and "dropped 0" in out
    recorded = list(BagReader(bag).messages())
    got = by_topic(recorded)
    assert set(got) == set(published)
    for topic in published:
        assert len(got[topic]) >= 20, topic  # 2 s at 25 Hz, less the start
        assert_run_of(got[topic], published[topic])

    rc, out, err = await uniros("bag", "info", str(bag))
    assert rc == 0, err
    assert f"messages:    {len(recorded)}" in out and "complete:    yes" in out
    assert "/rx200/joint_states" in out and "sensor_msgs/msg/JointState" in out and "zstd" in out

    types = {t: type(msgs[0]) for t, msgs in got.items()}
    span_s = (recorded[-1].log_time_ns - recorded[0].log_time_ns) / 1e9
    # on the wall clock: everything, in order, spread over the bag's span
    async with open_domain() as domain2:
        played = Played()
        async with await collect(domain2.uri, types, played):
            t0 = asyncio.get_running_loop().time()
            rc, out, err = await uniros("bag", "play", str(bag), "--domain", domain2.uri, "--wait-subscribers", "1")
            took_s = asyncio.get_running_loop().time() - t0
            assert rc == 0, err
            await played.wait_for(got)
    assert took_s >= span_s * 0.9
    for topic, msgs in got.items():
        assert len(played[topic]) == len(msgs), topic
        for a, b in zip(played[topic], msgs, strict=True):
            assert_same(a, b)

    # on the sim clock as fast as it goes: the player is /clock, and /clock carries the bag's log times; a recorder on
    # the sim clock records the played messages at those times
    types.pop("/clock")
    types["/clock"] = m.ClockTick
    again = tmp_path / "again.mcap"
    async with open_domain() as domain3:
        played = Played()
        async with await collect(domain3.uri, types, played):
            rec = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "uniros_async.cli", "bag", "record", "-o", str(again), "--domain", domain3.uri,
                "--clock", "sim", stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
            )  # fmt: skip
            try:
                assert rec.stdout is not None
                async with asyncio.timeout(30):
                    assert (await rec.stdout.readline()).startswith(b"# recording 12 topic(s)")
                rc, out, err = await uniros(
                    "bag", "play", str(bag), "--domain", domain3.uri, "--clock", "sim", "--rate", "0",
                    "--wait-subscribers", "2",
                )  # fmt: skip
                assert rc == 0, err
                await played.wait_for({t: msgs for t, msgs in got.items() if t != "/clock"})
                await asyncio.sleep(0.5)  # the recorder, another subscriber of the same publisher, has them too
                rec.send_signal(signal.SIGINT)
                async with asyncio.timeout(30):
                    rec_out, rec_err = await rec.communicate()
            finally:
                if rec.returncode is None:
                    rec.kill()
                    await rec.wait()
        assert rc == 0, err
        assert rec.returncode == 0, rec_err
    for topic, msgs in got.items():
        if topic != "/clock":
            assert len(played[topic]) == len(msgs), topic
            for a, b in zip(played[topic], msgs, strict=True):
                assert_same(a, b)
    ticks = [t.sim_time_ns for t in played["/clock"]]
    assert ticks == [bm.log_time_ns for bm in recorded if bm.topic != "/clock"]
    recorded_again = list(BagReader(again).messages())
    again_by_topic = by_topic(recorded_again)
    for topic, msgs in got.items():
        if topic != "/clock":
            assert len(again_by_topic[topic]) == len(msgs), topic
            for a, b in zip(again_by_topic[topic], msgs, strict=True):
                assert_same(a, b)
    # log times on the bag's time, which /clock carried (not this run's wall clock)
    first, last = recorded[0].log_time_ns, recorded[-1].log_time_ns
    assert all(first <= bm.log_time_ns <= last for bm in recorded_again)


async def test_a_sigkilled_recording_reads_up_to_its_last_complete_chunk(tmp_path: Path) -> None:
    bag = tmp_path / "k.mcap"
    async with open_domain() as domain, publishing(domain.uri) as published:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "uniros_async.cli", "bag", "record", "-o", str(bag), "--domain", domain.uri,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        try:
            assert proc.stdout is not None
            async with asyncio.timeout(30):
                line = await proc.stdout.readline()
            assert line.startswith(b"# recording"), line
            await asyncio.sleep(2.6)  # the writer flushes a chunk at least every second
            os.kill(proc.pid, signal.SIGKILL)
        finally:
            with contextlib.suppress(ProcessLookupError):
                proc.kill()
            await proc.wait()
    reader = BagReader(bag)
    got: list[BagMessage] = []
    with pytest.raises(BagDamagedError) as exc:
        for bm in reader.messages():
            got.append(bm)
    assert f"damaged at byte {exc.value.offset}" in str(exc.value)
    per_topic = by_topic(got)
    assert len(per_topic) == 12 and min(len(v) for v in per_topic.values()) >= 20  # two flushed seconds at 25 Hz
    for topic, msgs in per_topic.items():
        assert_run_of(msgs, published[topic])
    rc, out, _ = await uniros("bag", "info", str(bag))
    assert rc == 1 and f"messages:    {len(got)}" in out and "damaged:" in out


async def test_a_topic_that_does_not_exist_names_the_closest(tmp_path: Path) -> None:
    async with open_domain() as domain, publishing(domain.uri):
        rc, out, err = await uniros("bag", "record", "/rx200/joint_state", "-o", str(tmp_path / "x.mcap"),
                                    "--domain", domain.uri)  # fmt: skip
    assert rc == 2
    assert "no topic '/rx200/joint_state'" in err and "closest: /rx200/joint_states" in err
    assert not (tmp_path / "x.mcap").exists()


def test_one_topic_given_as_a_string_is_that_topic(tmp_path: Path) -> None:
    from uniros_async.bag.player import PlayConfig
    from uniros_async.bag.recorder import RecordConfig

    assert RecordConfig(path=tmp_path / "x.mcap", topics="/rx200/joint_states").topics == ("/rx200/joint_states",)
    assert PlayConfig(path=tmp_path / "x.mcap", topics="/clock").topics == ("/clock",)


def big_images(i: int) -> list[tuple[str, Any]]:
    rng = np.random.default_rng(i)  # noise: compresses to nothing, so a 1 MiB disk fills in a few frames
    return [("/camera/image", m.Image(header=m.Header(stamp_ns=i), data=rng.integers(0, 255, (80, 80, 3), np.uint8)))]


async def test_a_full_disk_stops_recording_with_a_clear_error_and_the_file_reads(tmp_path: Path) -> None:
    disk, kept = tmp_path / "disk", tmp_path / "kept.mcap"
    disk.mkdir()
    script = (
        f"mount -t tmpfs -o size=1m tmpfs {disk} || exit 99; "
        f"{sys.executable} -m uniros_async.cli bag record -o {disk}/b.mcap --compression lz4 --domain $DOMAIN; "
        f"rc=$?; cp {disk}/b.mcap {kept}; exit $rc"
    )
    async with open_domain() as domain, publishing(domain.uri, big_images) as published:
        proc = await asyncio.create_subprocess_exec(
            "unshare", "--mount", "--", "sh", "-c", script,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, env={**os.environ, "DOMAIN": domain.uri},
        )  # fmt: skip
        try:
            async with asyncio.timeout(60):
                out, err = await proc.communicate()
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
    assert proc.returncode == 2, (proc.returncode, out, err)
    assert b"No space left on device" in err and b"the file reads up to its last complete chunk" in err
    reader = BagReader(kept)
    got = list(reader.messages(strict=False))
    assert reader.damage is not None and len(got) >= 5
    assert_run_of([bm.message for bm in got], published["/camera/image"])


async def test_play_loops_on_the_sim_clock_with_time_going_on(tmp_path: Path) -> None:
    from uniros_async.bag import BagWriter, PlayConfig, play

    bag = tmp_path / "l.mcap"
    with BagWriter(bag) as w:
        for i in range(5):
            w.put("/text", m.Text(data=f"t{i}"), 1_000 + 1_000 * i)
    async with open_domain() as domain:
        got = Played()
        async with await collect(domain.uri, {"/text": m.Text, "/clock": m.ClockTick}, got):
            task = asyncio.create_task(
                play(PlayConfig(path=bag, domain=domain.uri, clock="sim", rate=0, loop=True, wait_subscribers=1))
            )
            try:
                for _ in range(3000):  # 30 s at most
                    if len(got["/text"]) >= 12:
                        break
                    await asyncio.sleep(0.01)
            finally:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
    texts = [t.data for t in got["/text"]][:12]
    assert texts == [f"t{i % 5}" for i in range(12)]
    ticks = [t.sim_time_ns for t in got["/clock"]][:12]
    assert ticks[:5] == [1_000, 2_000, 3_000, 4_000, 5_000]
    assert ticks[5:10] == [t + 4_001 for t in ticks[:5]]  # the next round goes on from the last one's end
    assert all(b > a for a, b in zip(ticks, ticks[1:], strict=False))
