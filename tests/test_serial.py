"""tests/_serial.py, run as a plugin of a pytest on two xdist workers: a test marked ``serial`` overlaps no other test,
while the unmarked ones do run side by side; without the plugin the same serial tests overlap others."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

SUITE = """
import json, os, time
import pytest

def record(name):
    start = time.monotonic()
    time.sleep(0.3)
    with open(os.environ["SPANS"], "a") as f:
        f.write(json.dumps([name, start, time.monotonic()]) + "\\n")

@pytest.mark.parametrize("i", range(8))
def test_beside(i):
    record(f"beside{i}")

@pytest.mark.serial
@pytest.mark.parametrize("i", range(4))
def test_alone(i):
    record(f"alone{i}")
"""


def run_suite(tmp_path: Path, *plugin: str) -> list[tuple[str, float, float]]:
    suite = tmp_path / "suite"
    suite.mkdir()
    (suite / "test_spans.py").write_text(SUITE)
    spans = tmp_path / "spans.jsonl"
    argv = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *plugin]
    argv += ["-n", "2", "--dist", "load", "-o", "markers=serial", "--rootdir", str(suite), str(suite)]
    env = {**os.environ, "SPANS": str(spans), "PYTEST_ADDOPTS": ""}
    out = subprocess.run(argv, cwd=suite, env=env, capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 0, out.stdout + out.stderr
    return [tuple(json.loads(line)) for line in spans.read_text().splitlines()]  # type: ignore[misc]


def overlaps(spans: list[tuple[str, float, float]]) -> set[tuple[str, str]]:
    return {(a[0], b[0]) for a in spans for b in spans if a[0] < b[0] and a[1] < b[2] and b[1] < a[2]}


def test_a_serial_test_runs_alone_and_the_others_side_by_side(tmp_path: Path) -> None:
    spans = run_suite(tmp_path, "-p", "_serial")
    assert len(spans) == 12
    pairs = overlaps(spans)
    assert not [p for p in pairs if any(n.startswith("alone") for n in p)], sorted(pairs)
    assert [p for p in pairs if all(n.startswith("beside") for n in p)], "the two workers never ran side by side"


def test_without_the_plugin_serial_tests_overlap_others(tmp_path: Path) -> None:
    spans = run_suite(tmp_path)
    assert [p for p in overlaps(spans) if any(n.startswith("alone") for n in p)], spans
