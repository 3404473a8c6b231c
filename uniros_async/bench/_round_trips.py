"""What ``uniros bench ros1`` and ``uniros bench ros2`` share: round trips of our client and a ROS peer in turns.

Each bench starts two processes of a ROS client library (rospy, rclpy): an echo that republishes ``/uniros_ping``
on ``/uniros_pong`` and the peer's own ping on its pong, and a client that answers ``go N`` on stdin with one JSON
line of N timed round trips (``_peer_loop.answer_go_lines``). Our client and that peer then take turns in blocks
(``blocks`` of ``per_block`` round trips each), so both meet the same moments of the machine's load; the first
block of each is warm-up and not counted. A round trip carries its token in ``header.frame_id``, as a rospy
publisher renumbers ``header.seq``.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import subprocess
import time
from collections.abc import Awaitable, Callable, Iterator, Mapping, Sequence
from typing import Any

from uniros_async.bench.common import progress_counter, report
from uniros_async.errors import ConfigError
from uniros_async.stats import summary

__all__ = ["Blocks", "RoundTripBenchConfig", "open_peers", "our_block", "print_table", "records_of", "take_turns"]

NAMES = ("waist", "shoulder", "elbow", "wrist_angle", "wrist_rotate", "gripper", "left_finger", "right_finger")
"""The rx200's 8 joints: the ``sensor_msgs`` joint state every round trip carries."""
MAX_LOST = 10
"""Round trips a block may lose before the bench gives up."""

Blocks = tuple[list[int], int]
"""Round-trip times in ns, and the round trips lost."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class RoundTripBenchConfig:
    blocks: int = 11
    """Blocks per client, taken in turns; the first of each is warm-up."""
    per_block: int = 500
    json_path: str | None = None
    progress: bool = True
    timeout_s: float = 2.0
    """How long one round trip may take before it counts as lost."""

    def __post_init__(self) -> None:
        if self.blocks < 2 or self.per_block < 1:
            raise ConfigError(f"blocks must be >= 2 and per_block >= 1, got {self.blocks}, {self.per_block}")


async def our_block(
    pub: Any, receive: Callable[[], Awaitable[Any]], make: Callable[[str], Any], n: int, seq0: int, timeout_s: float
) -> Blocks:
    """``n`` timed round trips of our client: publish ``make(token)`` on ``pub``, then ``receive()`` until its echo.

    Args:
        pub: our publisher of the ping topic (``publish``, ``topic``).
        receive: the next message of the pong topic.
        make: the ping message that carries ``token`` in ``header.frame_id``.
        n: round trips to time.
        seq0: the token before the first of this block (tokens never repeat within a run).
        timeout_s: how long one round trip may take before it counts as lost.

    Raises:
        RuntimeError: more than ``MAX_LOST`` round trips got no echo.
    """
    times: list[int] = []
    lost = 0
    seq = seq0
    while len(times) < n:
        seq += 1
        token = str(seq)
        msg = make(token)
        t0 = time.perf_counter_ns()
        pub.publish(msg)
        try:
            async with asyncio.timeout(timeout_s):
                while (await receive()).header.frame_id != token:
                    pass  # a late echo of a lost one
        except TimeoutError:
            lost += 1
            if lost > MAX_LOST:
                raise RuntimeError(
                    f"more than {MAX_LOST} round trips over {pub.topic} got no echo within {timeout_s} s"
                ) from None
            continue
        times.append(time.perf_counter_ns() - t0)
    return times, lost


def _peer_block(proc: subprocess.Popen[str], peer: str, n: int, timeout_s: float) -> Blocks:
    """``n`` timed round trips of the peer's client process (``go N``, one JSON line back)."""
    from uniros_async.bench.ros1_peers import wait_for_line

    assert proc.stdin is not None
    proc.stdin.write(f"go {n}\n")
    proc.stdin.flush()
    out = json.loads(wait_for_line(proc, "{", timeout_s=n * timeout_s + 30.0))
    if len(out["ns"]) < n:
        raise RuntimeError(f"the {peer} client lost more than {MAX_LOST} round trips (got {len(out['ns'])} of {n})")
    return list(out["ns"]), int(out["lost"])


async def take_turns(
    cfg: RoundTripBenchConfig,
    client: subprocess.Popen[str],
    peer: str,
    *,
    pub: Any,
    receive: Callable[[], Awaitable[Any]],
    make: Callable[[str], Any],
) -> dict[str, Blocks]:
    """Alternate blocks of our client (``our_block`` with ``pub``, ``receive`` and ``make``) and of the ``peer``
    ``client`` process; the counted results of each.

    Returns:
        ``{"uniros": ..., peer: ...}``: every counted block's times joined, and the round trips lost.
    """
    results: dict[str, Blocks] = {"uniros": ([], 0), peer: ([], 0)}
    step = progress_counter(2 * cfg.blocks, cfg.progress, f"{peer} bench", "block")
    seq = 0
    for b in range(cfg.blocks):
        mine = await our_block(pub, receive, make, cfg.per_block, seq, cfg.timeout_s)
        seq += cfg.per_block + mine[1]
        step(1)
        theirs = await asyncio.to_thread(_peer_block, client, peer, cfg.per_block, cfg.timeout_s)
        step(1)
        if b == 0:
            continue  # warm-up: connections, discovery and caches
        for key, (t, n_lost) in (("uniros", mine), (peer, theirs)):
            prev_t, prev_lost = results[key]
            results[key] = (prev_t + t, prev_lost + n_lost)
    step(0, done=True)
    return results


@contextlib.contextmanager
def open_peers(
    argv: Sequence[str], env: Mapping[str, str], *, ready_timeout_s: float
) -> Iterator[subprocess.Popen[str]]:
    """Start ``argv + ["echo"]`` and ``argv + ["client"]``, each until its ``ready``; yields the client.

    Both are killed when the block ends.
    """
    from uniros_async.bench.ros1_peers import kill_process, wait_for_line

    procs: list[subprocess.Popen[str]] = []
    try:
        for mode in ("echo", "client"):
            proc = subprocess.Popen(
                [*argv, mode],
                env=dict(env),
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
                text=True,
                bufsize=1,
            )
            procs.append(proc)
            wait_for_line(proc, "ready", timeout_s=ready_timeout_s)
        yield procs[1]
    finally:
        for proc in procs:
            kill_process(proc)


def records_of(results: Mapping[str, Blocks]) -> list[dict[str, Any]]:
    """One record per client, in ``results``' order: the summary of its times in us, its count and losses."""
    records: list[dict[str, Any]] = []
    for key, (times, lost) in results.items():
        s = summary([t / 1e3 for t in times])
        records.append(
            {"client": key, **{f"{k}_us": v for k, v in s.items() if k != "count"}, "count": s["count"], "lost": lost}
        )
    return records


def print_table(
    config: RoundTripBenchConfig,
    records: list[dict[str, Any]],
    labels: Mapping[str, str],
    *,
    title: str,
    ratio_note: str = "",
    log: Callable[[str], None],
) -> None:
    """Log the table of ``records`` (ours first, the peer's second) and write them to ``config.json_path``.

    Args:
        config: the run's blocks and sizes, for the heading.
        records: from ``records_of``.
        labels: each client's name in the table.
        title: what went round (the message, through what echo).
        ratio_note: said after the ratio of the medians, in parentheses.
        log: where the table goes.
    """
    width = max(len(v) for v in labels.values()) + 2
    ours, theirs = records[0]["client"], records[1]["client"]
    lines = [
        f"{title}, {config.blocks - 1} blocks of {config.per_block} per client, taken in turns "
        "(first block of each: warm-up)",
        f"{'client':<{width}}{'p50 us':>10}{'p90 us':>10}{'p99 us':>10}{'IQR us':>10}{'lost':>6}{'count':>7}",
        "-" * (width + 53),
    ]
    for r in records:
        lines.append(
            f"{labels[r['client']]:<{width}}{r['p50_us']:>10.1f}{r['p90_us']:>10.1f}{r['p99_us']:>10.1f}"
            f"{r['iqr_us']:>10.1f}{r['lost']:>6}{r['count']:>7}"
        )
    ratio = records[0]["p50_us"] / records[1]["p50_us"]
    lines.append(f"median round trip: {ours} / {theirs} = {ratio:.2f}" + (f" ({ratio_note})" if ratio_note else ""))
    report("\n".join(lines), records, config.json_path, log)
