"""Scaling figures for docs/scaling.md: N env workers placed by Ray on a second node, stepped by one agent.

For N = 1, 2, 4, 8 copies of the rx200 reach env in accelerated turn-based mode, placed by Ray on a node other than
the agent's (our tcp between them), the agent steps random actions back to back and this prints per N:

- aggregate env steps/s and the time per vector step;
- per-env CPU: the workers' CPU time (user + system, read from /proc: the nodes share this host) per env step, and
  the agent's own CPU time per vector step;
- bandwidth: observation bytes x env steps/s (the reply's payload; the action and framing add ~100 B a step);

and once, the learner's load: the time of one TD3 gradient update (batch 256, 256x256 MLP, torch on one CPU
thread), so updates/s one core sustains.

Run it in a network namespace (Ray binds the host's interfaces otherwise)::

    unshare --net -- sh -c 'ip link set lo up && python benchmarks/scaling_ray.py --json out.json'
"""

from __future__ import annotations

import argparse
import json
import os
import time
from typing import Any

import numpy as np

ENV_ID = "uniros/Rx200Reach-v0"
ENV_KW: dict[str, Any] = {"turn_based": True, "max_episode_steps": 10**9}
CLK = os.sysconf("SC_CLK_TCK")


def _cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / CLK  # utime, stime


def _row(n: int, node: str, steps: int) -> dict[str, Any]:
    from uniros_async.runtime import make_vec

    where = {"worker": {"ray": {"node_id": node, "num_cpus": 0}}}
    venv = make_vec([(ENV_ID, where)] * n, backend="ray", **ENV_KW)
    try:
        venv.reset(seed=0)
        rng = np.random.default_rng(0)
        actions = [rng.uniform(-1, 1, venv.action_space.shape).astype(np.float32) for _ in range(steps + 20)]
        for a in actions[:20]:
            venv.step(a)
        pids = [p for p in venv.pids if p is not None]
        w0 = sum(_cpu_s(p) for p in pids)
        a0 = time.process_time()
        t0 = time.perf_counter()
        for a in actions[20:]:
            obs, *_ = venv.step(a)
        wall = time.perf_counter() - t0
        agent = time.process_time() - a0
        workers = sum(_cpu_s(p) for p in pids) - w0
        obs_bytes = int(np.asarray(obs).nbytes // n)
    finally:
        venv.close()
    rate = n * steps / wall
    return {
        "n_envs": n,
        "steps_per_s": round(rate, 1),
        "vector_step_ms": round(wall / steps * 1e3, 3),
        "worker_cpu_ms_per_env_step": round(workers / (n * steps) * 1e3, 3),
        "agent_cpu_ms_per_vector_step": round(agent / steps * 1e3, 3),
        "obs_bytes": obs_bytes,
        "obs_bandwidth_kB_s": round(obs_bytes * rate / 1e3, 1),
    }


def _learner_update_ms() -> float:
    import gymnasium as gym
    import torch
    from stable_baselines3 import TD3

    import uniros_async  # noqa: F401  (registers the ids)

    torch.set_num_threads(1)
    env = gym.make(ENV_ID, clock="sim")
    try:
        model = TD3("MlpPolicy", env, batch_size=256, learning_starts=0, device="cpu", verbose=0, seed=0)
        model.learn(300)  # fills the buffer (and warms up)
        t0 = time.perf_counter()
        model.train(gradient_steps=100, batch_size=256)
        return (time.perf_counter() - t0) / 100 * 1e3
    finally:
        env.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--n-envs", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    import ray
    from ray.cluster_utils import Cluster

    head = {"num_cpus": 2, "include_dashboard": False, "object_store_memory": 80 * 1024 * 1024}
    cluster = Cluster(initialize_head=True, head_node_args=head)
    try:
        other = cluster.add_node(num_cpus=2, object_store_memory=80 * 1024 * 1024)
        ray.init(address=cluster.address)
        rows = [_row(n, other.node_id, args.steps) for n in args.n_envs]
        ray.shutdown()
    finally:
        cluster.shutdown()
    update_ms = _learner_update_ms()
    out = {"cores": os.cpu_count(), "rows": rows, "td3_update_ms": round(update_ms, 2)}
    for r in rows:
        print(r)
    print(f"TD3 update (batch 256, 256x256, 1 thread): {update_ms:.2f} ms -> {1e3 / update_ms:.0f} updates/s")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
