"""How long after a Ray node is lost the agent's step raises WorkerError, for docs/reliability.md.

Each trial adds a node to a local Ray cluster (the "arm PC", a resource of its own), makes a vector env of two
real-time rx200 envs (the wall clock, 10 Hz, the action cycle 0.8 s): one on the agent's node (over shm), one on the
new node (over our tcp); steps twice, then, while the third step is in flight (0.3 s into its 0.8 s action cycle, so
the other env's reply is still 0.5 s away), removes the node (``Cluster.remove_node(allow_graceful=False)``: its
raylet and every process Ray started there are SIGKILLed) from another thread. It prints the time from the kill to
the WorkerError the step raised (and checks that the error names the worker and its node), per trial and as a
summary, with how many of the errors say that the node is lost (the rest: the connection broke before the node's
actor reported why). ``--load K`` keeps K busy-looping processes (ordinary priority) running through the trials:
a host as loaded as a shared one at its busiest.

Run it in a network namespace (Ray binds the host's interfaces otherwise)::

    unshare --net -- sh -c 'ip link set lo up && python benchmarks/ray_lost_node.py --trials 10'
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from typing import Any

import numpy as np

RX = "uniros/Rx200Reach-v0"
ACTION_CYCLE_S = 0.8
KILL_AFTER_S = 0.3
OBJECT_STORE_BYTES = 80 * 1024 * 1024


def trial(cluster: Any, head_id: str, k: int) -> dict[str, Any]:
    """One node lost mid-step; its figures."""
    from uniros_async.errors import WorkerError
    from uniros_async.runtime import make_vec

    resource = f"lost_pc_{k}"
    node = cluster.add_node(num_cpus=2, resources={resource: 1}, object_store_memory=OBJECT_STORE_BYTES)
    cluster.wait_for_nodes()
    venv = make_vec(
        [
            (RX, {"worker": {"ray": {"node_id": head_id}}}),
            (RX, {"worker": {"ray": {"resources": {resource: 1}}}}),
        ],
        backend="ray",
        clock="wall",
        action_cycle_s=ACTION_CYCLE_S,
        call_timeout_s=30.0,
    )
    killed: list[float] = []

    def kill(at: float) -> None:
        time.sleep(max(0.0, at - time.monotonic()))
        killed.append(time.monotonic())
        cluster.remove_node(node, allow_graceful=False)

    try:
        venv.reset(seed=k)
        action = np.zeros((2, *venv.single_action_space.shape), np.float32)
        for _ in range(2):
            venv.step(action)
        killer = threading.Thread(target=kill, args=(time.monotonic() + KILL_AFTER_S,))
        killer.start()
        try:
            for _ in range(3):
                venv.step(action)
        except WorkerError as exc:
            raised = time.monotonic()
            error = exc
        else:
            raise AssertionError("three steps after the node was lost raised nothing")
        finally:
            killer.join()
        assert error.index == 1 and node.node_id[:12] in str(error), str(error)
        return {"trial": k, "kill_to_error_s": raised - killed[0], "error": str(error)}
    finally:
        venv.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=10)
    ap.add_argument("--json", default=None, metavar="PATH")
    ap.add_argument("--load", type=int, default=0, metavar="K", help="busy-looping processes meanwhile (default 0)")
    args = ap.parse_args()
    import ray
    from ray.cluster_utils import Cluster

    cluster = Cluster(
        initialize_head=True,
        head_node_args={"num_cpus": 2, "include_dashboard": False, "object_store_memory": OBJECT_STORE_BYTES},
    )
    rows = []
    burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.load)]
    try:
        ray.init(address=cluster.address, log_to_driver=False)
        head_id = ray.get_runtime_context().get_node_id()
        for k in range(args.trials):
            row = trial(cluster, head_id, k)
            rows.append(row)
            print(f"trial {k}: kill to WorkerError {row['kill_to_error_s'] * 1e3:.1f} ms: {row['error'][:160]}")
    finally:
        for p in burners:
            p.kill()
            p.wait()
        ray.shutdown()
        cluster.shutdown()
    ms = np.array([r["kill_to_error_s"] * 1e3 for r in rows])
    lost = sum("is lost" in r["error"] for r in rows)
    print(
        f"kill to WorkerError over {len(ms)} trials: median {np.median(ms):.1f} ms, min {ms.min():.1f}, "
        f"max {ms.max():.1f} (the action cycle: {ACTION_CYCLE_S * 1e3:.0f} ms); the node named lost in {lost} of "
        f"{len(rows)}, load {args.load}"
    )
    if args.json:
        with open(args.json, "w") as f:
            summary = {"action_cycle_s": ACTION_CYCLE_S, "kill_after_s": KILL_AFTER_S, "load": args.load}
            json.dump({**summary, "node_named_lost": lost, "trials": rows}, f, indent=1)


if __name__ == "__main__":
    main()
