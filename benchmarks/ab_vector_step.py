"""The agent's side of a vector step, lean against general, in one process.

    python benchmarks/ab_vector_step.py [BLOCKS]

One `make_vec(["CartPole-v1"])` (one worker over shm) is stepped in alternating blocks of 2,000 steps two ways:

- `lean`: `UnirosVectorEnv.step` as it is (`Supervisor.send_steps_now` / `receive_steps_now`, returns' arrays made
  with positional dtypes);
- `general`: the step's earlier, general path (`b2dd1ed`), kept here as the baseline: the
  supervisor's general send and receive of that code (`_send_now`, a `_SentPending`-like object and its `result`,
  `_receive_now`: sets, a sort, the checks of any request) and the returns' arrays made with keyword dtypes. Only
  its common case is kept (every request goes and every reply is taken in this thread); anything else raises.

The worker, the env, the transport and the moment are the same for both, so the difference per block is the agent
code's own cost inside the loop, which this VM's hour-to-hour drift (about 1.5-2x) hides between separate runs.
Prints the median us per step of each and the median difference per block pair.
"""

from __future__ import annotations

import statistics
import sys
import time
from typing import Any

import numpy as np

from uniros_async.runtime.protocol import pack
from uniros_async.runtime.supervisor import LATER, Supervisor, _raise_unexpected
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


def _send_now(sup: Supervisor, messages: list[Any]) -> frozenset[int]:  # b2dd1ed's Supervisor._send_now
    for i, m in enumerate(messages):
        if m is not None:
            sup.workers[i].check_idle()
    if sup._loop.is_closed() or sup._orphans or not sup._lock.acquire(blocking=False):
        return frozenset()
    try:
        frames = [None if m is None else pack(m) for m in messages]
        sent: list[int] = []
        for i, frame in enumerate(frames):
            if frame is None:
                continue
            if not sup.workers[i].try_send_request(frame):
                break
            sent.append(i)
        return frozenset(sent)
    finally:
        sup._lock.release()


def _receive_now(
    sup: Supervisor, messages: list[Any], sent: frozenset[int], deadline: float, results: list[Any], decode: Any
) -> set[int]:  # b2dd1ed's Supervisor._receive_now
    rest = {i for i, m in enumerate(messages) if m is not None}
    if not sent or not sup._lock.acquire(blocking=False):
        return rest
    try:
        if sup._loop.is_closed() or sup._orphans:
            return rest
        for i in sorted(sent):
            w = sup.workers[i]
            op = messages[i].get("op")
            try:
                r = w.receive_reply_blocking(op, max(deadline - time.monotonic(), 0.0), decode)
            except Exception as exc:  # noqa: BLE001
                r = exc
            if r is LATER:
                break
            results[i] = r
            rest.discard(i)
        return rest
    finally:
        sup._lock.release()


class _Sent:  # b2dd1ed's _SentPending, its result() when every reply is taken in this thread
    def __init__(self, sup: Supervisor, messages: list[Any], sent: frozenset[int]) -> None:
        self._sup, self._messages, self._sent = sup, messages, sent
        self._results: list[Any] = [None] * len(messages)
        self._rest: set[int] | None = None

    def result(self, timeout: float | None = None, decode: Any = None) -> list[Any]:
        now = time.monotonic()
        end = None if timeout is None else now + timeout
        deadline = now + self._sup.call_timeout_s
        until = deadline if end is None else min(deadline, end)
        self._rest = _receive_now(self._sup, self._messages, self._sent, until, self._results, decode)
        if self._rest:
            raise RuntimeError("a reply could not be taken in this thread: the baseline keeps only the common case")
        return _raise_unexpected(self._results)


def general_step(venv: UnirosVectorEnv, actions: np.ndarray) -> Any:
    venv._check_open()
    msgs = venv._step_messages(actions, "next_step")
    sup = venv._sup
    pending = _Sent(sup, msgs, _send_now(sup, msgs))
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
