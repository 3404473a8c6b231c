"""The agent's side of a vector step, lean against general, in one process.

    python benchmarks/ab_vector_step.py [BLOCKS]

One `make_vec(["CartPole-v1"])` (one worker over shm) is stepped in alternating blocks of 2,000 steps two ways:

- `lean`: `UnirosVectorEnv.step` as it is (`Supervisor.send_steps_now` / `receive_steps_now`, returns' arrays made
  with positional dtypes);
- `general`: the path the step took before the tenth session, still the one `submit_all` takes: `_send_now`, a
  `_SentPending` and its `result` (`_receive_now`), and the returns' arrays made with keyword dtypes.

The worker, the env, the transport and the moment are the same for both, so the difference per block is the agent
code's own cost inside the loop, which this VM's hour-to-hour drift (about 1.5-2x) hides between separate runs.
Prints the median us per step of each and the median difference per block pair. Recorded in docs/performance.md.
"""

from __future__ import annotations

import statistics
import sys
import time
from typing import Any

import numpy as np

from uniros_async.runtime.supervisor import _SentPending
from uniros_async.runtime.vector import UnirosVectorEnv, _Returns, make_vec

STEPS = 2000


class _KeywordReturns(_Returns):
    """``_Returns`` as it was: every array made with its dtype given by keyword."""

    def __init__(self, venv: UnirosVectorEnv) -> None:
        n = venv.num_envs
        space: Any = venv.single_observation_space
        self.venv = venv
        self.rewards = np.empty(n, dtype=np.float64)
        self.terminated = np.empty(n, dtype=np.bool_)
        self.truncated = np.empty(n, dtype=np.bool_)
        self.obs = np.empty((n, *space.shape), dtype=space.dtype)
        self.raw = self.obs.data.cast("B")
        self.row_bytes = self.obs.nbytes // n


def general_step(venv: UnirosVectorEnv, actions: np.ndarray) -> Any:
    venv._check_open()
    msgs = venv._step_messages(actions, "next_step")
    sup = venv._sup
    pending = _SentPending(sup, msgs, sup._send_now(msgs))
    returns = _KeywordReturns(venv)
    return returns.finish(venv._collect(pending.result(decode=returns.decode)))


def main() -> None:
    blocks = int(sys.argv[1]) if len(sys.argv) > 1 else 30
    venv = make_vec(["CartPole-v1"], pad=False)
    try:
        venv.reset(seed=0)
        actions = np.zeros(1, dtype=np.int64)
        ways = {"lean": lambda: venv.step(actions), "general": lambda: general_step(venv, actions)}
        for way in ways.values():  # warm both
            for _ in range(STEPS):
                way()
        per_step: dict[str, list[float]] = {name: [] for name in ways}
        for b in range(blocks):
            order = list(ways.items()) if b % 2 else list(reversed(ways.items()))
            for name, way in order:
                t0 = time.perf_counter_ns()
                for _ in range(STEPS):
                    way()
                per_step[name].append((time.perf_counter_ns() - t0) / STEPS / 1e3)
        for name, us in per_step.items():
            print(f"{name:8s} median {statistics.median(us):6.2f} us/step  (min {min(us):6.2f})")
        diff = [g - lean for g, lean in zip(per_step["general"], per_step["lean"], strict=True)]
        faster = sum(d > 0 for d in diff)
        gain = statistics.median(diff)
        print(f"general - lean per block pair: median {gain:5.2f} us, lean faster in {faster} of {blocks}")
    finally:
        venv.close()


if __name__ == "__main__":
    main()
