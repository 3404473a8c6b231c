"""ViewerServer: the Rerun viewer's gRPC proxy and web app, as a child process bound to one address.

The ``rerun`` program shipped in the rerun-sdk wheel serves the web viewer (its wasm app is inside the program) and a
gRPC proxy that loggers connect to; browsers open ``web_url``. The address is 127.0.0.1 unless the caller asks for
another with ``allow_remote=True``: the proxy has no authentication.
"""

from __future__ import annotations

import contextlib
import ctypes
import ipaddress
import json
import os
import signal
import socket
import subprocess
import time
import urllib.parse
from pathlib import Path
from types import TracebackType
from typing import IO

from uniros_async.view import ViewError

__all__ = ["ViewerServer", "die_with_parent", "rerun_program"]


def rerun_program() -> Path:
    """The ``rerun`` program of the installed rerun-sdk wheel.

    Raises:
        ViewError: rerun-sdk is not installed (the ``view`` extra).
    """
    try:
        import rerun_cli
    except ImportError as exc:
        raise ViewError("the view needs rerun-sdk: pip install 'uniros-async[view]'") from exc
    path = Path(rerun_cli.__file__).parent / "rerun"
    if not path.is_file():
        raise ViewError(f"rerun-sdk is installed without its viewer program (no {path})")
    return path


def die_with_parent() -> None:
    """In a child before its exec: a SIGKILL when its parent dies, so a killed view leaves no server or browser."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG


def _quiet_rerun_home(program: Path) -> Path:
    """A config home for the viewer's program in which its usage reports are off (``rerun analytics disable``, run
    once there), so the view sends nothing beyond this machine."""
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "uniros_async" / "rerun_home"
    config = base / "rerun" / "analytics.json"
    with contextlib.suppress(OSError, ValueError):
        if json.loads(config.read_text()).get("analytics_enabled") is False:
            return base
    base.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, XDG_CONFIG_HOME=str(base), XDG_DATA_HOME=str(base))
    done = subprocess.run([str(program), "analytics", "disable"], env=env, capture_output=True, text=True, timeout=30)
    if done.returncode != 0:
        raise ViewError(f"could not turn the viewer's usage reports off in {base}: {done.stderr.strip()}")
    return base


def _check_free(host: str, port: int, what: str) -> None:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds: TIME_WAIT is no owner
        try:
            s.bind((host, port))
        except OSError as exc:
            raise ViewError(
                f"the viewer's {what} port {port} on {host} is in use ({exc.strerror}); choose another with "
                f"--{'web-port' if what == 'web' else 'port'}"
            ) from exc


class ViewerServer:
    """Runs the viewer's server for the block (``with ViewerServer(...) as server``).

    Args:
        host: the address both ports bind (default loopback).
        grpc_port: where loggers connect (``grpc_url``).
        web_port: where browsers open the viewer (``web_url``).
        allow_remote: required for a host that is not a loopback address.
        memory_limit: how much the proxy buffers for late viewers (oldest data dropped past it).
        start_timeout_s: how long to wait for both ports to answer.

    Raises:
        ViewError: a non-loopback host without ``allow_remote``, a port in use, or a server that does not start
            (with its output).
    """

    def __init__(
        self,
        *,
        host: str = "127.0.0.1",
        grpc_port: int = 9876,
        web_port: int = 9090,
        allow_remote: bool = False,
        memory_limit: str = "1GiB",
        start_timeout_s: float = 20.0,
    ) -> None:
        try:
            addr = ipaddress.ip_address(host)
        except ValueError as exc:
            raise ViewError(f"viewer host: expected an IP address such as 127.0.0.1, got {host!r}") from exc
        if not addr.is_loopback and not allow_remote:
            raise ViewError(
                f"viewer host {host} is not a loopback address: the viewer has no authentication, so serving it "
                "beyond this machine needs --allow-remote"
            )
        for port in (grpc_port, web_port):
            if not 1 <= port <= 65535:
                raise ViewError(f"viewer port: expected 1..65535, got {port}")
        if grpc_port == web_port:
            raise ViewError(f"the viewer's gRPC and web ports must differ, both are {grpc_port}")
        self.host, self.grpc_port, self.web_port = host, grpc_port, web_port
        self.memory_limit, self.start_timeout_s = memory_limit, start_timeout_s
        self._proc: subprocess.Popen[bytes] | None = None
        self._log: IO[bytes] | None = None

    @property
    def _url_host(self) -> str:
        return f"[{self.host}]" if ":" in self.host else self.host

    @property
    def grpc_url(self) -> str:
        """The proxy's URL for loggers (``rr.connect_grpc``) and the viewer."""
        return f"rerun+http://{self._url_host}:{self.grpc_port}/proxy"

    @property
    def web_url(self) -> str:
        """The page a browser opens: the web viewer, connected to the proxy."""
        return f"http://{self._url_host}:{self.web_port}/?url={urllib.parse.quote(self.grpc_url, safe='')}"

    def start(self) -> None:
        """Start the server and wait until both ports answer."""
        program = rerun_program()
        _check_free(self.host, self.grpc_port, "gRPC")
        _check_free(self.host, self.web_port, "web")
        import tempfile

        self._log = tempfile.TemporaryFile()  # no name: nothing is left behind, whatever ends this process
        home = _quiet_rerun_home(program)
        env = dict(os.environ, XDG_CONFIG_HOME=str(home), XDG_DATA_HOME=str(home))
        # the viewer's own program: serving is all it does here, and a child keeps its threads off the caller's
        self._proc = subprocess.Popen(
            [
                str(program),
                "--serve-web",
                "--bind",
                self.host,
                "--port",
                str(self.grpc_port),
                "--web-viewer-port",
                str(self.web_port),
                "--hide-welcome-screen",
                "--server-memory-limit",
                self.memory_limit,
            ],  # fmt: skip
            stdin=subprocess.DEVNULL,
            stdout=self._log,
            stderr=self._log,
            env=env,
            preexec_fn=die_with_parent,
        )
        deadline = time.monotonic() + self.start_timeout_s
        waiting = [self.grpc_port, self.web_port]
        while waiting:
            rc = self._proc.poll()
            if rc is not None:
                out = self._output()
                self.close()
                raise ViewError(f"the viewer's server exited with {rc}: {out}")
            if time.monotonic() > deadline:
                out = self._output()
                self.close()
                raise ViewError(
                    f"the viewer's server did not open port(s) {waiting} in {self.start_timeout_s} s: {out}"
                )
            try:
                with socket.create_connection((self.host, waiting[0]), timeout=0.5):
                    waiting.pop(0)
            except OSError:
                time.sleep(0.05)

    def _output(self) -> str:
        if self._log is None:
            return ""
        self._log.seek(0)
        return self._log.read().decode(errors="replace")[-2000:].strip()

    def close(self) -> None:
        """Stop the server (SIGTERM, then SIGKILL after 5 s)."""
        proc, self._proc = self._proc, None
        if proc is not None and proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(5.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if self._log is not None:
            self._log.close()
            self._log = None

    def __enter__(self) -> ViewerServer:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
