"""The Ray backend's tests (tests/ray_netns), each module on a real multi-node Ray cluster in a network namespace.

Ray binds the host's own interface address even when told 127.0.0.1, so its test clusters run inside
``unshare --net`` with only ``lo`` up: this test runs each module of tests/ray_netns there, in a pytest of its own,
and fails with that run's output. Without Ray or ``unshare --net`` it skips saying what is needed;
``UNIROS_REQUIRE_RAY=1`` (CI) makes that a failure.
"""

from __future__ import annotations

import importlib.util
import os
import pathlib
import shutil
import subprocess
import sys

import pytest

HERE = pathlib.Path(__file__).resolve().parent
INNER = HERE.parent / "ray_netns"
MODULES = sorted(p.name for p in INNER.glob("test_*.py"))
ROOT = HERE.parent.parent


def _missing() -> str | None:
    """What the Ray tests need and this machine lacks, or None."""
    if importlib.util.find_spec("ray") is None:
        return "Ray is not installed: pip install -e '.[ray]'"
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return "the Ray tests need unshare (util-linux) and ip (iproute2) to run their cluster in a network namespace"
    probe = subprocess.run(["unshare", "--net", "--", "true"], capture_output=True, text=True, check=False)
    if probe.returncode != 0:
        return f"the Ray tests need `unshare --net` (root, or unprivileged user namespaces): {probe.stderr.strip()}"
    return None


@pytest.mark.slow
@pytest.mark.parametrize("module", MODULES)
def test_ray_module_in_a_network_namespace(module: str) -> None:
    missing = _missing()
    if missing is not None:
        if os.environ.get("UNIROS_REQUIRE_RAY") == "1":
            pytest.fail(f"UNIROS_REQUIRE_RAY=1: {missing}")
        pytest.skip(missing)
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    env = dict(os.environ, UNIROS_RAY_NETNS="1", PYTHONPATH=path)
    env.pop("RAY_ADDRESS", None)
    # hypothesis's plugin is left out: these modules don't use it, and loading it while Ray's threads run can hit
    # CPython 3.11's "AST constructor recursion depth mismatch" (python/cpython#106905) and fail the run at its end
    inner = (
        f"ip link set lo up && exec {sys.executable} -m pytest -q -p no:cacheprovider -p no:hypothesispytest"
        " -rs --tb=short"
        f" tests/ray_netns/{module}"
    )
    proc = subprocess.run(
        ["unshare", "--net", "--", "sh", "-c", inner],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
        check=False,
    )
    out = proc.stdout + proc.stderr
    failures = out.find("= FAILURES =") if "= FAILURES =" in out else out.find("= ERRORS =")
    shown = (out[failures : failures + 10000] + "\n...\n" if failures >= 0 else "") + out[-3000:]
    assert proc.returncode == 0, f"tests/ray_netns/{module} failed in its network namespace:\n{shown}"
    assert " passed" in out and "skipped" not in out, f"tests/ray_netns/{module}: not every test ran:\n{out[-4000:]}"
