"""A pytest plugin: a test marked ``serial`` runs with no other test beside it when the suite runs on several xdist
workers (the README's test command): the tests that hold real-time loops to their timing, and the tests that check
machine-wide state.

The workers share a readers-writer lock, two ``flock``ed files in the session's temporary folder: every other test
holds it shared, a serial test exclusively. A serial test takes the turnstile first, which every new shared holder
passes through, so that the other workers cannot keep the lock shared forever. Setup, call, teardown and reruns of a
test all run under its lock, and a worker keeps it across consecutive serial tests (the suite's conftest puts them in
one xdist group, so that they come one after the other). Outside xdist (one process) there is nothing to lock."""

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


_held: list[int] = []
"""The descriptors of the turnstile and the lock while this worker runs a block of serial tests."""


def _acquire(path: Path, how: int) -> int:
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, how)
    except BaseException:
        os.close(fd)
        raise
    return fd


@contextlib.contextmanager
def _flocked(path: Path, how: int) -> Iterator[None]:
    fd = _acquire(path, how)
    try:
        yield
    finally:
        os.close(fd)  # releases the lock


def _release() -> None:
    while _held:
        os.close(_held.pop())  # closing the descriptor releases its lock


def _serial(item: pytest.Item | None) -> bool:
    return item is not None and item.get_closest_marker("serial") is not None


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    folder = _lock_dir(item.config)
    if folder is None:
        yield
        return
    turnstile, lock = folder / "uniros-serial.turnstile", folder / "uniros-serial.lock"
    if _serial(item):
        # consecutive serial tests of this worker keep the lock between them: the other workers' tests, once they
        # are done, wait once for the whole block, not once per test
        if not _held:
            _held.append(_acquire(turnstile, fcntl.LOCK_EX))
            _held.append(_acquire(lock, fcntl.LOCK_EX))
        try:
            yield
        finally:
            if not _serial(nextitem):
                _release()
    else:
        with _flocked(turnstile, fcntl.LOCK_EX):
            pass
        with _flocked(lock, fcntl.LOCK_SH):
            yield
