"""tests/_reruns.py, run as a plugin of a pytest on two xdist workers with one rerun (as .ci/run runs the suite): the
failed first attempt of a test that was run again is printed at the end, with how its rerun ended; a run without
reruns prints no such section, and neither does the same run without the plugin."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

SUITE = """
import os
from pathlib import Path

def test_fails_once():
    seen = Path(os.environ["SEEN"])
    if not seen.exists():
        seen.write_text("1")
        assert os.environ["SEEN"] == "the second attempt", "only the first attempt fails"

def test_passes():
    assert os.environ["SEEN"]

def test_fails_twice():
    assert os.environ.get("NEVER") == "set", "every attempt fails"
"""


def run_suite(tmp_path: Path, *plugin: str, flaky: bool = True, select: str = "") -> str:
    suite = tmp_path / "suite"
    suite.mkdir()
    (suite / "test_flaky.py").write_text(SUITE)
    seen = tmp_path / "seen"
    if not flaky:
        seen.write_text("1")
    argv = [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", *plugin, "-n", "2", "--reruns", "1"]
    argv += ["--rootdir", str(suite), str(suite)] + (["-k", select] if select else [])
    env = {**os.environ, "SEEN": str(seen), "PYTEST_ADDOPTS": ""}
    out = subprocess.run(argv, cwd=suite, env=env, capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == (0 if select else 1), out.stdout + out.stderr  # 1: test_fails_twice
    return out.stdout


def test_the_failed_attempt_of_a_rerun_is_printed(tmp_path: Path) -> None:
    out = run_suite(tmp_path, "-p", "_reruns")
    assert "1 failed, 2 passed, 2 rerun" in out, out
    summary = out.split("failed attempts that were run again", 1)[1]
    assert "--- test_flaky.py::test_fails_once (call), its failed attempt (its rerun passed):" in summary
    assert "AssertionError: only the first attempt fails" in summary
    assert "--- test_flaky.py::test_fails_twice (call), its failed attempt (its rerun failed again):" in summary
    assert "test_passes" not in summary


def test_a_test_that_never_failed_is_not_printed(tmp_path: Path) -> None:
    out = run_suite(tmp_path, "-p", "_reruns", flaky=False)
    assert "1 failed, 2 passed, 1 rerun" in out and "failed attempts that were run again" in out, out
    assert "test_fails_once" not in out.split("failed attempts that were run again", 1)[1]  # it never failed


def test_without_the_plugin_the_failed_attempt_is_not_shown(tmp_path: Path) -> None:
    out = run_suite(tmp_path)
    assert "2 rerun" in out and "only the first attempt fails" not in out, out


def test_nothing_is_printed_without_a_rerun(tmp_path: Path) -> None:
    out = run_suite(tmp_path, "-p", "_reruns", flaky=False, select="not fails_twice")
    assert "2 passed in" in out and "failed attempts that were run again" not in out, out
