"""A step whose wait is interrupted (Ctrl-C, a signal that raises in the agent's thread) while some replies are
taken and others still owed: the vector env closes at once, it does not wait out the call timeout for replies it
already took."""

from __future__ import annotations

import signal
import time
from typing import Any

import numpy as np
import pytest
from _children import children

from uniros_async.runtime import make_vec

CALL_TIMEOUT_S = 30.0


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def _cartpole_slow_on_1() -> Any:
    """A CartPole whose step sleeps 3 s on action 1 (a local class: cloudpickled by value into the worker)."""
    import gymnasium as gym

    class SlowOnOne(gym.Wrapper):
        def step(self, action: Any) -> Any:
            if int(action) == 1:
                time.sleep(3.0)
            return self.env.step(action)

    return SlowOnOne(gym.make("CartPole-v1"))


@pytest.mark.slow
def test_close_after_an_interrupted_step_wait_does_not_wait_for_taken_replies() -> None:
    venv = make_vec([_cartpole_slow_on_1] * 2, call_timeout_s=CALL_TIMEOUT_S)
    try:
        venv.reset(seed=0)
        old = signal.signal(signal.SIGALRM, _interrupt)
        try:
            # the first worker replies at once, the second sleeps 3 s: the interruption comes between the two
            venv.step_async(np.array([0, 1]))
            signal.setitimer(signal.ITIMER_REAL, 0.5)
            with pytest.raises(KeyboardInterrupt):
                venv.step_wait()
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, old)
    finally:
        t0 = time.monotonic()
        venv.close()
        took = time.monotonic() - t0
    assert took < CALL_TIMEOUT_S / 3, f"close() took {took:.1f} s after an interrupted step"
    assert children() == []
