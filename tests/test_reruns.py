"""tests/_reruns.py, run as a plugin of a pytest on two xdist workers with one rerun (as .ci/run runs the suite): the
failed first attempt of a test that passes on its rerun is printed at the end; a run without reruns prints no such
section, and neither does the same run without the plugin."""

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
"""


def run_suite(tmp_path: Path, *plugin: str, flaky: bool = True) -> str:
    suite = tmp_path / "suite"
    suite.mkdir()
    (suite / "test_flaky.py").write_text(SUITE)
    seen = tmp_path / "seen"
    if not flaky:
        seen.write_text("1")
    argv = [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", *plugin, "-n", "2", "--reruns", "1"]
    argv += ["--rootdir", str(suite), str(suite)]
    env = {**os.environ, "SEEN": str(seen), "PYTEST_ADDOPTS": ""}
    out = subprocess.run(argv, cwd=suite, env=env, capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout


def test_the_failed_attempt_of_a_rerun_is_printed(tmp_path: Path) -> None:
    out = run_suite(tmp_path, "-p", "_reruns")
    assert "2 passed, 1 rerun" in out, out
    summary = out.split("failures that passed on their rerun", 1)[1]
    assert "--- test_flaky.py::test_fails_once (call), its failed attempt:" in summary
    assert "AssertionError: only the first attempt fails" in summary
    assert "test_passes" not in summary


def test_nothing_is_printed_without_a_rerun(tmp_path: Path) -> None:
    out = run_suite(tmp_path, "-p", "_reruns", flaky=False)
    assert "2 passed" in out and "failures that passed on their rerun" not in out and "1 rerun" not in out, out


def test_without_the_plugin_the_failed_attempt_is_not_shown(tmp_path: Path) -> None:
    out = run_suite(tmp_path)
    assert "1 rerun" in out and "only the first attempt fails" not in out, out
