"""The rclpy row of ``uniros bench transport``: ``sensor_msgs/Image`` round trips through an rclpy echo.

Both ends run in the rclpy venv of ``ros2_peers`` (Jazzy, Fast DDS): the echo of ``uniros bench ros2``
(``_ros2_rclpy.py echo``, which also republishes ``/rclpy_image_ping`` on ``/rclpy_image_pong``) and one client
process per frame size (``_ros2_rclpy.py image_client H W ENC``), which times round trips one at a time as that
bench's client does (publish, spin its executor until the echo is back). A payload of an image's size is an rgb8
frame of that image; any other is a mono8 row of its length. Discovery stays on this host
(``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``), on a ROS domain of its own. Its ``msgs/s`` column is round trips per
second (the client waits for each echo).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import tempfile
import time

from uniros_async.bench import ros1_peers, ros2_peers

__all__ = ["RclpyImageClient", "rclpy_missing"]

logger = logging.getLogger(__name__)

SCRIPT = os.path.join(os.path.dirname(__file__), "_ros2_rclpy.py")
START_TIMEOUT_S = 60.0
ROUND_TRIP_TIMEOUT_S = 120.0
MAX_ROUNDS = 300
"""Round trips per call at most: rclpy's take milliseconds each, so its rows take fewer samples than the others."""
IMAGE_SHAPES = {640 * 480 * 3: (480, 640), 1280 * 720 * 3: (720, 1280)}
"""Payload sizes sent as rgb8 frames of these (height, width)."""


def rclpy_missing() -> str | None:
    """Why the rclpy row cannot run here (what to install), or None."""
    return ros2_peers.ros2_missing()


class RclpyImageClient:
    """An rclpy echo and its image clients, for ``uniros bench transport``'s ``rclpy`` row."""

    name = "rclpy"

    def __init__(self) -> None:
        self._tmp = tempfile.mkdtemp(prefix="uniros-bench-rclpy-")
        self._domain = 150 + os.getpid() % 80  # a ROS domain of its own: other rclpy tests may run beside
        self._clients: dict[int, subprocess.Popen[str]] = {}
        self._echo = self._start("echo")

    def _start(self, *args: str) -> subprocess.Popen[str]:
        proc = ros2_peers.start_rclpy(SCRIPT, *args, domain_id=self._domain, tmp_path=self._tmp, stdin=True)
        try:
            ros1_peers.wait_for_line(proc, "ready", timeout_s=START_TIMEOUT_S)
        except BaseException:
            ros1_peers.kill_process(proc)
            raise
        return proc

    def _client(self, size: int) -> subprocess.Popen[str]:
        if size not in self._clients:
            h, w = IMAGE_SHAPES.get(size, (1, size))
            self._clients[size] = self._start(
                "image_client", str(h), str(w), "rgb8" if size in IMAGE_SHAPES else "mono8"
            )
        return self._clients[size]

    def _go(self, size: int, n: int) -> list[float]:
        """``n`` round trips of ``size`` bytes (``MAX_ROUNDS`` at most), in us. A round trip whose echo is not back
        within 2 s is lost (the client stops after 10: ``_peer_loop.MAX_LOST``) and logged, not timed."""
        proc = self._client(size)
        assert proc.stdin is not None
        proc.stdin.write(f"go {min(n, MAX_ROUNDS)}\n")
        proc.stdin.flush()
        line = ros1_peers.wait_for_line(proc, "{", timeout_s=ROUND_TRIP_TIMEOUT_S)
        got = json.loads(line)
        times = [t / 1e3 for t in got["ns"]]
        if got["lost"]:
            logger.warning("rclpy: %d round trips of %d bytes lost (no echo within 2 s)", got["lost"], size)
        if not times:
            raise RuntimeError(f"rclpy image echo answered none of {n} round trips of {size} bytes")
        return times

    def rtt(self, payload: bytes, n: int) -> list[float]:
        return self._go(len(payload), n)

    def throughput(self, payload: bytes, n: int) -> float:
        t0 = time.perf_counter()
        done = len(self._go(len(payload), n))
        return done / (time.perf_counter() - t0)

    def close(self) -> None:
        for proc in [*self._clients.values(), self._echo]:
            ros1_peers.kill_process(proc)
        self._clients.clear()
        shutil.rmtree(self._tmp, ignore_errors=True)
