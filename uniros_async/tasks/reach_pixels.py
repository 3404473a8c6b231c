"""ReachPixels: reach a coloured target on the table, seen only by the camera (``uniros/Rx200ReachPixels-v0``).

The reach task (tasks/reach.py) with its goal hidden from the vector: each episode puts a red disc on the table at
a reachable (x, y) and the goal is the point ``TARGET_HEIGHT_M`` above its centre. The observation is a Dict of
the scene camera's frame (``pixels``, uint8 84x84x3 by default) and, with the default
``obs_mode="pixels+state"``, the arm's own state (``state``: EE position, joint positions, the previous action,
joint velocities; no goal direction or distance); ``obs_mode="pixels"`` gives the frame alone. Where the target
is, only the image says. Actions, rewards, success and episode length are the reach task's.

The target is a ``Marker`` (a cylinder) published on the arm's ``markers_in``: the sim cameras draw it, the sim and
the emulated real arm show it as their goal marker. On a real arm the disc is a real one: the env publishes where it
wants it, and someone puts it there.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from uniros_async.bus.messages import Header, JointState, Marker
from uniros_async.errors import ConfigError
from uniros_async.tasks.reach import ReachEnv

__all__ = ["TARGET_BOXES", "TARGET_HEIGHT_M", "ReachPixelsEnv"]

TARGET_HEIGHT_M = 0.05
"""The goal is this far above the target's centre (UniROS's rx200 goal box starts at z = 0.05 m)."""
TARGET_BOXES = {"rx200": ((0.15, -0.15), (0.25, 0.15)), "ned2": ((0.15, -0.15), (0.25, 0.15))}
"""Where targets are put on the table (x, y in m): UniROS's goal box of the arm, seen from above."""
TARGET_DIAMETER_M = 0.05
TARGET_RGBA = (0.9, 0.05, 0.05, 1.0)
_GOAL_ENTRIES = slice(3, 7)  # direction to the goal and distance, in the reach task's vector


class ReachPixelsEnv(ReachEnv):
    """Reach a target on the table seen only in the camera's frames (see the module docstring)."""

    def __init__(self, arm: str = "rx200", **kwargs: Any) -> None:
        kwargs.setdefault("obs_mode", "pixels+state")
        if kwargs["obs_mode"] == "state":
            raise ConfigError(
                "obs_mode='state': the pixel reach task's goal is seen only by the camera; expected 'pixels' or "
                "'pixels+state'"
            )
        if arm not in TARGET_BOXES and ("goal_min" not in kwargs or "goal_max" not in kwargs):
            raise ConfigError(f"ReachPixels on {arm!r}: give goal_min and goal_max (targets are known for rx200, ned2)")
        lo, hi = TARGET_BOXES.get(arm, ((0.0, 0.0), (0.0, 0.0)))
        kwargs.setdefault("goal_min", (lo[0], lo[1], TARGET_HEIGHT_M))
        kwargs.setdefault("goal_max", (hi[0], hi[1], TARGET_HEIGHT_M))
        self._markers: Any = None
        super().__init__(arm, **kwargs)

    def _make_observation_space(self) -> gym.Space[Any]:
        lo, hi = (np.delete(b, np.r_[_GOAL_ENTRIES]) for b in self._vector_bounds())
        state = gym.spaces.Box(lo, hi, dtype=np.float32)
        assert self._pixels is not None  # obs_mode is never "state" here
        return self._pixels.space(state)

    def _observation(self, state: JointState, ee: np.ndarray) -> Any:
        return np.delete(self._vector_obs(state, ee), np.r_[_GOAL_ENTRIES])

    async def _join(self, domain: Any, transport: str, options: Any) -> None:
        await super()._join(domain, transport, options)
        self._markers = await self._node.create_publisher(Marker, "markers_in")

    def target_marker(self) -> Marker:
        """The episode's target: a red disc on the table under the goal."""
        return Marker(
            header=Header(stamp_ns=self._clock.now_ns(), frame_id="world"),
            ns="target",
            kind="cylinder",
            position=np.array([self.goal[0], self.goal[1], 0.002]),
            scale=np.array([TARGET_DIAMETER_M, TARGET_DIAMETER_M, 0.004]),
            color=np.array(TARGET_RGBA),
        )

    def _on_reset(self, q_arm: np.ndarray) -> None:
        super()._on_reset(q_arm)
        marker = self.target_marker()
        if self._markers is not None:
            self._markers.publish(marker)
        assert self._pixels is not None
        self._pixels.show(marker)
