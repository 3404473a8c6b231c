"""``uniros camera serve SOURCE``: a V4L2/UVC device or a video file as a camera node (camera/capture.py)."""

from __future__ import annotations

import argparse
import asyncio
import signal
import sys
from typing import Any

__all__ = ["add_parser", "run"]


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``camera`` and its actions to the ``uniros`` parser."""
    camera: argparse.ArgumentParser = subparsers.add_parser("camera", help="cameras on the bus")
    actions = camera.add_subparsers(dest="action", required=True)
    serve = actions.add_parser(
        "serve",
        help="publish a V4L2/UVC device or a video file as Image (OpenCV; the camera extra)",
        description="Publish the frames of SOURCE (/dev/videoN, a device index, or a video file) as Image on "
        "NAMESPACE/CAMERA/color/image_raw until SIGINT/SIGTERM (or the file's end). Joins --domain or "
        "$UNIROS_DOMAIN; with neither, opens a domain of its own and prints `export UNIROS_DOMAIN=...`.",
    )
    serve.add_argument("source", help="/dev/videoN, a device index such as 0, or a video file")
    serve.add_argument("--domain", default=None, help="domain URI (default: $UNIROS_DOMAIN, else a new one)")
    serve.add_argument("--namespace", default="", help="namespace of the topic, e.g. /rx200 (default: none)")
    serve.add_argument("--camera", default="camera", help="camera name in the topic (default camera)")
    serve.add_argument("--rate", type=float, default=None, help="frames per second (default: the source's own)")
    serve.add_argument("--width", type=int, default=None, help="resize to this width (with --height)")
    serve.add_argument("--height", type=int, default=None, help="resize to this height (with --width)")
    serve.add_argument("--loop", action="store_true", help="start a video file again at its end")
    return camera


def _print_ready(uri: str, topic: str) -> None:
    print(f"export UNIROS_DOMAIN={uri}", flush=True)
    print(f"# publishing {topic}; watch it with: uniros topic hz {topic}", flush=True)


def run(args: argparse.Namespace) -> int:
    """Run a ``uniros camera`` command; returns the exit code.

    Raises:
        ConfigError: bad settings. CameraError: the source cannot be opened (named).
    """
    from uniros_async.camera.capture import CaptureConfig, serve_camera

    config = CaptureConfig(
        source=args.source,
        namespace=args.namespace,
        camera=args.camera,
        rate_hz=args.rate,
        width=args.width,
        height=args.height,
        loop=args.loop,
    )

    async def main() -> None:
        task = asyncio.current_task()
        assert task is not None
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, task.cancel)
        await serve_camera(config, domain=args.domain, on_ready=_print_ready)

    try:
        asyncio.run(main())
    except asyncio.CancelledError:  # SIGINT/SIGTERM: an orderly stop
        pass
    except BaseExceptionGroup as group:  # a task group's wrapping of one clear error: that error
        first: BaseException = group
        while isinstance(first, BaseExceptionGroup):
            first = first.exceptions[0]
        raise first from None
    sys.stdout.flush()
    return 0
