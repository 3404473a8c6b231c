"""``uniros bench throughput --backend ray`` and ``uniros bench latency --backend ray`` on a real two-node Ray
cluster: the Ray rows beside the others, in one run, and the goal line; the latency scenario's envs placed by Ray.
Checks what the records say, never a figure's size (docs/performance.md)."""

from __future__ import annotations

from typing import Any

import pytest

from uniros_async.bench import latency, throughput
from uniros_async.bench._ray_rows import RAY_IMPLS

pytestmark = pytest.mark.usefixtures("nothing_left")


def test_the_ray_rows_run_beside_the_others_and_the_goal_line_is_printed(cluster: dict[str, Any]) -> None:
    lines: list[str] = []
    config = throughput.ThroughputBenchConfig(
        n_envs=(1,), steps=5, backend="ray", ray_address=cluster["address"], progress=False
    )
    records = throughput.main(config, log=lines.append)
    trivial = {r["impl"] for r in records if r["env"] == throughput.TRIVIAL_ID and not r.get("envs_in_turn")}
    assert trivial == set(throughput.IMPLS) | set(RAY_IMPLS)
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
