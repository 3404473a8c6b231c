"""The served arm both hostile tests attack (``uniros robot serve rx200 ...``, a real process) and what they check
after the attacks: the process is there, the legitimate stream is whole, the log stays rate-limited."""

from __future__ import annotations

import os
import select
import subprocess
import sys
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

RSS_LIMIT = 64 * 1024 * 1024
"""How much the server's RSS may grow while 1,000 connections are held."""


def start_serve(args: list[str], log: Path, *, unset: tuple[str, ...]) -> tuple[subprocess.Popen[str], str]:
    """Start ``uniros robot serve rx200 ARGS`` (its stderr into ``log``, ``unset`` removed from its environment);
    the process and the first line it printed.

    Raises:
        AssertionError: it printed nothing within 60 s (the message holds its log).
    """
    env = {**os.environ, "PYTHONPATH": os.getcwd() + os.pathsep + os.environ.get("PYTHONPATH", "")}
    for name in unset:
        env.pop(name, None)
    with open(log, "w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "uniros_async.cli", "robot", "serve", "rx200", *args],
            stdout=subprocess.PIPE,
            stderr=err,
            stdin=subprocess.DEVNULL,
            text=True,
            env=env,
        )
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], 60)
    line = proc.stdout.readline().strip() if ready else ""
    if not line:
        stop_serve(proc)
        raise AssertionError(f"robot serve {' '.join(args)} did not start; its log:\n{log.read_text()[-2000:]}")
    return proc, line


def stop_serve(proc: subprocess.Popen[str]) -> None:
    """Terminate ``proc`` (killed after 10 s) and close its stdout."""
    proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    if proc.stdout is not None:
        proc.stdout.close()


def host_port(uri: str) -> tuple[str, int]:
    """The host and port of ``uri`` (``tcp://`` or ``http://``)."""
    parts = urlsplit(uri)
    assert parts.hostname is not None and parts.port is not None
    return parts.hostname, parts.port


def check_stream_whole(seqs: list[int], n_before: int) -> None:
    """The legitimate joint states' header seqs: more came after the attacks (``n_before``), none lost or out of
    order."""
    assert len(seqs) > n_before, "joint states stopped flowing after the attacks"
    gaps = [(a, b) for a, b in zip(seqs, seqs[1:], strict=False) if b != a + 1]
    assert not gaps, f"legitimate joint states lost or reordered: {gaps[:5]} (of {len(seqs)})"


def check_rss_bounded(reports: dict[str, Any], server: str) -> None:
    """The ``server``'s RSS grew by less than ``RSS_LIMIT`` during every attack of ``reports``."""
    for what, r in reports.items():
        assert r.peak_rss_growth < RSS_LIMIT, f"{what}: {server} RSS grew {r.peak_rss_growth / 2**20:.1f} MiB"


def check_log_rate_limited(log: Path, elapsed_s: float, reports: dict[str, Any]) -> None:
    """At most one log line a second per listener (and per domain) over ``elapsed_s``: far fewer than the thousands
    of refusals. Prints ``reports`` and the count."""
    lines = [ln for ln in log.read_text().splitlines() if ln.strip()]
    assert len(lines) <= 4 * elapsed_s + 20, f"{len(lines)} log lines in {elapsed_s:.0f} s:\n" + "\n".join(lines[:40])
    sys.stdout.write(
        "\n".join(f"{k}: {v}" for k, v in reports.items()) + f"\nlog lines: {len(lines)} in {elapsed_s:.1f} s\n"
    )
