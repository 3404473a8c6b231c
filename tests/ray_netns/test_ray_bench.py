"""``uniros bench throughput --backend ray`` and ``uniros bench latency --backend ray`` on a real two-node Ray
cluster: the Ray rows beside the others, in one run, and the goal line; the latency scenario's envs placed by Ray;
``--repeat`` with Ray-placed rows, Ray-placed workers that outnumber their node's cores pinned round robin, and the
bench's own cluster started without the daemons it does not need.
Checks what the records say, never a figure's size (docs/performance.md)."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from typing import Any

import pytest

from uniros_async.bench import latency, throughput
from uniros_async.bench._ray_rows import QUIET_ENV, QUIET_SYSTEM_CONFIG, RAY_IMPLS

pytestmark = pytest.mark.usefixtures("nothing_left")


def test_the_ray_rows_run_beside_the_others_and_the_goal_line_is_printed(cluster: dict[str, Any]) -> None:
    lines: list[str] = []
    config = throughput.ThroughputBenchConfig(
        n_envs=(1,), steps=5, backend="ray", ray_address=cluster["address"], progress=False
    )
    records = throughput.main(config, log=lines.append)
    trivial = {r["impl"] for r in records if r["env"] == throughput.TRIVIAL_ID and not r.get("envs_in_turn")}
    assert trivial == set(throughput.IMPLS) | set(throughput._placed_impls()) | set(RAY_IMPLS)
    rx200 = {r["impl"] for r in records if r["env"] == throughput.ENV_ID}
    assert rx200 == set(throughput.IMPLS) | {"uniros-ray"}
    for r in records:
        if r["env"] == throughput.TRIVIAL_ID and r["impl"] in RAY_IMPLS:
            lo, hi = r["overhead_ci_us"]
            assert lo <= r["overhead_us"] <= hi and r["steps_per_s"] > 0
    text = "\n".join(lines)
    assert "CartPole-v1, N=1: Ray-placed worker over tcp" in text and "a Ray actor call per step" in text
    assert cluster["arm_id"][:12] in text or cluster["head_id"][:12] in text  # the nodes the rows ran on


def test_the_latency_scenario_runs_its_env_placed_by_ray(cluster: dict[str, Any]) -> None:
    lines: list[str] = []
    config = latency.LatencyBenchConfig(
        scenario="single",
        learners=("sb3-td3",),
        duration_s=3.0,
        learning_starts=2,
        backend="ray",
        ray_address=cluster["address"],
        progress=False,
        keep_cores_awake=False,
    )
    records = latency.main(config, log=lines.append)
    assert "--backend ray --ray-address" in "\n".join(lines)
    cycles = [r for r in records if r["env"] == "rx200 sim" and r["metric"] == "actuator_cycle"]
    assert len(cycles) == 1 and cycles[0]["count"] > 0, records


def test_repeat_runs_the_ray_placed_rows_beside_the_local_ones(
    cluster: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    from uniros_async.bench import _stepmeter

    monkeypatch.setattr(_stepmeter, "MAX_TIGHT_STEPS", 20)  # the interval's goal would take hundreds of steps
    lines: list[str] = []
    config = throughput.ThroughputBenchConfig(
        n_envs=(4,), steps=5, repeat=1, backend="ray", ray_address=cluster["address"], progress=False
    )
    records = throughput.main(config, log=lines.append)
    assert [(r["impl"], r["n_envs"], r["run"]) for r in records] == [("uniros", 4, 1), ("uniros-ray", 4, 1)]
    for r in records:
        assert r["bound_steps_per_s"] > 0 and r["bound_pct"] > 0 and 6 <= r["tight_steps"] <= 20
    assert "worker_cpu_ms" in records[0]  # local workers' CPU time is read here; a Ray node's is not
    assert "worker_cpu_ms" not in records[1]
    text = "\n".join(lines)
    assert "  4 uniros-ray   pin  " in text and "uniros-ray: workers placed by Ray there, over tcp" in text


def test_ray_placed_workers_that_outnumber_their_nodes_cores_are_pinned_round_robin(cluster: dict[str, Any]) -> None:
    """The slot each worker pins itself by is its rank among the vector env's workers on its own node."""
    import os

    from uniros_async.runtime import make_vec

    cpus = sorted(os.sched_getaffinity(0))  # every node of this cluster is this machine
    n = len(cpus) + 1
    arm = {"worker": {"ray": {"node_id": cluster["arm_id"], "num_cpus": 0}}}
    venv = make_vec([("CartPole-v1", arm)] * n, pad=False, backend="ray")
    try:
        venv.reset(seed=0)
        venv.step([0] * n)
        pinned = [w.info["pinned_cpu"] for w in venv._sup.workers]
        assert pinned == [cpus[i % len(cpus)] for i in range(n)]
        # their node runs on the agent's machine (its address is this machine's): the agent does not poll for their
        # replies, and takes them last sent first (Supervisor._take_replies)
        assert all(w.info["cores_shared"] and w.transport.spin_ns == 0 for w in venv._sup.workers)
        assert venv._sup._reply_rank == [n - 1 - i for i in range(n)]
    finally:
        venv.close()


def test_the_benchs_own_cluster_starts_without_the_daemons_it_does_not_need() -> None:
    """Without ``--ray-address`` the bench starts its own two-node cluster (``RayRows.start``): no log monitor, no
    autoscaler, and the system config and environment that keep its daemons' own work down reach them (read back
    from their command lines and environments, in a process of its own: this one is connected to the module's
    cluster); everything stopped at the end."""
    code = textwrap.dedent(
        r"""
        import base64, json, os, subprocess
        from uniros_async.bench._ray_rows import RayRows

        def tree(root):
            out = subprocess.run(["ps", "-eo", "pid=,ppid="], capture_output=True, text=True, check=True).stdout
            kids = {}
            for line in out.splitlines():
                pid, ppid = (int(x) for x in line.split())
                kids.setdefault(ppid, []).append(pid)
            found, todo = [], [root]
            while todo:
                more = kids.get(todo.pop(), [])
                found += more
                todo += more
            return found

        def read(path):
            try:
                with open(path, "rb") as f:
                    return f.read().replace(b"\0", b" ").decode(errors="replace")
            except OSError:
                return ""

        rows = RayRows()
        rows.start()
        try:
            procs = {p: (read(f"/proc/{p}/cmdline"), read(f"/proc/{p}/environ")) for p in tree(os.getpid())}
        finally:
            rows.close()
        configs = [a.split("--config_list=", 1)[1].split()[0] for a, _ in procs.values() if "--config_list=" in a]
        print(json.dumps({
            "commands": [a for a, _ in procs.values()],
            "configs": [json.loads(base64.b64decode(c)) for c in configs],
            "daemon_env": [e for a, e in procs.values() if "raylet/raylet" in a or "gcs/gcs_server" in a],
            "nodes": [rows.agent_node, rows.other_node],
        }))
        """
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr[-4000:]
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert all(got["nodes"]) and got["nodes"][0] != got["nodes"][1]
    commands = "\n".join(got["commands"])
    assert "gcs_server" in commands and commands.count("raylet/raylet") == 2
    assert "log_monitor.py" not in commands and "autoscaler/_private/monitor.py" not in commands
    assert got["configs"] and all(c.items() >= QUIET_SYSTEM_CONFIG.items() for c in got["configs"])
    # (the raylets start the dashboard and runtime env agents with theirs; an agent's own /proc environ is not
    # readable as such: its process title overwrites it)
    assert len(got["daemon_env"]) == 3 and all(
        f"{name}={value}" in env.split() for env in got["daemon_env"] for name, value in QUIET_ENV.items()
    )
