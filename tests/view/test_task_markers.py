"""The reach task's markers: a real Rx200Reach-v0 env on an arm served in a tcp domain publishes its goal, end
effector, safety bounds and goal box on ``/rx200/markers`` at reset and at a modest rate while stepping, and a
node of the domain (as ``uniros view`` is) receives them."""

from __future__ import annotations

import asyncio
from collections import Counter

import gymnasium as gym
import numpy as np
import pytest

import uniros_async  # noqa: F401  (registers the envs)
from uniros_async.bus import open_domain, open_node, reliable
from uniros_async.bus.messages import Marker
from uniros_async.sim.node import open_servo_sim
from uniros_async.tasks.markers import MARKER_PERIOD_S, box_edges

pytestmark = pytest.mark.slow


def test_box_edges_walk_all_twelve_edges() -> None:
    pts = box_edges([0, 0, 0], [1, 2, 3])
    steps = {tuple(sorted(map(tuple, (a, b)))) for a, b in zip(pts[:-1], pts[1:], strict=True)}
    assert len(steps) == 12 and all(np.count_nonzero(np.subtract(*s)) == 1 for s in steps)


async def test_a_reach_env_publishes_its_markers_to_the_arms_domain() -> None:
    got: list[Marker] = []
    async with (
        open_domain() as domain,
        open_servo_sim("rx200", domain=domain.uri),
        open_node("watcher", domain=domain.uri) as node,
    ):
        await node.create_subscription(Marker, "/rx200/markers", got.append, qos=reliable(64))

        def run() -> tuple[np.ndarray, int]:
            env = gym.make("uniros/Rx200Reach-v0", robot=domain.uri)
            try:
                env.reset(seed=1)
                for _ in range(3):  # three 0.8 s action cycles: the step's markers are due again
                    env.step(env.action_space.sample())
                return np.array(env.unwrapped.goal), env.unwrapped._task_markers.published
            finally:
                env.close()

        goal, published = await asyncio.wait_for(asyncio.to_thread(run), 120)
        await asyncio.sleep(0.3)
    kinds = Counter(m.ns for m in got)
    assert {"goal", "ee", "bounds", "goal_box"} <= set(kinds), kinds
    assert 2 <= published <= 1 + 3 * 0.8 / MARKER_PERIOD_S + 1, published
    assert kinds["goal"] == published, (kinds, published)
    np.testing.assert_allclose(next(m for m in reversed(got) if m.ns == "goal").position, goal)
    ee = [m for m in got if m.ns == "ee"]
    assert all(m.header.frame_id == "world" and 0.05 < np.linalg.norm(m.position) < 0.7 for m in ee)
