"""What a reach task draws: its goal, the end effector, the goal box and the safety bounds, as Marker messages.

``TaskMarkers`` publishes them on the arm's ``markers`` topic (``/rx200/markers``, beside the sim's own), as
UniROS's Markers module does for RViz: the goal at every reset, and all of them at most every ``period_s`` of wall
time from the step, never from the env loop's tick. ``uniros view`` draws them; a bag records them.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from uniros_async.bus.messages import Header, Marker

__all__ = ["MARKER_PERIOD_S", "TaskMarkers", "box_edges", "reach_markers"]

MARKER_PERIOD_S = 0.5
"""The least wall time between two publications of a task's markers (a modest rate for a person watching)."""

GOAL_RGBA = (0.9, 0.1, 0.1, 0.9)
EE_RGBA = (0.1, 0.8, 0.1, 1.0)
BOUNDS_RGBA = (0.3, 0.5, 1.0, 1.0)
GOAL_BOX_RGBA = (0.9, 0.6, 0.1, 1.0)


def box_edges(lo: Any, hi: Any) -> np.ndarray:
    """The 12 edges of the axis-aligned box ``lo``-``hi`` as one line strip (16 points, some edges twice)."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    c = [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    order = [0, 1, 3, 2, 0, 4, 5, 7, 6, 4, 5, 1, 3, 7, 6, 2]
    return np.array([c[i] for i in order], dtype=np.float64)


def reach_markers(
    stamp_ns: int,
    goal: np.ndarray,
    ee: np.ndarray | None,
    bounds: tuple[Any, Any],
    goal_box: tuple[Any, Any],
    tolerance_m: float,
) -> list[Marker]:
    """A reach task's markers at ``stamp_ns`` (frame ``world``): the goal (a sphere of the reach tolerance's
    diameter, labelled), the end effector (None: left out), the safety bounds and the box goals are drawn from."""
    h = Header(stamp_ns=stamp_ns, frame_id="world")
    out = [
        Marker(header=h, ns="goal", kind="sphere", position=np.asarray(goal, dtype=np.float64),
               scale=np.full(3, max(2 * tolerance_m, 0.01)), color=np.array(GOAL_RGBA), text="goal"),
        Marker(header=h, ns="bounds", kind="line_strip", points=box_edges(*bounds), scale=np.full(3, 0.003),
               color=np.array(BOUNDS_RGBA), text="safety bounds"),
        Marker(header=h, ns="goal_box", kind="line_strip", points=box_edges(*goal_box), scale=np.full(3, 0.002),
               color=np.array(GOAL_BOX_RGBA), text="goal box"),
    ]  # fmt: skip
    if ee is not None:
        out.append(Marker(header=h, ns="ee", kind="sphere", position=np.asarray(ee, dtype=np.float64),
                          scale=np.full(3, 0.02), color=np.array(EE_RGBA), text="end effector"))  # fmt: skip
    return out


class TaskMarkers:
    """A task's marker publisher on its node (see the module docstring).

    Args:
        period_s: the least wall time between two publications by ``maybe_publish``.
    """

    def __init__(self, period_s: float = MARKER_PERIOD_S) -> None:
        self.period_s = period_s
        self._pub: Any = None
        self._last = -float("inf")
        self.published = 0

    async def join(self, node: Any) -> None:
        """Create the ``markers`` publisher on ``node`` (again after the env rejoins its domain)."""
        from uniros_async.bus import reliable

        # a burst of several markers: a reader that keeps only the newest would see the last alone
        self._pub = await node.create_publisher(Marker, "markers", qos=reliable(16))

    def publish(self, markers: list[Marker]) -> None:
        """Publish ``markers`` now (nothing before ``join``)."""
        if self._pub is None:
            return
        for m in markers:
            self._pub.publish(m)
        self._last = time.monotonic()
        self.published += 1

    def due(self) -> bool:
        """True when ``period_s`` has passed since the last publication."""
        return self._pub is not None and time.monotonic() - self._last >= self.period_s
