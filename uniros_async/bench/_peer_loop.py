"""The client loop both ROS peers of the round-trip benches run (``_ros1_rospy.py``, ``_ros2_rclpy.py``).

The peers run in other interpreters (the system Python with ROS 1, the rclpy venv), which have neither our
package nor its dependencies: they import this module by its file name, from the folder they run in, so it must
need nothing beyond the standard library.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable

MAX_LOST = 10
"""Round trips a block may lose before the client stops it (``_round_trips.MAX_LOST``)."""


def answer_go_lines(arm: Callable[[str], None], round_trip: Callable[[], bool]) -> None:
    """For each ``go N`` line on stdin, time N round trips and print one JSON line: ``{"ns": [...], "lost": k}``.

    Args:
        arm: sets up the next round trip for ``token`` (the echo to wait for); not timed.
        round_trip: publishes and waits for the echo of the armed token; whether it came back in time. Timed.
    """
    seq = 0
    for line in sys.stdin:
        if not line.startswith("go "):
            continue
        n = int(line.split()[1])
        times: list[int] = []
        lost = 0
        while len(times) < n:
            seq += 1
            arm(str(seq))
            t0 = time.perf_counter_ns()
            if round_trip():
                times.append(time.perf_counter_ns() - t0)
            else:
                lost += 1
                if lost > MAX_LOST:
                    break
        print(json.dumps({"ns": times, "lost": lost}), flush=True)
