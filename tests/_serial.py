"""A pytest plugin: a test marked ``serial`` runs with no other test beside it when the suite runs on several xdist
workers (the README's test command): the tests that hold real-time loops to their timing, and the tests that check
machine-wide state.

The workers share a readers-writer lock, two ``flock``ed files in the session's temporary folder: every other test
holds it shared, a serial test exclusively. A serial test takes the turnstile first, which every new shared holder
passes through, so that the other workers cannot keep the lock shared forever. Setup, call, teardown and reruns of a
test all run under its lock. Outside xdist (one process) there is nothing to lock."""

from __future__ import annotations

import contextlib
import fcntl
import os
from collections.abc import Iterator
from pathlib import Path

import pytest


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", "serial: runs with no other test beside it when the suite runs on several xdist workers"
    )


def _lock_dir(config: pytest.Config) -> Path | None:
    """The folder every worker of this session shares, or None outside xdist."""
    if not hasattr(config, "workerinput"):
        return None
    return Path(config._tmp_path_factory.getbasetemp()).parent  # type: ignore[attr-defined]


@contextlib.contextmanager
def _flocked(path: Path, how: int) -> Iterator[None]:
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, how)
        yield
    finally:
        os.close(fd)  # releases the lock


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    folder = _lock_dir(item.config)
    if folder is None:
        yield
        return
    turnstile, lock = folder / "uniros-serial.turnstile", folder / "uniros-serial.lock"
    if item.get_closest_marker("serial") is not None:
        with _flocked(turnstile, fcntl.LOCK_EX), _flocked(lock, fcntl.LOCK_EX):
            yield
    else:
        with _flocked(turnstile, fcntl.LOCK_EX):
            pass
        with _flocked(lock, fcntl.LOCK_SH):
            yield
