"""Suite-wide settings."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

EXTENSION_DIR = Path(__file__).resolve().parent / "extension"
"""Holds ``acme_arms``, a user's own package that registers an arm, a placement and task ids from outside
uniros_async; tests name it as ``"acme_arms:..."``, which imports it when the test runs (never at collection, so
the ids other tests sweep at collection stay the built-in ones)."""
if str(EXTENSION_DIR) not in sys.path:
    sys.path.append(str(EXTENSION_DIR))

TESTS_DIR = Path(__file__).resolve().parent
"""Holds ``rig``, the suite's own test rig. Processes the tests start run its modules as ``python -m rig.<module>``
(inside network namespaces too), so tests/ goes on their ``PYTHONPATH``."""
TREE_DIR = TESTS_DIR.parent
"""The checkout under test. It goes first on the started processes' ``PYTHONPATH`` too, so that they import this
tree's ``uniros_async`` even when another checkout is the one ``pip install -e`` points at."""
_pythonpath = [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
os.environ["PYTHONPATH"] = os.pathsep.join(
    [str(TREE_DIR), str(TESTS_DIR)] + [p for p in _pythonpath if p not in (str(TREE_DIR), str(TESTS_DIR))]
)


@pytest.fixture(scope="session", autouse=True)
def _sb3_logs_in_the_sessions_tmp(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """SB3 makes a log folder for every ``learn`` without a tensorboard folder: ``$SB3_LOGDIR``, or else a new
    ``/tmp/SB3-<time>`` each time, which nothing removes (the training tests alone left 20 a run). Point it into
    pytest's own temporary folder, which pytest prunes (worker processes inherit the variable)."""
    old = os.environ.get("SB3_LOGDIR")
    os.environ["SB3_LOGDIR"] = str(tmp_path_factory.mktemp("sb3_logs"))
    yield
    if old is None:
        os.environ.pop("SB3_LOGDIR", None)
    else:
        os.environ["SB3_LOGDIR"] = old


# Two plugins of the suite's own, their hooks made this conftest's by importing them (tests/test_serial.py and
# tests/test_reruns.py run each as a plugin of its own):
# - tests/_reruns.py: the failed first attempt of each test that passed on its rerun, printed at the end of the run;
# - tests/_serial.py: a test marked ``serial`` runs with no other test beside it on the suite's xdist workers.
from _reruns import pytest_runtest_logreport, pytest_terminal_summary  # noqa: E402, F401
from _serial import pytest_configure, pytest_runtest_protocol  # noqa: E402, F401

SERIAL_FILES = {
    # real-time env loops whose cycles the test holds near their period
    "bag/test_bag_bench.py",
    "bench/test_latency.py",
    # real-time arms beside a learner, held to their action-cycle timing
    "training/test_alongside.py",
    "training/test_realtime_training.py",
    "training/test_training_cli.py",
    # compares the whole of /dev/shm before and after, which another test's processes may write to meanwhile
    "transports/test_shm.py",
    # each case runs a Ray cluster, holds it to a time (a lost node reported within one action cycle) and checks
    # afterwards that no Ray process is left, machine-wide
    "runtime/test_runtime_ray.py",
}
"""Test files (under tests/) whose every test runs alone; the comments say why."""


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if not item.path.is_relative_to(TESTS_DIR):
            continue
        path = item.path.relative_to(TESTS_DIR).as_posix()
        if path in SERIAL_FILES:
            item.add_marker(pytest.mark.serial)
        if item.get_closest_marker("serial") is not None:
            item.add_marker(pytest.mark.xdist_group("serial"))  # one after the other, on one worker
