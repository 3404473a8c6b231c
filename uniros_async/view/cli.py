"""``uniros view``: a domain's arms live, or a bag, in Rerun's web viewer served on this machine."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import signal
import threading
from typing import Any

__all__ = ["add_parser", "run"]


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``view`` to the ``uniros`` parser."""
    view: argparse.ArgumentParser = subparsers.add_parser(
        "view",
        help="show a domain's arms live, or a bag, in the browser (Rerun's web viewer)",
        description="Serve Rerun's web viewer on HOST (127.0.0.1 by default) and draw the arms of --domain live, "
        "or every arm of --bag with a time slider: the arms posed from their joint states, markers, camera frames "
        "and commanded against measured joint positions. Open the printed URL in a browser.",
    )
    src = view.add_mutually_exclusive_group()
    src.add_argument("--domain", default=None, help="domain URI (default: $UNIROS_DOMAIN)")
    src.add_argument("--bag", default=None, metavar="FILE", help="an MCAP bag to replay instead")
    view.add_argument("--host", default="127.0.0.1", help="the address to serve on (default 127.0.0.1)")
    view.add_argument(
        "--allow-remote", action="store_true", help="allow a --host that is not loopback (the viewer has no login)"
    )
    view.add_argument("--port", type=int, default=9876, help="the viewer's gRPC port (default 9876)")
    view.add_argument("--web-port", type=int, default=9090, help="the web viewer's port (default 9090)")
    view.add_argument("--duration", type=float, default=None, help="seconds to serve (default: until stopped)")
    view.add_argument("--arm-wait", type=float, default=5.0, help="seconds to wait for an arm in the domain")
    return view


def _wait(stop: threading.Event, duration_s: float | None) -> None:
    stop.wait(duration_s)


def run(args: argparse.Namespace) -> int:
    """Run ``uniros view``; returns the exit code.

    Raises:
        ViewError: no arm in the domain or the bag, a port in use, a non-loopback host without --allow-remote.
        BagError: the file is not a bag.
    """
    from uniros_async.view.server import ViewerServer

    if args.bag is not None:
        from uniros_async.bag import BagReader

        BagReader(args.bag)  # not a bag: its error before any server starts
    if args.domain is None and args.bag is None and not os.environ.get("UNIROS_DOMAIN"):
        from uniros_async.view import ViewError

        raise ViewError("uniros view: give --domain URI or --bag FILE (or set $UNIROS_DOMAIN)")
    server = ViewerServer(host=args.host, grpc_port=args.port, web_port=args.web_port, allow_remote=args.allow_remote)
    with server:
        from uniros_async.view.feed import open_recording, view_bag, view_domain

        print(f"# the view: {server.web_url}", flush=True)
        if args.bag is not None:
            stop = threading.Event()
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, lambda *_: stop.set())
            rec = open_recording(server.grpc_url, f"bag {os.path.basename(args.bag)}")
            scene = view_bag(args.bag, rec)
            rec.flush()
            drawn = {t: n for t, n in scene.counts.items() if t != "not drawn"}
            arms = ", ".join(sorted(a for a, g in scene.arms.items() if g is not None)) or "none"
            print(f"# drew {sum(drawn.values())} messages of {len(drawn)} topic(s); arms: {arms}", flush=True)
            _wait(stop, args.duration)
            return 0
        rec = open_recording(server.grpc_url, f"domain {args.domain or os.environ['UNIROS_DOMAIN']}")

        async def live() -> None:
            loop = asyncio.get_running_loop()
            me = asyncio.current_task()
            assert me is not None
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, me.cancel)
            with contextlib.suppress(asyncio.CancelledError):  # SIGINT/SIGTERM: the view ends
                await view_domain(
                    args.domain,
                    rec,
                    duration_s=args.duration,
                    arm_wait_s=args.arm_wait,
                    started=lambda topics: print(f"# drawing {' '.join(topics)}", flush=True),
                )

        asyncio.run(live())
        rec.flush()
    return 0
