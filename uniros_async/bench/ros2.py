"""``uniros bench ros2``: round trips through a ROS 2 graph, our participant against rclpy, in one run.

What the ROS 2 bridge (``adapters/ros2_bridge.py``) pays per message is a DDS hop of our own participant
(``adapters/ros2``: cyclonedds + rosbags, in an asyncio loop). This bench puts a number on it beside rclpy's. An
rclpy echo node (Jazzy, Fast DDS, from the rclpy venv of ``uniros_async.bench.ros2_peers``) republishes
``/uniros_ping`` on ``/uniros_pong`` and ``/rclpy_ping`` on ``/rclpy_pong``. Two clients then time round trips of
a ``sensor_msgs/msg/JointState`` of the rx200's 8 joints, one at a time (send, wait for the echo, send the next):

- ours, a ``Ros2Node`` in this process (serializing and deserializing each message with rosbags);
- rclpy in its own process, at its fastest for this pattern (publish, then spin its executor once per wake-up).

Both go through the same echo and, by default, over the same medium: UDP on loopback (Fast DDS would otherwise
carry rclpy-to-rclpy over its own shared memory, which our participant cannot speak; ``rclpy_shm=True`` measures
that too). So the difference between them is the two clients' own cost on both ends of a hop.
They take turns in blocks (``blocks`` of ``per_block`` round trips each), so both meet the same moments of the
machine's load; the first block of each is warm-up and not counted. Reported: p50, p90, p99 and IQR in us, and the
ratio of the medians. The turns, the table and the peer's loop are shared with ``uniros bench ros1``
(``_round_trips``, ``_peer_loop``).

DDS discovers by multicast: run as root, the bench re-runs itself in a network namespace of its own (loopback only,
``ros2_peers.netns_command``) unless ``netns=False``; otherwise it uses discovery on this host only.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from uniros_async.bench import _round_trips
from uniros_async.errors import ConfigError

__all__ = ["Ros2BenchConfig", "main"]

RCLPY_SCRIPT = Path(__file__).with_name("_ros2_rclpy.py")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Ros2BenchConfig(_round_trips.RoundTripBenchConfig):
    """The blocks and sizes of ``uniros bench ros2`` (``_round_trips.RoundTripBenchConfig``), and where DDS runs."""

    domain_id: int = 0
    netns: bool = True
    """Run in a network namespace of its own when one can be made (root and ``unshare``)."""
    rclpy_shm: bool = False
    """Let the two rclpy processes (client and echo) use Fast DDS's shared-memory transport between them. Off: both
    clients' hops cross UDP on loopback, the medium our participant has (Fast DDS's shared memory is its own)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 0 <= self.domain_id <= 232:
            raise ConfigError(f"domain_id must be in 0..232, got {self.domain_id}")


async def _run(cfg: Ros2BenchConfig, client: subprocess.Popen[str]) -> dict[str, _round_trips.Blocks]:
    from uniros_async.adapters.ros2 import COMMANDS, open_ros2_node
    from uniros_async.adapters.ros2.msgs import message_class

    js, header, stamp = (
        message_class(t) for t in ("sensor_msgs/msg/JointState", "std_msgs/msg/Header", "builtin_interfaces/msg/Time")
    )

    def make(token: str) -> Any:
        return js(
            header=header(stamp=stamp(sec=0, nanosec=0), frame_id=token),
            name=list(_round_trips.NAMES),
            position=np.full(8, 0.1),
            velocity=np.zeros(8),
            effort=np.zeros(8),
        )

    inbox: asyncio.Queue[Any] = asyncio.Queue()
    async with open_ros2_node("uniros_bench_client", domain_id=cfg.domain_id) as node:
        pub = node.create_publisher("/uniros_ping", "sensor_msgs/msg/JointState", qos=COMMANDS)
        sub = node.create_subscription("/uniros_pong", "sensor_msgs/msg/JointState", inbox.put_nowait, qos=COMMANDS)
        await pub.wait_for_subscribers(1, timeout_s=15.0)
        await sub.wait_for_publishers(1, timeout_s=15.0)
        return await _round_trips.take_turns(cfg, client, "rclpy", pub=pub, receive=inbox.get, make=make)


def _in_netns(config: Ros2BenchConfig) -> list[dict[str, Any]] | None:
    """Re-run this bench in a network namespace of its own; its records, or None when none can be made here."""
    from uniros_async.bench.ros2_peers import in_netns, netns_command, netns_missing

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
    from uniros_async.bench.ros2_peers import in_netns, rclpy_env, ros2_missing, ros2_python

    reason = ros2_missing()
    if reason is not None:
        raise ConfigError(f"uniros bench ros2 needs the rclpy peer: {reason}")
    records = _in_netns(config)
    if records is not None:
        _print(config, records, log, "a network namespace of its own")
        return records
    with tempfile.TemporaryDirectory(prefix="uniros_bench_ros2_") as tmp:
        env = rclpy_env(config.domain_id, home=tmp)
        if not config.rclpy_shm:
            env["FASTDDS_BUILTIN_TRANSPORTS"] = "UDPv4"
        with _round_trips.open_peers([str(ros2_python()), str(RCLPY_SCRIPT)], env, ready_timeout_s=60.0) as client:
            results = asyncio.run(_run(config, client))
    records = _round_trips.records_of(results)
    _print(config, records, log, "a network namespace of its own" if in_netns() else "this host's loopback")
    return records


def _print(config: Ros2BenchConfig, records: list[dict[str, Any]], log: Callable[[str], None], where: str) -> None:
    labels = {"uniros": "uniros (cyclonedds+rosbags, asyncio)", "rclpy": "rclpy (spin_once)"}
    title = "ROS 2 round trips, sensor_msgs/msg/JointState of 8 joints through an rclpy echo node (Jazzy, Fast DDS)"
    medium = "rclpy-to-rclpy over Fast DDS shared memory" if config.rclpy_shm else "every hop over UDP on loopback"
    _round_trips.print_table(config, records, labels, title=title, ratio_note=f"DDS in {where}; {medium}", log=log)
