"""``uniros bench ros2``: round trips through a ROS 2 graph, our participant against rclpy, in one run.

What the ROS 2 bridge (``adapters/ros2_bridge.py``) pays per message is a DDS hop of our own participant
(``adapters/ros2``: cyclonedds + rosbags, in an asyncio loop). This bench puts a number on it beside rclpy's. An
rclpy echo node (Jazzy, Fast DDS, from the rclpy venv of ``uniros_async.testing.ros2``) republishes
``/uniros_ping`` on ``/uniros_pong`` and ``/rclpy_ping`` on ``/rclpy_pong``. Two clients then time round trips of
a ``sensor_msgs/msg/JointState`` of the rx200's 8 joints, one at a time (send, wait for the echo, send the next):

- ours, a ``Ros2Node`` in this process (serializing and deserializing each message with rosbags);
- rclpy in its own process, at its fastest for this pattern (publish, then spin its executor once per wake-up).

Both go through the same echo and, by default, over the same medium: UDP on loopback (Fast DDS would otherwise
carry rclpy-to-rclpy over its own shared memory, which our participant cannot speak; ``rclpy_shm=True`` measures
that too). So the difference between them is the two clients' own cost on both ends of a hop.
They take turns in blocks (``blocks`` of ``per_block`` round trips each), so both meet the same moments of the
machine's load; the first block of each is warm-up and not counted. Reported: p50, p90, p99 and IQR in us, and the
ratio of the medians.

DDS discovers by multicast: run as root, the bench re-runs itself in a network namespace of its own (loopback only,
``testing.ros2.netns_command``) unless ``netns=False``; otherwise it uses discovery on this host only.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from uniros_async.bench.stats import progress_counter, report, summary
from uniros_async.errors import ConfigError

__all__ = ["Ros2BenchConfig", "main"]

RCLPY_SCRIPT = Path(__file__).with_name("_ros2_rclpy.py")
NAMES = ("waist", "shoulder", "elbow", "wrist_angle", "wrist_rotate", "gripper", "left_finger", "right_finger")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Ros2BenchConfig:
    blocks: int = 11
    """Blocks per client, taken in turns; the first of each is warm-up."""
    per_block: int = 500
    json_path: str | None = None
    progress: bool = True
    timeout_s: float = 2.0
    """How long one round trip may take before it counts as lost."""
    domain_id: int = 0
    netns: bool = True
    """Run in a network namespace of its own when one can be made (root and ``unshare``)."""
    rclpy_shm: bool = False
    """Let the two rclpy processes (client and echo) use Fast DDS's shared-memory transport between them. Off: both
    clients' hops cross UDP on loopback, the medium our participant has (Fast DDS's shared memory is its own)."""

    def __post_init__(self) -> None:
        if self.blocks < 2 or self.per_block < 1:
            raise ConfigError(f"blocks must be >= 2 and per_block >= 1, got {self.blocks}, {self.per_block}")
        if not 0 <= self.domain_id <= 232:
            raise ConfigError(f"domain_id must be in 0..232, got {self.domain_id}")


async def _our_block(pub: Any, inbox: asyncio.Queue[Any], n: int, seq0: int, timeout_s: float) -> tuple[list[int], int]:
    """``n`` timed round trips of our participant; (times in ns, messages lost)."""
    from uniros_async.adapters.ros2.msgs import message_class

    js, header, stamp = (
        message_class(t) for t in ("sensor_msgs/msg/JointState", "std_msgs/msg/Header", "builtin_interfaces/msg/Time")
    )
    times: list[int] = []
    lost = 0
    seq = seq0
    while len(times) < n:
        seq += 1
        token = str(seq)
        msg = js(
            header=header(stamp=stamp(sec=0, nanosec=0), frame_id=token),
            name=list(NAMES),
            position=np.full(8, 0.1),
            velocity=np.zeros(8),
            effort=np.zeros(8),
        )
        t0 = time.perf_counter_ns()
        pub.publish(msg)
        try:
            async with asyncio.timeout(timeout_s):
                while (await inbox.get()).header.frame_id != token:
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


def _rclpy_block(proc: subprocess.Popen[str], n: int, timeout_s: float) -> tuple[list[int], int]:
    from uniros_async.testing.ros2 import wait_for_line

    assert proc.stdin is not None
    proc.stdin.write(f"go {n}\n")
    proc.stdin.flush()
    out = json.loads(wait_for_line(proc, "{", timeout_s=n * timeout_s + 30.0))
    if len(out["ns"]) < n:
        raise RuntimeError(f"the rclpy client lost more than 10 round trips (got {len(out['ns'])} of {n})")
    return list(out["ns"]), int(out["lost"])


async def _run(cfg: Ros2BenchConfig, client: subprocess.Popen[str]) -> dict[str, tuple[list[int], int]]:
    from uniros_async.adapters.ros2 import COMMANDS, open_ros2_node

    results: dict[str, tuple[list[int], int]] = {"uniros": ([], 0), "rclpy": ([], 0)}
    step = progress_counter(2 * cfg.blocks, cfg.progress, "ros2 bench", "block")
    inbox: asyncio.Queue[Any] = asyncio.Queue()
    async with open_ros2_node("uniros_bench_client", domain_id=cfg.domain_id) as node:
        pub = node.create_publisher("/uniros_ping", "sensor_msgs/msg/JointState", qos=COMMANDS)
        sub = node.create_subscription("/uniros_pong", "sensor_msgs/msg/JointState", inbox.put_nowait, qos=COMMANDS)
        await pub.wait_for_subscribers(1, timeout_s=15.0)
        await sub.wait_for_publishers(1, timeout_s=15.0)
        seq = 0
        for b in range(cfg.blocks):
            ours, lost = await _our_block(pub, inbox, cfg.per_block, seq, cfg.timeout_s)
            seq += cfg.per_block + lost
            step(1)
            theirs, their_lost = await asyncio.to_thread(_rclpy_block, client, cfg.per_block, cfg.timeout_s)
            step(1)
            if b == 0:
                continue  # warm-up: discovery, caches
            for key, (t, n_lost) in (("uniros", (ours, lost)), ("rclpy", (theirs, their_lost))):
                prev_t, prev_lost = results[key]
                results[key] = (prev_t + t, prev_lost + n_lost)
    step(0, done=True)
    return results


def _in_netns(config: Ros2BenchConfig) -> list[dict[str, Any]] | None:
    """Re-run this bench in a network namespace of its own; its records, or None when none can be made here."""
    from uniros_async.testing.ros2 import in_netns, netns_command, netns_missing

    if not config.netns or in_netns() or netns_missing() is not None:
        return None
    with tempfile.TemporaryDirectory(prefix="uniros_bench_ros2_") as tmp:
        out = Path(tmp) / "records.json"
        argv = [sys.executable, "-m", "uniros_async.cli", "bench", "ros2", "--blocks", str(config.blocks)]
        argv += ["--per-block", str(config.per_block), "--domain-id", str(config.domain_id), "--json", str(out)]
        argv += [] if config.progress else ["--no-progress"]
        argv += ["--rclpy-shm"] if config.rclpy_shm else []
        proc = subprocess.run(netns_command(argv), text=True, check=False, stdout=subprocess.PIPE)
        if proc.returncode != 0:
            raise RuntimeError(f"the bench in its network namespace failed ({proc.returncode}):\n{proc.stdout}")
        records: list[dict[str, Any]] = json.loads(out.read_text())
    return records


def main(config: Ros2BenchConfig, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Run the benchmark, print its table, return its records.

    Raises:
        ConfigError: the rclpy venv or our ROS 2 dependencies are missing (the message says what to install).
    """
    from uniros_async.testing.ros2 import kill_process, rclpy_env, ros2_missing, ros2_python, wait_for_line

    reason = ros2_missing()
    if reason is not None:
        raise ConfigError(f"uniros bench ros2 needs the rclpy peer: {reason}")
    from uniros_async.testing.ros2 import in_netns

    records = _in_netns(config)
    if records is not None:
        _print(config, records, log, "a network namespace of its own")
        return records
    with tempfile.TemporaryDirectory(prefix="uniros_bench_ros2_") as tmp:
        env = rclpy_env(config.domain_id, home=tmp)
        if not config.rclpy_shm:
            env["FASTDDS_BUILTIN_TRANSPORTS"] = "UDPv4"
        procs = []
        try:
            for mode in ("echo", "client"):
                proc = subprocess.Popen(
                    [str(ros2_python()), str(RCLPY_SCRIPT), mode],
                    env=env,
                    stdin=subprocess.PIPE,
                    stdout=subprocess.PIPE,
                    stderr=subprocess.DEVNULL,
                    text=True,
                    bufsize=1,
                )
                procs.append(proc)
                wait_for_line(proc, "ready", timeout_s=60.0)
            results = asyncio.run(_run(config, procs[1]))
        finally:
            for proc in procs:
                kill_process(proc)
    records = []
    for key in ("uniros", "rclpy"):
        times, lost = results[key]
        s = summary([t / 1e3 for t in times])
        records.append(
            {"client": key, **{f"{k}_us": v for k, v in s.items() if k != "count"}, "count": s["count"], "lost": lost}
        )
    _print(config, records, log, "a network namespace of its own" if in_netns() else "this host's loopback")
    return records


def _print(config: Ros2BenchConfig, records: list[dict[str, Any]], log: Callable[[str], None], where: str) -> None:
    lines = [
        f"ROS 2 round trips, sensor_msgs/msg/JointState of 8 joints through an rclpy echo node (Jazzy, Fast DDS), "
        f"{config.blocks - 1} blocks of {config.per_block} per client, taken in turns (first block of each: warm-up)",
        f"{'client':<38}{'p50 us':>10}{'p90 us':>10}{'p99 us':>10}{'IQR us':>10}{'lost':>6}{'count':>7}",
        "-" * 91,
    ]
    labels = {"uniros": "uniros (cyclonedds+rosbags, asyncio)", "rclpy": "rclpy (spin_once)"}
    for r in records:
        lines.append(
            f"{labels[r['client']]:<38}{r['p50_us']:>10.1f}{r['p90_us']:>10.1f}{r['p99_us']:>10.1f}{r['iqr_us']:>10.1f}"
            f"{r['lost']:>6}{r['count']:>7}"
        )
    ratio = records[0]["p50_us"] / records[1]["p50_us"]
    medium = "rclpy-to-rclpy over Fast DDS shared memory" if config.rclpy_shm else "every hop over UDP on loopback"
    lines.append(f"median round trip: uniros / rclpy = {ratio:.2f} (DDS in {where}; {medium})")
    report("\n".join(lines), records, config.json_path, log)
