"""``uniros bag record|info|play``: bags of a domain's topics, as ``ros2 bag`` (recorder.py, reader.py, player.py)."""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import sys
from typing import Any

__all__ = ["add_parser", "run"]


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``bag`` and its actions to the ``uniros`` parser."""
    bag: argparse.ArgumentParser = subparsers.add_parser("bag", help="record, inspect and play MCAP bags")
    actions = bag.add_subparsers(dest="action", required=True)
    rec = actions.add_parser(
        "record",
        help="record topics of a domain into an MCAP file",
        description="Record TOPICs (or, with none or --all, every topic, new ones included) of --domain or "
        "$UNIROS_DOMAIN into FILE until SIGINT/SIGTERM or --duration. Standard types are ROS 2 CDR.",
    )
    rec.add_argument("topics", nargs="*", help="topics to record (default: all)")
    rec.add_argument("-a", "--all", action="store_true", help="every topic (the default when none is named)")
    rec.add_argument("-o", "--output", required=True, metavar="FILE", help="the .mcap file to write")
    rec.add_argument("--domain", default=None, help="domain URI (default: $UNIROS_DOMAIN)")
    rec.add_argument("--duration", type=float, default=None, help="seconds to record (default: until stopped)")
    rec.add_argument("--clock", choices=("wall", "sim"), default="wall", help="log times: wall clock or /clock")
    rec.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd", help="chunks (default zstd)")
    rec.add_argument("--depth", type=int, default=100, help="reliable queue depth per topic (default 100)")
    rec.add_argument(
        "--nice",
        type=int,
        default=10,
        help="lower the recorder's priority by this much, so that on a busy machine it yields the CPU to the loops "
        "it records and drops (counted) instead (default 10; 0: not)",
    )
    info = actions.add_parser("info", help="topics, types, counts, time span and chunks of a bag")
    info.add_argument("file", help="the .mcap file")
    play = actions.add_parser(
        "play",
        help="publish a bag's messages into a domain",
        description="Publish FILE's messages on their topics at their log times. --clock sim also publishes the "
        "bag's time on /clock, as the domain's sim clock source.",
    )
    play.add_argument("file", help="the .mcap file")
    play.add_argument("--domain", default=None, help="domain URI (default: $UNIROS_DOMAIN)")
    play.add_argument("--topics", nargs="+", default=[], help="only these topics")
    play.add_argument("--rate", type=float, default=1.0, help="speed factor (default 1; 0 with --clock sim: max)")
    play.add_argument("--loop", action="store_true", help="start again at the end")
    play.add_argument("--clock", choices=("wall", "sim"), default="wall", help="pace on the wall clock or be /clock")
    play.add_argument("--wait-subscribers", type=int, default=0, help="first wait for N subscribers per topic")
    return bag


def run(args: argparse.Namespace) -> int:
    """Run a ``uniros bag`` command; returns the exit code.

    Raises:
        BagError: the bag cannot be read or written, a topic is not in the domain (named, with the closest).
    """
    if args.action == "info":
        from uniros_async.bag.reader import BagReader

        info = BagReader(args.file).info()
        print(info.format())
        return 1 if info.damage else 0
    if args.action == "record":
        from uniros_async.bag.recorder import RecordConfig, record

        config = RecordConfig(
            path=args.output,
            topics=[] if args.all else args.topics,
            domain=args.domain,
            duration_s=args.duration,
            clock=args.clock,
            depth=args.depth,
            compression=args.compression,
        )

        def started(topics: list[str]) -> None:
            print(f"# recording {len(topics)} topic(s) to {args.output}: {' '.join(topics)}", flush=True)

        if args.nice > 0:
            os.nice(args.nice)

        async def main_record() -> None:
            stop = asyncio.Event()
            loop = asyncio.get_running_loop()
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, stop.set)
            stats = await record(config, started=started, stop=stop)
            print(
                f"# wrote {stats.total_written} messages, {stats.file_bytes / 1e6:.3f} MB, dropped "
                f"{stats.total_dropped}{' ' + str(stats.dropped) if stats.dropped else ''}; writer thread CPU "
                f"{stats.thread_cpu_s:.2f} s",
                flush=True,
            )

        asyncio.run(main_record())
        return 0
    from uniros_async.bag.player import PlayConfig, play

    pconfig = PlayConfig(
        path=args.file,
        domain=args.domain,
        topics=args.topics,
        rate=args.rate,
        loop=args.loop,
        clock=args.clock,
        wait_subscribers=args.wait_subscribers,
    )

    async def main_play() -> int:
        task = asyncio.current_task()
        assert task is not None
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, task.cancel)
        try:
            return await play(pconfig)
        except asyncio.CancelledError:
            return -1

    n = asyncio.run(main_play())
    if n >= 0:
        print(f"# played {n} messages", file=sys.stderr)
    return 0
