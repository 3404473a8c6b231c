"""``uniros bench ros1`` runs end to end on a tiny configuration (real rosmaster, real rospy echo and client).

Only that it works and reports what it measured; the figures are the benchmark's job (docs/performance.md)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from uniros_async.bench.ros1_peers import ros1_missing
from uniros_async.bench.ros2_peers import skip_or_fail
from uniros_async.errors import ConfigError


@pytest.fixture(autouse=True)
def _needs_ros1() -> None:
    reason = ros1_missing()
    if reason is not None:
        skip_or_fail(reason)


def test_both_clients_are_timed_through_the_echo(tmp_path: Path) -> None:
    from uniros_async.bench.ros1 import Ros1BenchConfig, main

    out = tmp_path / "ros1.json"
    lines: list[str] = []
    records = main(Ros1BenchConfig(blocks=3, per_block=20, json_path=str(out), progress=False), log=lines.append)
    assert [r["client"] for r in records] == ["uniros", "rospy"]
    for r in records:
        assert r["count"] == 40 and r["lost"] == 0  # two counted blocks of 20; the warm-up block is left out
        assert 0 < r["min_us"] <= r["p50_us"] <= r["p99_us"] <= r["max_us"] and math.isfinite(r["p50_us"])
    assert json.loads(out.read_text()) == records
    assert "uniros / rospy" in lines[0]


def test_bad_settings_and_the_cli() -> None:
    from uniros_async.bench.ros1 import Ros1BenchConfig

    with pytest.raises(ConfigError, match="blocks must be >= 2"):
        Ros1BenchConfig(blocks=1)
    proc = subprocess.run(
        [sys.executable, "-m", "uniros_async.cli", "bench", "ros1", "--blocks", "2", "--per-block", "5"]
        + ["--no-progress"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert "rospy (queue_size=None)" in proc.stdout and "uniros / rospy" in proc.stdout
