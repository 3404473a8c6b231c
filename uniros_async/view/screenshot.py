"""Screenshots of a page in headless Chromium, over the DevTools protocol (``python -m uniros_async.view.screenshot``).

Rerun's web viewer draws with WebGL; headless Chromium gives it SwiftShader's software GL
(``--use-angle=swiftshader --enable-unsafe-swiftshader``). The browser is a child process with a profile of its
own in a temporary directory, removed with it.

    python -m uniros_async.view.screenshot http://127.0.0.1:9090/?url=... -o view.png --wait 20
"""

from __future__ import annotations

import argparse
import base64
import json
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from uniros_async.view import ViewError
from uniros_async.view.server import die_with_parent

__all__ = ["Browser", "headless_chromium"]

CHROMIUM_FLAGS = (
    "--headless=new",
    "--no-sandbox",  # root in a container has no user namespace sandbox
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",  # no name resolves: nothing beyond this host
    "--remote-debugging-address=127.0.0.1",
    "--remote-debugging-port=0",
)


class Browser:
    """One page of a headless Chromium, driven over its DevTools websocket."""

    def __init__(self, ws: Any) -> None:
        self._ws = ws
        self._id = 0

    def call(self, method: str, timeout_s: float = 30.0, **params: Any) -> dict[str, Any]:
        """Call a DevTools ``method`` and return its result.

        Raises:
            ViewError: the browser answered with an error, or not within ``timeout_s``.
        """
        self._id += 1
        self._ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise ViewError(f"headless Chromium did not answer {method} within {timeout_s} s")
            reply = json.loads(self._ws.recv(timeout=left))
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise ViewError(f"headless Chromium: {method}: {reply['error']}")
                result: dict[str, Any] = reply.get("result", {})
                return result

    def open(self, url: str) -> None:
        """Navigate to ``url``."""
        self.call("Page.navigate", url=url)

    def screenshot(self) -> bytes:
        """The page as PNG bytes."""
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])


@contextmanager
def headless_chromium(width: int = 1280, height: int = 720, start_timeout_s: float = 30.0) -> Iterator[Browser]:
    """A headless Chromium for the block (Debian's ``chromium``); closed, profile and all, after it.

    Raises:
        ViewError: no ``chromium`` program, or it did not open its DevTools port within ``start_timeout_s``.
    """
    from websockets.sync.client import connect

    program = shutil.which("chromium") or shutil.which("chromium-browser")
    if program is None:
        raise ViewError("no chromium program: install Debian's chromium package")
    profile = Path(tempfile.mkdtemp(prefix="uniros_chromium_"))
    proc = subprocess.Popen(
        [program, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}", "about:blank"],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        preexec_fn=die_with_parent,
    )
    try:
        port_file = profile / "DevToolsActivePort"
        deadline = time.monotonic() + start_timeout_s
        while not (port_file.exists() and len(port_file.read_text().split()) >= 2):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise ViewError(f"chromium did not open its DevTools port within {start_timeout_s} s")
            time.sleep(0.1)
        port = port_file.read_text().split()[0]
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json", timeout=10) as r:
            pages = [t for t in json.load(r) if t.get("type") == "page"]
        if not pages:
            raise ViewError("headless Chromium opened no page")
        with connect(pages[0]["webSocketDebuggerUrl"], max_size=None, open_timeout=10) as ws:
            yield Browser(ws)
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        shutil.rmtree(profile, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    """Open URL, wait, and write one screenshot per ``-o`` (``--every`` seconds apart)."""
    p = argparse.ArgumentParser(prog="python -m uniros_async.view.screenshot", description=__doc__)
    p.add_argument("url")
    p.add_argument("-o", "--output", action="append", required=True, help="a PNG to write (repeat for more)")
    p.add_argument("--wait", type=float, default=20.0, help="seconds before the first screenshot (default 20)")
    p.add_argument("--every", type=float, default=3.0, help="seconds between screenshots (default 3)")
    p.add_argument("--size", default="1280x720", help="window size WxH (default 1280x720)")
    args = p.parse_args(argv)
    w, h = (int(v) for v in args.size.split("x"))
    with headless_chromium(w, h) as browser:
        browser.open(args.url)
        time.sleep(args.wait)
        for i, out in enumerate(args.output):
            if i:
                time.sleep(args.every)
            Path(out).write_bytes(browser.screenshot())
            print(f"# {out}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
