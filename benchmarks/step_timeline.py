"""Where one vector step's time goes, piece by piece: `python benchmarks/step_timeline.py [STEPS] [RUNS]`.

One `make_vec` of a CartPole (one worker over shm) is stepped STEPS times (20,000 by default) back to back, after
2,000 steps of warm-up, RUNS times (1 by default; each run a fresh worker). Both processes stamp the moments of
each step with CLOCK_MONOTONIC, which they share: the agent around its own pieces (wrapped methods of the vector
env and the supervisor), the worker's env around its step and, through wrapped functions, after packing the reply
and after putting it in the ring (`_timeline_env.py`). Prints the median and quartiles of each piece. The wrappers
cost a little themselves (~0.2 us each), so the pieces add up to a bit more than an unwrapped step; the bare step
of the same env in this process is printed for the overhead. Not a benchmark of record: the tool to find out what
to work on next.
"""

from __future__ import annotations

import sys
import time
from multiprocessing import shared_memory
from typing import Any

import _timeline_env
import gymnasium as gym
import numpy as np

from uniros_async.runtime import make_vec
from uniros_async.runtime import vector as vector_module

WARM = 2_000
_clock = time.perf_counter_ns


def _run(steps: int) -> dict[str, np.ndarray]:
    shm = shared_memory.SharedMemory(create=True, size=_timeline_env.STEPS * 4 * 8)
    try:
        worker_t = np.ndarray((_timeline_env.STEPS, 4), np.int64, shm.buf)
        venv = make_vec([(_timeline_env.ENV_ID, {"shm_name": shm.name})], pad=False)
        agent_t = np.zeros((steps, 6), np.int64)  # start, messages built, sent, decoding, decoded, received
        row = [0]
        try:
            sup = venv._sup
            messages, send, receive = venv._step_messages, sup.send_steps_now, sup.receive_steps_now
            decode_into = vector_module.unpack_step_reply_into

            def stamped_messages(actions: Any, autoreset: str) -> Any:
                out = messages(actions, autoreset)
                agent_t[row[0], 1] = _clock()
                return out

            def stamped_send(msgs: Any) -> int:
                sent = send(msgs)
                agent_t[row[0], 2] = _clock()
                return sent

            def stamped_decode(frame: Any, out: Any, head: bytes) -> Any:
                agent_t[row[0], 3] = _clock()
                got = decode_into(frame, out, head)
                agent_t[row[0], 4] = _clock()
                return got

            def stamped_receive(msgs: Any, sent: int, decode: Any) -> Any:
                got = receive(msgs, sent, decode)
                agent_t[row[0], 5] = _clock()
                return got

            venv._step_messages = stamped_messages  # type: ignore[method-assign]
            sup.send_steps_now = stamped_send  # type: ignore[method-assign]
            sup.receive_steps_now = stamped_receive  # type: ignore[method-assign]
            vector_module.unpack_step_reply_into = stamped_decode
            venv.reset(seed=0)
            action = np.zeros(1, np.int64)
            for _ in range(WARM):
                venv.step(action)
            ends = np.zeros(steps, np.int64)
            for k in range(steps):
                row[0] = k
                agent_t[k, 0] = _clock()
                venv.step(action)
                ends[k] = _clock()
        finally:
            vector_module.unpack_step_reply_into = decode_into
            venv.close()
        w = worker_t[WARM : WARM + steps].copy()
    finally:
        shm.close()
        shm.unlink()
    start, built, sent, decoding, decoded, received = agent_t.T
    env0, env1, packed, in_ring = w.T
    return {
        "agent: actions -> request packed": built - start,
        "agent: request into the ring": sent - built,
        "worker: notices it, unpacks, calls step": env0 - sent,
        "the env's step": env1 - env0,
        "worker: returns, info, packs the reply": packed - env1,
        "worker: reply into the ring": in_ring - packed,
        "agent: notices the reply": decoding - in_ring,
        "agent: reply into the vector returns": decoded - decoding,
        "agent: back out of the supervisor": received - decoded,
        "agent: infos, returns": ends - received,
        "the whole step": ends - start,
    }


def _bare_us(steps: int) -> float:
    env = gym.make("CartPole-v1")
    env.reset(seed=0)
    times = np.zeros(steps)
    for k in range(steps):
        t0 = time.perf_counter()
        _, _, terminated, truncated, _ = env.step(0)
        times[k] = time.perf_counter() - t0
        if terminated or truncated:
            env.reset()
    env.close()
    return float(np.median(times)) * 1e6


def main() -> None:
    steps = int(sys.argv[1]) if len(sys.argv) > 1 else 20_000
    runs = int(sys.argv[2]) if len(sys.argv) > 2 else 1
    for run in range(runs):
        pieces = _run(steps)
        bare = _bare_us(steps)
        print(f"run {run + 1}: {steps} steps; median (p25-p75) us")
        for name, ns in pieces.items():
            us = ns / 1e3
            p25, p50, p75 = np.percentile(us, [25, 50, 75])
            print(f"  {name:<42} {p50:7.2f} ({p25:.2f}-{p75:.2f})")
        whole = float(np.median(pieces["the whole step"])) / 1e3
        print(f"  the bare CartPole step in this process: {bare:.2f} us; the whole step over it: {whole - bare:.2f} us")


if __name__ == "__main__":
    main()
