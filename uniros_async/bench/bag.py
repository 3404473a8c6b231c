"""``uniros bench bag``: record four real-time arms and a 30 Hz 640x480 camera while their env loops run.

The world is a process of its own: four domains, each with a servo sim process (rx200 and ned2, nominal and
emulated real, as in ``uniros bench cameras``), and in the first domain a camera node publishing 640x480 rgb8 frames
at 30 Hz. The frames are synthetic (a fixed textured picture shifted by the frame's sequence number, so every frame
differs and can be checked on read-back without keeping it); they are not renders, so their compression ratio is
not a rendered scene's. Four real-time envs (``make_vec``, a worker process each, wall clock, the scripted reach agent)
drive the arms over the domains' tcp, and a recorder process (a node per domain, one ``BagWriter``) records every
topic of every domain into one bag, each domain's topics under ``/armN``.

It prints, per env, the actuator cycle (the loop's goal: median within ``MEDIAN_GOAL_MS`` of the period, IQR below
``IQR_GOAL_MS``), and for the bag its size, the messages written and dropped, the CPU seconds of the writer thread
and of the whole recorder process, and whether the bag read back equals what the recorder received, message for
message (topic, stamp and a CRC of every array), and the camera frames equal what was published.
"""

from __future__ import annotations

import asyncio
import dataclasses
import multiprocessing
import multiprocessing.connection
import os
import resource
import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from uniros_async.bench.cameras import IQR_GOAL_MS, MEDIAN_GOAL_MS, meets_goal
from uniros_async.bench.common import report
from uniros_async.errors import ConfigError
from uniros_async.stats import loop_metrics, since, summary

__all__ = ["BagBenchConfig", "main"]

ARMS: tuple[tuple[str, str, bool], ...] = (
    ("uniros/Rx200Reach-v0", "rx200", False),
    ("uniros/Rx200Reach-v0", "rx200", True),
    ("uniros/Ned2Reach-v0", "ned2", False),
    ("uniros/Ned2Reach-v0", "ned2", True),
)
CAMERA_TOPIC = "/camera/color/image_raw"
NICE = 10
"""How much the recorder lowers its priority (``uniros bag record --nice``'s default)."""
_TIMEOUT_S = 60.0


@dataclasses.dataclass(frozen=True, kw_only=True)
class BagBenchConfig:
    """What ``uniros bench bag`` runs."""

    duration_s: float = 600.0
    out: str = "bench_bag.mcap"
    width: int = 640
    height: int = 480
    camera_hz: float = 30.0
    think_ms: float = 50.0
    seed: int = 0
    baseline_s: float = 60.0
    """First, this long without recording: the same loops' figures beside those while recording (0: none)."""
    keep: bool = False
    json_path: str | None = None

    def __post_init__(self) -> None:
        if self.duration_s <= 0 or self.camera_hz <= 0 or self.width < 8 or self.height < 8:
            raise ConfigError(
                f"bench bag: expected duration > 0, camera rate > 0 and a frame of 8x8 or more; got "
                f"{self.duration_s} s, {self.camera_hz} Hz, {self.width}x{self.height}"
            )


def frame(stamp_ns: int, base: np.ndarray) -> np.ndarray:
    """The synthetic camera's frame stamped ``stamp_ns``: ``base`` shifted right by the stamp's milliseconds."""
    return np.roll(base, (stamp_ns // 1_000_000) % base.shape[1], axis=1)


def base_picture(width: int, height: int) -> np.ndarray:
    """A textured picture: 16x16 blocks of random colours with a little noise, fixed by its size."""
    rng = np.random.default_rng(width * 10_000 + height)
    blocks = rng.integers(0, 255, ((height + 15) // 16, (width + 15) // 16, 3), dtype=np.uint8)
    pic = np.repeat(np.repeat(blocks, 16, axis=0), 16, axis=1)[:height, :width]
    noise = rng.integers(0, 8, pic.shape, dtype=np.uint8)
    return np.ascontiguousarray(pic + noise)


def digest(topic: str, msg: Any) -> tuple[str, int, int]:
    """(topic, stamp, CRC of every array) of a message: what is compared after reading back."""
    crc = 0
    for spec in getattr(msg, "__uniros_arrays__", ()):
        a = getattr(msg, spec.name)
        if a is not None:
            crc = zlib.crc32(np.ascontiguousarray(a).data, crc)
    h = getattr(msg, "header", None)
    return (topic, h.stamp_ns if h else 0, crc)


# ------------------------------------------------------------------------------------------------ the world


def _world_main(cfg: BagBenchConfig, conn: multiprocessing.connection.Connection) -> None:
    asyncio.run(_world(cfg, conn))


async def _world(cfg: BagBenchConfig, conn: multiprocessing.connection.Connection) -> None:
    import contextlib

    from uniros_async.bus import open_domain, open_node
    from uniros_async.bus.messages import Header, Image
    from uniros_async.sim.emulated import EmulationConfig
    from uniros_async.sim.serve import open_servo_sim_process

    async with contextlib.AsyncExitStack() as stack:
        uris = []
        for i, (_, arm, emulated) in enumerate(ARMS):
            domain = await stack.enter_async_context(open_domain())
            await stack.enter_async_context(
                open_servo_sim_process(
                    arm, domain=domain, emulation=EmulationConfig(seed=i) if emulated else None, start_timeout_s=60
                )
            )
            uris.append(domain.uri)
        node = await stack.enter_async_context(open_node("camera", domain=uris[0]))
        pub = await node.create_publisher(Image, CAMERA_TOPIC)
        base = base_picture(cfg.width, cfg.height)
        published = [0]

        def shoot() -> None:
            stamp = node.now_ns()
            pub.publish(Image(header=Header(stamp_ns=stamp, seq=published[0]), data=frame(stamp, base)))
            published[0] += 1

        timer = node.create_timer(1.0 / cfg.camera_hz, shoot)
        conn.send(uris)
        while not await asyncio.to_thread(conn.poll, 1.0):
            pass
        conn.recv()
        timer.cancel()
        conn.send(published[0])
        while not await asyncio.to_thread(conn.poll, 1.0):  # the domains stay until the envs have closed
            pass


# --------------------------------------------------------------------------------------------- the recorder


def _recorder_main(uris: list[str], path: str, conn: multiprocessing.connection.Connection) -> None:
    os.nice(NICE)  # as `uniros bag record` does
    asyncio.run(_recorder(uris, path, conn))


async def _recorder(uris: list[str], path: str, conn: multiprocessing.connection.Connection) -> None:
    import contextlib

    from uniros_async.bag.writer import BagWriter
    from uniros_async.bus import open_node, reliable
    from uniros_async.bus.messages import message_type

    writer = BagWriter(path)
    digests: list[tuple[str, int, int]] = []
    subs = []
    async with contextlib.AsyncExitStack() as stack:
        for i, uri in enumerate(uris):
            node = await stack.enter_async_context(open_node(f"recorder_{i}", domain=uri))
            for t in await node.list_topics():
                if t["topic"] in ("/clock",):
                    continue
                name = f"/arm{i}{t['topic']}"

                def on_msg(msg: Any, name: str = name, node: Any = node) -> None:
                    if writer.put(name, msg, node.now_ns()):
                        digests.append(digest(name, msg))

                sub = await node.create_subscription(message_type(t["type"]), t["topic"], on_msg, qos=reliable(100))
                subs.append(sub)
        conn.send(sorted({s.topic for s in subs}))
        while not await asyncio.to_thread(conn.poll, 1.0):
            pass
        conn.recv()
        dropped_at_subscription = sum(s.dropped for s in subs)
        for s in subs:
            await s.aclose()
    stats = await asyncio.to_thread(writer.close)
    ru = resource.getrusage(resource.RUSAGE_SELF)
    conn.send(
        {
            "written": stats.total_written,
            "dropped": stats.total_dropped + dropped_at_subscription,
            "file_bytes": stats.file_bytes,
            "writer_cpu_s": stats.thread_cpu_s,
            "recorder_cpu_s": ru.ru_utime + ru.ru_stime,
            "digests": digests,
        }
    )


def _recv(conn: multiprocessing.connection.Connection, what: str) -> Any:
    if not conn.poll(_TIMEOUT_S):
        raise TimeoutError(f"bench bag: no answer from the {what} process within {_TIMEOUT_S:.0f} s")
    try:
        return conn.recv()
    except EOFError:
        raise ConfigError(f"bench bag: the {what} process ended without answering (its error is above)") from None


# ----------------------------------------------------------------------------------------------------- main


def phase(vecs: list[Any], agents: list[Any], duration_s: float) -> list[dict[str, Any]]:
    """Step every env for ``duration_s``; the envs' timing records of that time."""
    before = [v.call("timing_snapshot")[0] for v in vecs]
    end = time.monotonic() + duration_s
    while time.monotonic() < end:
        for v, agent in zip(vecs, agents, strict=True):
            v.step_async(agent.act()[None, :])
        for v in vecs:
            v.step_wait()
    return [since(v.call("timing_snapshot")[0], b) for v, b in zip(vecs, before, strict=True)]


def _run(cfg: BagBenchConfig, log: Callable[[str], None]) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    from uniros_async.bag.reader import BagReader
    from uniros_async.bench.looptiming import ScriptedReachAgent
    from uniros_async.runtime import make_vec

    ctx = multiprocessing.get_context("spawn")
    world_conn, world_end = ctx.Pipe()
    # not a daemon: it starts the servo sims' processes; joined, else terminated, below
    world = ctx.Process(target=_world_main, args=(cfg, world_end), daemon=False, name="bench bag world")
    world.start()
    world_end.close()  # a world that dies closes the pipe: the wait for it ends at once
    vecs: list[Any] = []
    recorder = None
    rec_conn: multiprocessing.connection.Connection | None = None
    try:
        uris = _recv(world_conn, "world")
        for (env_id, _, _), uri in zip(ARMS, uris, strict=True):
            vecs.append(
                make_vec(
                    [(env_id, {"robot": uri})],
                    action_mode="absolute",
                    max_episode_steps=10**9,
                    call_timeout_s=60.0,
                )
            )
        agents = [
            ScriptedReachAgent(arm, think_ms=cfg.think_ms, seed=cfg.seed + i) for i, (_, arm, _) in enumerate(ARMS)
        ]
        for i, v in enumerate(vecs):
            v.reset(seed=cfg.seed + i)
        baseline = phase(vecs, agents, cfg.baseline_s) if cfg.baseline_s > 0 else []
        rec_conn, rec_end = ctx.Pipe()
        recorder = ctx.Process(target=_recorder_main, args=(uris, cfg.out, rec_end), daemon=True, name="bench bag rec")
        recorder.start()
        rec_end.close()
        topics = _recv(rec_conn, "recorder")
        log(f"recording {len(topics)} topics to {cfg.out} for {cfg.duration_s:g} s: {' '.join(topics)}")
        snaps = phase(vecs, agents, cfg.duration_s)
        rates = [float(v.get_attr("env_loop_rate_hz")[0]) for v in vecs]
        rec_conn.send("stop")
        world_conn.send("stop")
        published = _recv(world_conn, "world")
        rec = _recv(rec_conn, "recorder")
    finally:
        for v in vecs:
            v.close()
        for proc, conn in ((recorder, rec_conn), (world, world_conn)):
            if proc is None:
                continue
            if conn is not None and proc.is_alive():
                try:
                    conn.send("exit")
                except (BrokenPipeError, OSError):
                    pass
            proc.join(15)
            if proc.is_alive():
                proc.terminate()
                proc.join(5)
    t0 = time.monotonic()
    base = base_picture(cfg.width, cfg.height)
    got: list[tuple[str, int, int]] = []
    frames_ok = True
    stamps = []
    for bm in BagReader(cfg.out).messages():
        got.append(digest(bm.topic, bm.message))
        if bm.topic.endswith(CAMERA_TOPIC):
            stamps.append(bm.message.header.stamp_ns)
            frames_ok = frames_ok and bool(np.array_equal(bm.message.data, frame(stamps[-1], base)))
    read_s = time.monotonic() - t0
    bag = {
        "scenario": "bag",
        "duration_s": cfg.duration_s,
        "file_mb": rec["file_bytes"] / 1e6,
        "written": rec["written"],
        "dropped": rec["dropped"],
        "writer_cpu_s": rec["writer_cpu_s"],
        "recorder_cpu_s": rec["recorder_cpu_s"],
        "camera_published": published,
        "camera_recorded": len(stamps),
        "camera_rate_hz": (len(stamps) - 1) / ((stamps[-1] - stamps[0]) / 1e9) if len(stamps) > 1 else 0.0,
        "read_back_equal": got == rec["digests"],
        "frames_equal": frames_ok,
        "read_s": read_s,
    }
    rows = []
    phases = [("off", baseline), ("recording", snaps)] if baseline else [("recording", snaps)]
    for label, snapshots in phases:
        for (_, arm, emulated), rate, snap in zip(ARMS, rates, snapshots, strict=True):
            act = summary(loop_metrics(snap)["actuator_cycle"])
            period_ms = 1e3 / rate
            rows.append(
                {
                    "scenario": "bag",
                    "bag": label,
                    "env": f"{arm} {'emulated-real' if emulated else 'sim'}",
                    "period_ms": period_ms,
                    "actuator_median_ms": act["p50"],
                    "actuator_iqr_ms": act["iqr"],
                    "actuator_p99_ms": act["p99"],
                    "ticks": act["count"],
                    "goal_met": meets_goal(act["p50"], act["iqr"], period_ms),
                }
            )
    return rows, bag


def format_table(rows: list[dict[str, Any]], bag: dict[str, Any], cfg: BagBenchConfig) -> str:
    """The env loops' table and the bag's line."""
    lines = [
        f"actuator cycle (ms) of four real-time envs while a recorder writes their domains and a {cfg.camera_hz:g} Hz "
        f"{cfg.width}x{cfg.height} camera to one MCAP bag, {cfg.duration_s:g} s",
        f"{'bag':<10} {'env':<20} {'period':>7} {'median':>8} {'IQR':>7} {'p99':>8} {'ticks':>7}  goal",
    ]
    for r in rows:
        lines.append(
            f"{r['bag']:<10} {r['env']:<20} {r['period_ms']:>7.1f} {r['actuator_median_ms']:>8.3f} "
            f"{r['actuator_iqr_ms']:>7.3f} {r['actuator_p99_ms']:>8.2f} {r['ticks']:>7}  "
            f"{'met' if r['goal_met'] else 'MISSED'}"
        )
    lines.append(
        f"bag: {bag['file_mb']:.1f} MB, {bag['written']} messages written, {bag['dropped']} dropped; writer thread CPU "
        f"{bag['writer_cpu_s']:.1f} s, recorder process CPU {bag['recorder_cpu_s']:.1f} s "
        f"({100 * bag['recorder_cpu_s'] / cfg.duration_s:.1f} % of one core); camera frames recorded "
        f"{bag['camera_recorded']} ({bag['camera_rate_hz']:.1f} Hz); read back equal to what the recorder received:"
        f" {'yes' if bag['read_back_equal'] else 'NO'}, frames equal to the published: "
        f"{'yes' if bag['frames_equal'] else 'NO'} (read in {bag['read_s']:.1f} s)"
    )
    lines.append(
        f"goal: actuator cycle median within {MEDIAN_GOAL_MS} ms of the period and IQR below {IQR_GOAL_MS} ms; the "
        "camera's frames are synthetic (a shifted textured picture), so the bag's size is not that of rendered frames"
    )
    return "\n".join(lines)


def main(config: BagBenchConfig, *, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Run the benchmark, print the table, write JSON when asked; returns the records (the envs', then the bag's)."""
    rows, bag = _run(config, log)
    records = [*rows, bag]
    report(format_table(rows, bag, config), records, config.json_path, log)
    if not config.keep:
        Path(config.out).unlink(missing_ok=True)
    return records
