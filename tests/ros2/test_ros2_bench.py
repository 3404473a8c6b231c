"""``uniros bench ros2`` runs end to end on a tiny configuration (our participant and a real rclpy client, both
through a real rclpy echo). Only that it works and reports what it measured; the figures are the benchmark's job
(docs/performance.md)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from uniros_async.errors import ConfigError


def test_both_clients_are_timed_through_the_echo(tmp_path: Path) -> None:
    from uniros_async.bench.ros2 import Ros2BenchConfig, main

    out = tmp_path / "ros2.json"
    lines: list[str] = []
    records = main(Ros2BenchConfig(blocks=3, per_block=20, json_path=str(out), progress=False), log=lines.append)
    assert [r["client"] for r in records] == ["uniros", "rclpy"]
    for r in records:
        assert r["count"] == 40 and r["lost"] == 0  # two counted blocks of 20; the warm-up block left out
        assert 0 < r["min_us"] <= r["p50_us"] <= r["p99_us"] <= r["max_us"] and math.isfinite(r["p50_us"])
    assert json.loads(out.read_text()) == records
    assert "uniros / rclpy" in lines[0] and "network namespace" in lines[0]


def test_bad_settings_and_the_cli(tmp_path: Path) -> None:
    from uniros_async.bench.ros2 import Ros2BenchConfig

    with pytest.raises(ConfigError, match="blocks must be >= 2"):
        Ros2BenchConfig(blocks=1)
    with pytest.raises(ConfigError, match="domain_id"):
        Ros2BenchConfig(domain_id=300)
    out = tmp_path / "cli.json"
    proc = subprocess.run(
        [sys.executable, "-m", "uniros_async.cli", "bench", "ros2", "--blocks", "2", "--per-block", "5"]
        + ["--no-progress", "--json", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert "rclpy (spin_once)" in proc.stdout and "uniros / rclpy" in proc.stdout
    assert [r["client"] for r in json.loads(out.read_text())] == ["uniros", "rclpy"]
