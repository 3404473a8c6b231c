"""``uniros bench ros1``: round trips through a ROS 1 graph, our asyncio client against rospy, in one run.

What the bridge to a real arm (``adapters/ros1_bridge.py``) pays per message is a TCPROS hop of our own client
(``adapters/ros1/``). This bench puts a number on it beside rospy's. A real rosmaster and a rospy echo node run
with the system Python (Debian's ROS 1 packages); the echo republishes ``/uniros_ping`` on ``/uniros_pong`` and
``/rospy_ping`` on ``/rospy_pong``. Two clients then time round trips of a ``sensor_msgs/JointState`` of the
rx200's 8 joints (~330 B), one at a time (send, wait for the echo, send the next):

- ours, a ``Ros1Node`` in this process;
- rospy in its own process, at its fastest: publishing without a queue, subscribing with ``tcp_nodelay``.

Both go through the same rospy echo, so the difference between them is the two clients' own cost on both ends of
a hop. They take turns in blocks (``blocks`` of ``per_block`` round trips each), so both meet the same moments of
the machine's load; the first block of each is warm-up and not counted. Reported: p50, p90, p99 and IQR in us,
and the ratio of the medians.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import subprocess
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from uniros_async.bench.stats import progress_counter, report, summary
from uniros_async.errors import ConfigError

__all__ = ["Ros1BenchConfig", "main"]

ROSPY_SCRIPT = Path(__file__).with_name("_ros1_rospy.py")
NAMES = ("waist", "shoulder", "elbow", "wrist_angle", "wrist_rotate", "gripper", "left_finger", "right_finger")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Ros1BenchConfig:
    blocks: int = 11
    """Blocks per client, taken in turns; the first of each is warm-up."""
    per_block: int = 500
    json_path: str | None = None
    progress: bool = True
    timeout_s: float = 2.0
    """How long one round trip may take before it counts as lost."""

    def __post_init__(self) -> None:
        if self.blocks < 2 or self.per_block < 1:
            raise ConfigError(f"blocks must be >= 2 and per_block >= 1, got {self.blocks}, {self.per_block}")


async def _our_block(pub: Any, sub: Any, msgs: Any, n: int, seq0: int, timeout_s: float) -> tuple[list[int], int]:
    """``n`` timed round trips of our client; (times in ns, messages lost)."""
    times: list[int] = []
    lost = 0
    seq = seq0
    while len(times) < n:
        seq += 1
        msg = msgs.JointState(  # the token rides in frame_id: a rospy publisher renumbers header.seq
            header=msgs.RosHeader(seq=seq, stamp_ns=0, frame_id=str(seq)),
            name=list(NAMES),
            position=np.full(8, 0.1),
            velocity=np.zeros(8),
            effort=np.zeros(8),
        )
        t0 = time.perf_counter_ns()
        pub.publish(msg)
        try:
            while (await sub.receive(timeout_s=timeout_s)).header.frame_id != msg.header.frame_id:
                pass  # a late echo of a lost one
        except TimeoutError:
            lost += 1
            if lost > 10:
                raise RuntimeError(
                    f"more than 10 round trips over {pub.topic} got no echo within {timeout_s} s"
                ) from None
            continue
        times.append(time.perf_counter_ns() - t0)
    return times, lost


def _rospy_block(proc: subprocess.Popen[str], n: int, timeout_s: float) -> tuple[list[int], int]:
    from uniros_async.testing.ros1 import wait_for_line

    assert proc.stdin is not None
    proc.stdin.write(f"go {n}\n")
    proc.stdin.flush()
    out = json.loads(wait_for_line(proc, "{", timeout_s=n * timeout_s + 30.0))
    if len(out["ns"]) < n:
        raise RuntimeError(f"the rospy client lost more than 10 round trips (got {len(out['ns'])} of {n})")
    return list(out["ns"]), int(out["lost"])


async def _run(cfg: Ros1BenchConfig, uri: str, client: subprocess.Popen[str]) -> dict[str, tuple[list[int], int]]:
    from uniros_async.adapters.ros1 import msgs, open_ros1_node

    results: dict[str, tuple[list[int], int]] = {"uniros": ([], 0), "rospy": ([], 0)}
    step = progress_counter(2 * cfg.blocks, cfg.progress, "ros1 bench", "block")
    async with open_ros1_node("/uniros_bench_client", master_uri=uri) as node:
        pub = await node.advertise("/uniros_ping", msgs.JointState)
        sub = await node.subscribe("/uniros_pong", msgs.JointState)
        await pub.wait_for_subscribers(1, timeout_s=15.0)
        await sub.wait_for_publishers(1, timeout_s=15.0)
        seq = 0
        for b in range(cfg.blocks):
            ours, lost = await _our_block(pub, sub, msgs, cfg.per_block, seq, cfg.timeout_s)
            seq += cfg.per_block + lost
            step(1)
            theirs, their_lost = await asyncio.to_thread(_rospy_block, client, cfg.per_block, cfg.timeout_s)
            step(1)
            if b == 0:
                continue  # warm-up: connections and caches
            for key, (t, n_lost) in (("uniros", (ours, lost)), ("rospy", (theirs, their_lost))):
                prev_t, prev_lost = results[key]
                results[key] = (prev_t + t, prev_lost + n_lost)
    step(0, done=True)
    return results


def main(config: Ros1BenchConfig, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Run the benchmark, print its table, return its records.

    Raises:
        ConfigError: ROS 1 is not installed (the message names the packages).
    """
    from uniros_async.testing.ros1 import (
        kill_process,
        open_rosmaster,
        ros1_missing,
        ros1_python,
        ros_env,
        wait_for_line,
    )

    reason = ros1_missing()
    if reason is not None:
        raise ConfigError(f"uniros bench ros1 needs ROS 1 for its master and the rospy peer: {reason}")
    with tempfile.TemporaryDirectory(prefix="uniros_bench_ros1_") as tmp, open_rosmaster(tmp) as uri:
        env = ros_env(uri, home=Path(tmp) / "ros_home")
        procs = []
        try:
            for mode in ("echo", "client"):
                proc = subprocess.Popen(
                    [ros1_python(), str(ROSPY_SCRIPT), mode],
                    env=env,
                    stdin=subprocess.PIPE,
                    stdout=subprocess.PIPE,
                    stderr=subprocess.DEVNULL,
                    text=True,
                    bufsize=1,
                )
                procs.append(proc)
                wait_for_line(proc, "ready", timeout_s=30.0)
            results = asyncio.run(_run(config, uri, procs[1]))
        finally:
            for proc in procs:
                kill_process(proc)
    records: list[dict[str, Any]] = []
    lines = [
        f"ROS 1 round trips, sensor_msgs/JointState of 8 joints through a rospy echo node, "
        f"{config.blocks - 1} blocks of {config.per_block} per client, taken in turns (first block of each: warm-up)",
        f"{'client':<30}{'p50 us':>10}{'p90 us':>10}{'p99 us':>10}{'IQR us':>10}{'lost':>6}{'count':>7}",
        "-" * 83,
    ]
    labels = {"uniros": "uniros (asyncio, this process)", "rospy": "rospy (queue_size=None)"}
    for key in ("uniros", "rospy"):
        times, lost = results[key]
        s = summary((np.asarray(times) / 1e3).tolist())
        records.append(
            {"client": key, **{f"{k}_us": v for k, v in s.items() if k != "count"}, "count": s["count"], "lost": lost}
        )
        lines.append(
            f"{labels[key]:<30}{s['p50']:>10.1f}{s['p90']:>10.1f}{s['p99']:>10.1f}{s['iqr']:>10.1f}{lost:>6}"
            f"{s['count']:>7}"
        )
    ratio = records[0]["p50_us"] / records[1]["p50_us"]
    lines.append(f"median round trip: uniros / rospy = {ratio:.2f}")
    report("\n".join(lines), records, config.json_path, log)
    return records
