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
and the ratio of the medians. The turns, the table and the peer's loop are shared with ``uniros bench ros2``
(``_round_trips``, ``_peer_loop``).
"""

from __future__ import annotations

import asyncio
import dataclasses
import subprocess
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from uniros_async.bench import _round_trips
from uniros_async.errors import ConfigError

__all__ = ["Ros1BenchConfig", "main"]

ROSPY_SCRIPT = Path(__file__).with_name("_ros1_rospy.py")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Ros1BenchConfig(_round_trips.RoundTripBenchConfig):
    """The blocks and sizes of ``uniros bench ros1`` (``_round_trips.RoundTripBenchConfig``)."""


async def _run(cfg: Ros1BenchConfig, uri: str, client: subprocess.Popen[str]) -> dict[str, _round_trips.Blocks]:
    from uniros_async.adapters.ros1 import msgs, open_ros1_node

    def make(token: str) -> Any:
        return msgs.JointState(
            header=msgs.RosHeader(seq=int(token), stamp_ns=0, frame_id=token),
            name=list(_round_trips.NAMES),
            position=np.full(8, 0.1),
            velocity=np.zeros(8),
            effort=np.zeros(8),
        )

    async with open_ros1_node("/uniros_bench_client", master_uri=uri) as node:
        pub = await node.advertise("/uniros_ping", msgs.JointState)
        sub = await node.subscribe("/uniros_pong", msgs.JointState)
        await pub.wait_for_subscribers(1, timeout_s=15.0)
        await sub.wait_for_publishers(1, timeout_s=15.0)
        return await _round_trips.take_turns(cfg, client, "rospy", pub=pub, receive=sub.receive, make=make)


def main(config: Ros1BenchConfig, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Run the benchmark, print its table, return its records.

    Raises:
        ConfigError: ROS 1 is not installed (the message names the packages).
    """
    from uniros_async.bench.ros1_peers import open_rosmaster, ros1_missing, ros1_python, ros_env

    reason = ros1_missing()
    if reason is not None:
        raise ConfigError(f"uniros bench ros1 needs ROS 1 for its master and the rospy peer: {reason}")
    with tempfile.TemporaryDirectory(prefix="uniros_bench_ros1_") as tmp, open_rosmaster(tmp) as uri:
        env = ros_env(uri, home=Path(tmp) / "ros_home")
        with _round_trips.open_peers([ros1_python(), str(ROSPY_SCRIPT)], env, ready_timeout_s=30.0) as client:
            results = asyncio.run(_run(config, uri, client))
    records = _round_trips.records_of(results)
    labels = {"uniros": "uniros (asyncio, this process)", "rospy": "rospy (queue_size=None)"}
    title = "ROS 1 round trips, sensor_msgs/JointState of 8 joints through a rospy echo node"
    _round_trips.print_table(config, records, labels, title=title, log=log)
    return records
