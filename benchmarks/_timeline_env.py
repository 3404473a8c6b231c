"""The env of ``step_timeline.py``: CartPole that never terminates (so that its own step count stays the agent's;
an autoreset step would not call ``step``), and that stamps, into a shared-memory table the script created, when
each step started and ended, when its reply was packed and when it was in the transport's ring. Imported in the
worker as ``"_timeline_env:TimelineCartPole-v0"`` (the worker finds this folder on the path it inherits from the
script, spawn); the stamps in the worker come from wrapping ``worker.pack_step_reply`` and
``ShmTransport.try_send`` there."""

from __future__ import annotations

import time
from multiprocessing import shared_memory
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.envs.classic_control.cartpole import CartPoleEnv

STEPS = 200_000
"""Rows of the stamp table: (step start, step end, reply packed, reply in the ring), ns of CLOCK_MONOTONIC, which
every process on the machine shares."""
ENV_ID = "_timeline_env:TimelineCartPole-v0"
_clock = time.perf_counter_ns


class TimelineCartPole(CartPoleEnv):
    def __init__(self, shm_name: str, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self._shm = shared_memory.SharedMemory(shm_name)  # the script created it and unlinks it
        self.stamps: np.ndarray = np.ndarray((STEPS, 4), np.int64, self._shm.buf)
        self.k = 0  # this step's row
        _stamp_the_reply(self)

    def step(self, action: Any) -> Any:
        t0 = _clock()
        obs, reward, _, truncated, info = super().step(action)
        t1 = _clock()
        self.k += 1
        if self.k <= STEPS:
            self.stamps[self.k - 1, :2] = (t0, t1)
        return obs, reward, False, truncated, info


def _stamp_the_reply(env: TimelineCartPole) -> None:
    import uniros_async.runtime.worker as worker
    from uniros_async.transports.shm import ShmTransport

    pack, try_send = worker.pack_step_reply, ShmTransport.try_send

    def stamped_pack(result: list[Any]) -> bytes:
        frame = pack(result)
        if env.k <= STEPS:
            env.stamps[env.k - 1, 2] = _clock()
        return frame

    def stamped_try_send(self: ShmTransport, frame: bytes) -> bool:
        sent = try_send(self, frame)
        if env.k <= STEPS:
            env.stamps[env.k - 1, 3] = _clock()
        return sent

    worker.pack_step_reply = stamped_pack  # type: ignore[assignment]
    ShmTransport.try_send = stamped_try_send  # type: ignore[method-assign]


gym.register("TimelineCartPole-v0", entry_point=TimelineCartPole, max_episode_steps=10**9)
