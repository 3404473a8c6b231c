"""Real ROS 1 parts for the ROS benches and the tests: a rosmaster and rospy scripts run as subprocesses by the
system Python.

ROS 1 (Noetic, or Debian's own packages) lives in the system interpreter, not in ours: ``ros1_python()`` names it
(``$UNIROS_ROS1_PYTHON``, default ``/usr/bin/python3``) and ``rosmaster_bin()`` the master (``$UNIROS_ROSMASTER``,
default ``/usr/bin/rosmaster``). ``requires_ros1`` skips a test when either is missing, saying what to install
(under ``UNIROS_REQUIRE_ROS=1``, as ``.ci/run`` sets it, such a test runs and fails instead)::

    @requires_ros1
    def test_x(ros_master: str, tmp_path: Path) -> None:
        with rospy_process(PEER, "echo", master_uri=ros_master, tmp_path=tmp_path) as proc: ...

Every process started here is killed and reaped by the context manager that started it.
"""

from __future__ import annotations

import contextlib
import functools
import os
import select
import signal
import socket
import subprocess
import time
import weakref
import xmlrpc.client
from collections.abc import Iterator
from pathlib import Path
from typing import Any

__all__ = [
    "ROS1_INSTALL_HINT",
    "kill_process",
    "open_rosmaster",
    "open_rosmaster_process",
    "ros1_missing",
    "ros1_python",
    "ros_env",
    "rosmaster_bin",
    "rospy_process",
    "start_rospy",
    "wait_for_line",
]

ROS1_INSTALL_HINT = (
    "apt-get install python3-rospy python3-rosmaster python3-sensor-msgs python3-std-msgs python3-trajectory-msgs"
)
_line_buffers: weakref.WeakKeyDictionary[subprocess.Popen[str], bytearray] = weakref.WeakKeyDictionary()
_ROS1_MODULES = "rospy, genpy, genmsg, sensor_msgs.msg, std_msgs.msg, trajectory_msgs.msg"


def ros1_python() -> str:
    """The interpreter that can ``import rospy``: ``$UNIROS_ROS1_PYTHON``, default ``/usr/bin/python3``."""
    return os.environ.get("UNIROS_ROS1_PYTHON", "/usr/bin/python3")


def rosmaster_bin() -> str:
    """The ROS 1 master executable: ``$UNIROS_ROSMASTER``, default ``/usr/bin/rosmaster``."""
    return os.environ.get("UNIROS_ROSMASTER", "/usr/bin/rosmaster")


@functools.cache
def ros1_missing() -> str | None:
    """Why the ROS 1 tests cannot run (a skip reason naming what to install), or None when they can."""
    master, python = rosmaster_bin(), ros1_python()
    if not os.access(master, os.X_OK):
        return f"no ROS 1 master at {master} ($UNIROS_ROSMASTER); install it: {ROS1_INSTALL_HINT}"
    if not os.access(python, os.X_OK):
        return f"no ROS 1 Python at {python} ($UNIROS_ROS1_PYTHON); install it: {ROS1_INSTALL_HINT}"
    try:
        probe = subprocess.run(
            [python, "-c", f"import {_ROS1_MODULES}"], capture_output=True, text=True, timeout=60, check=False
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"{python} could not import rospy ({exc}); install it: {ROS1_INSTALL_HINT}"
    if probe.returncode != 0:
        last = probe.stderr.strip().splitlines()[-1:] or ["?"]
        return f"{python} cannot import {_ROS1_MODULES} ({last[0]}); install them: {ROS1_INSTALL_HINT}"
    return None


def __getattr__(name: str) -> Any:
    # ``requires_ros1``, a pytest mark, made on first use: the benchmarks use this module without pytest, and
    # without probing for ROS 1 when it is imported
    if name == "requires_ros1":
        import pytest

        if os.environ.get("UNIROS_REQUIRE_ROS") == "1":  # .ci/run: ROS 1 must be there; a test without it fails
            return pytest.mark.skipif(False, reason="UNIROS_REQUIRE_ROS=1: ROS 1 must be installed")
        return pytest.mark.skipif(ros1_missing() is not None, reason=ros1_missing() or "")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def ros_env(master_uri: str, *, home: str | os.PathLike[str] | None = None) -> dict[str, str]:
    """A copy of ``os.environ`` with the variables a ROS 1 process needs: the master URI, ``ROS_HOSTNAME`` on
    loopback, and ``ROS_HOME`` / ``ROS_LOG_DIR`` under ``home`` (default: a folder in the system temp dir), so no
    test writes to ``~/.ros``."""
    if home is None:
        home = Path(os.environ.get("TMPDIR", "/tmp")) / f"uniros_ros_home_{os.getuid()}"
    home = Path(home)
    (home / "log").mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env.update(
        ROS_MASTER_URI=master_uri,
        ROS_HOSTNAME="127.0.0.1",
        ROS_HOME=str(home),
        ROS_LOG_DIR=str(home / "log"),
        PYTHONUNBUFFERED="1",
    )
    env.pop("ROS_IP", None)
    # The system Python must not see our virtualenv's site-packages (numpy ABI, etc.).
    env.pop("PYTHONPATH", None)
    env.pop("PYTHONHOME", None)
    return env


def kill_process(proc: subprocess.Popen[str], *, grace_s: float = 3.0) -> None:
    """Stop ``proc``: SIGINT (rospy and rosmaster shut down cleanly on it), SIGKILL after ``grace_s``; then reap it."""
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(signal.SIGINT)
        try:
            proc.wait(grace_s)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                proc.kill()
    with contextlib.suppress(subprocess.TimeoutExpired):
        proc.wait(10.0)
    for stream in (proc.stdout, proc.stderr, proc.stdin):
        if stream is not None:
            stream.close()


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _master_answers(uri: str) -> bool:
    class _Transport(xmlrpc.client.Transport):
        def make_connection(self, host: str) -> object:  # type: ignore[override]
            conn = super().make_connection(host)
            conn.timeout = 1.0
            return conn

    try:
        with xmlrpc.client.ServerProxy(uri, transport=_Transport()) as proxy:
            reply: Any = proxy.getSystemState("/uniros_probe")
            code = reply[0]
    except (OSError, xmlrpc.client.Error):
        return False
    return bool(code == 1)


@contextlib.contextmanager
def open_rosmaster_process(
    tmp_path: str | os.PathLike[str], *, timeout_s: float = 10.0
) -> Iterator[tuple[subprocess.Popen[str], str]]:
    """Run ``rosmaster --core`` on a free loopback port until the block ends; yields (process, URI) once
    ``getSystemState`` answers (within ``timeout_s``). Raises RuntimeError if it does not come up."""
    home = Path(tmp_path) / "ros_home"
    last_log = ""
    for _attempt in range(3):  # the free port can be taken between our probe and rosmaster's bind
        port = _free_port()
        uri = f"http://127.0.0.1:{port}/"
        log_path = Path(tmp_path) / f"rosmaster_{port}.log"
        with open(log_path, "w") as log:
            proc = subprocess.Popen(
                [rosmaster_bin(), "--core", "-p", str(port)],
                env=ros_env(uri, home=home),
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                text=True,
            )
        try:
            deadline = time.monotonic() + timeout_s
            while proc.poll() is None and time.monotonic() < deadline and not _master_answers(uri):
                time.sleep(0.05)
            if proc.poll() is None and _master_answers(uri):
                yield proc, uri
                return
            last_log = log_path.read_text()[-2000:]
        finally:
            kill_process(proc)
    raise RuntimeError(f"rosmaster did not come up within {timeout_s} s; its log:\n{last_log}")


@contextlib.contextmanager
def open_rosmaster(tmp_path: str | os.PathLike[str], *, timeout_s: float = 10.0) -> Iterator[str]:
    """``open_rosmaster_process`` yielding only the URI ("http://127.0.0.1:PORT/")."""
    with open_rosmaster_process(tmp_path, timeout_s=timeout_s) as (_, uri):
        yield uri


def start_rospy(
    script_path: str | os.PathLike[str],
    *args: str,
    master_uri: str,
    tmp_path: str | os.PathLike[str],
) -> subprocess.Popen[str]:
    """Start ``ros1_python() script_path *args`` with ``ros_env(master_uri)``; stdout is a text pipe (the scripts
    print a few status lines), stderr goes to ``tmp_path/<script>_<pid>.stderr``. Prefer ``rospy_process``, which
    also kills it."""
    with open(Path(tmp_path) / f"{Path(script_path).stem}_{time.monotonic_ns()}.stderr", "w") as stderr:
        return subprocess.Popen(  # the child keeps its own copy of the stderr file
            [ros1_python(), str(script_path), *args],
            env=ros_env(master_uri, home=Path(tmp_path) / "ros_home"),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=stderr,
            text=True,
        )


@contextlib.contextmanager
def rospy_process(
    script_path: str | os.PathLike[str],
    *args: str,
    master_uri: str,
    tmp_path: str | os.PathLike[str],
) -> Iterator[subprocess.Popen[str]]:
    """``start_rospy`` for the length of the block; the process is killed and reaped when the block ends."""
    proc = start_rospy(script_path, *args, master_uri=master_uri, tmp_path=tmp_path)
    try:
        yield proc
    finally:
        kill_process(proc)


def wait_for_line(proc: subprocess.Popen[str], prefix: str, *, timeout_s: float = 10.0) -> str:
    """Read ``proc``'s stdout until a line starting with ``prefix`` (returned without the newline); lines before it
    are skipped. Raises TimeoutError after ``timeout_s`` or RuntimeError if the process ends first.

    Reads the pipe's file descriptor directly (the text wrapper's read-ahead would hide lines from select), so use
    only this to read a ``start_rospy`` process's stdout. Blocking: from async code use ``asyncio.to_thread``.
    """
    assert proc.stdout is not None
    fd = proc.stdout.fileno()
    buf = _line_buffers.setdefault(proc, bytearray())
    deadline = time.monotonic() + timeout_s
    while True:
        while (nl := buf.find(b"\n")) >= 0:
            line = buf[:nl].decode(errors="replace")
            del buf[: nl + 1]
            if line.startswith(prefix):
                return line
        left = deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError(f"no line starting with {prefix!r} from {proc.args!r} within {timeout_s} s")
        ready, _, _ = select.select([fd], [], [], left)
        if not ready:
            continue
        chunk = os.read(fd, 65536)
        if not chunk:
            code = proc.wait(5)
            raise RuntimeError(f"{proc.args!r} ended (exit code {code}) before a line starting with {prefix!r}")
        buf += chunk
