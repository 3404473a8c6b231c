"""Real ROS 2 peers for tests and the bench: rclpy (Jazzy, from PyPI) in a venv of its own, in a network namespace.

rclpy never enters our interpreter. ``ros2_venv()`` is a virtual environment with the ``ros-jazzy-*`` wheels
(``ROS2_PEER_PACKAGES``; ``$UNIROS_ROS2_VENV``, default ``~/.cache/uniros/ros2-venv``), made by
``install_ros2_venv()`` or ``python -m uniros_async.bench.ros2_peers --install``. Its scripts run with ``rclpy_env()``
(``LD_LIBRARY_PATH=<venv>/lib``, Fast DDS as the rmw, no PYTHONPATH of ours).

DDS discovers peers by multicast, so everything on DDS here runs in a network namespace of its own
(``netns_command``: ``unshare --net --mount``, loopback up with multicast on, a /dev/shm of its own), never on the
host's interfaces: tests cannot disturb, or be disturbed by, other hosts or other test runs, and what rclpy leaves
in /dev/shm goes with the namespace. Inside it ``UNIROS_NETNS=1`` is set.

``ros2_missing()`` / ``netns_missing()`` say why the peers cannot run (what to install or what is lacking);
``skip_or_fail(reason)`` skips a test with that reason, or fails it when ``UNIROS_REQUIRE_ROS=1`` (set by
``.ci/run``, where the peers must run).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import NoReturn

from uniros_async.bench.ros1_peers import kill_process, wait_for_line

__all__ = [
    "ROS2_PEER_PACKAGES",
    "in_netns",
    "install_ros2_venv",
    "kill_process",
    "netns_command",
    "netns_missing",
    "rclpy_env",
    "rclpy_process",
    "ros2_missing",
    "ros2_python",
    "ros2_venv",
    "ros_required",
    "skip_or_fail",
    "start_rclpy",
    "wait_for_line",
]

ROS2_PEER_PACKAGES = (
    "ros-jazzy-rclpy",
    "ros-jazzy-rmw-fastrtps-cpp",
    "ros-jazzy-sensor-msgs",
    "ros-jazzy-std-msgs",
    "ros-jazzy-trajectory-msgs",
)
_MODULES = ("rclpy", "sensor_msgs", "std_msgs", "trajectory_msgs")
# found, not imported: importing rclpy loads the lttng-ust bundled in its wheels, which leaves files in the host's
# /dev/shm; the peers themselves run in a namespace with a /dev/shm of its own
_PROBE = f"import importlib.util as u, sys; sys.exit(0 if all(u.find_spec(m) for m in {_MODULES!r}) else 1)"


def ros2_venv() -> Path:
    """The rclpy venv: ``$UNIROS_ROS2_VENV``, default ``~/.cache/uniros/ros2-venv``."""
    default = Path.home() / ".cache" / "uniros" / "ros2-venv"
    return Path(os.environ.get("UNIROS_ROS2_VENV", str(default)))


def ros2_python() -> Path:
    """The venv's interpreter (it can ``import rclpy`` with ``rclpy_env()``)."""
    return ros2_venv() / "bin" / "python"


def _install_hint() -> str:
    return (
        f"python3.11 -m venv {ros2_venv()} && {ros2_venv()}/bin/pip install {' '.join(ROS2_PEER_PACKAGES)} "
        f"(or: python -m uniros_async.bench.ros2_peers --install)"
    )


def ros_required() -> bool:
    """True where the ROS peers must run (``UNIROS_REQUIRE_ROS=1``, set by ``.ci/run``): a missing peer fails."""
    return os.environ.get("UNIROS_REQUIRE_ROS") == "1"


def skip_or_fail(reason: str) -> NoReturn:
    """Skip the calling test saying ``reason``, or fail it when ``ros_required()``."""
    import pytest

    if ros_required():
        pytest.fail(f"UNIROS_REQUIRE_ROS=1 and the ROS peers cannot run: {reason}")
    pytest.skip(reason)


def rclpy_env(domain_id: int = 0, *, home: str | os.PathLike[str] | None = None) -> dict[str, str]:
    """A copy of ``os.environ`` for an rclpy process: the venv's libraries, Fast DDS, ``ROS_DOMAIN_ID``, ROS's log
    and home folders under ``home`` (default: the system temp dir), no PYTHONPATH of ours."""
    home = Path(home) if home is not None else Path(os.environ.get("TMPDIR", "/tmp")) / f"uniros_ros2_{os.getuid()}"
    (home / "log").mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    lib = str(ros2_venv() / "lib")
    env.update(
        LD_LIBRARY_PATH=lib + (":" + env["LD_LIBRARY_PATH"] if env.get("LD_LIBRARY_PATH") else ""),
        ROS_DOMAIN_ID=str(domain_id),
        RMW_IMPLEMENTATION="rmw_fastrtps_cpp",
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",  # as our side's default: peers on this host only
        ROS_HOME=str(home),
        ROS_LOG_DIR=str(home / "log"),
        PYTHONUNBUFFERED="1",
    )
    for key in ("PYTHONPATH", "PYTHONHOME", "ROS_LOCALHOST_ONLY", "ROS_STATIC_PEERS", "CYCLONEDDS_URI"):
        env.pop(key, None)
    return env


@functools.cache
def ros2_missing() -> str | None:
    """Why the rclpy peers cannot run (naming what to install), or None when they can."""
    python = ros2_python()
    if not os.access(python, os.X_OK):
        return f"no rclpy venv at {ros2_venv()} ($UNIROS_ROS2_VENV); make it: {_install_hint()}"
    try:
        probe = subprocess.run(
            [str(python), "-c", _PROBE],
            env=rclpy_env(),
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"{python} could not import rclpy ({exc}); install it: {_install_hint()}"
    if probe.returncode != 0:
        last = probe.stderr.strip().splitlines()[-1:] or ["?"]
        return f"{python} does not have {', '.join(_MODULES)} ({last[0]}); install them: {_install_hint()}"
    try:
        import cyclonedds  # noqa: F401
        import rosbags  # noqa: F401
    except ImportError as exc:
        return f"our side of ROS 2 is not installed ({exc}): pip install -e '.[ros2]'"
    return None


@functools.cache
def netns_missing() -> str | None:
    """Why a network namespace cannot be made here (``unshare --net`` needs root or user namespaces, and ``ip``),
    or None when it can."""
    unshare, ip = (
        shutil.which("unshare"),
        shutil.which("ip") or ("/sbin/ip" if os.access("/sbin/ip", os.X_OK) else None),
    )
    if unshare is None or ip is None:
        return (
            "the ROS 2 tests run in a network namespace of their own: they need unshare (util-linux) and ip (iproute2)"
        )
    try:
        probe = subprocess.run(netns_command(["true"]), capture_output=True, text=True, timeout=30, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"cannot make a network namespace ({exc})"
    if probe.returncode != 0:
        return f"cannot make a namespace with `unshare --net --mount` (root needed?): {probe.stderr.strip()[-300:]}"
    return None


def in_netns() -> bool:
    """True inside a namespace ``netns_command`` made."""
    return os.environ.get("UNIROS_NETNS") == "1"


def netns_command(argv: Sequence[str]) -> list[str]:
    """``argv`` run in a new network namespace whose loopback is up with multicast on (``UNIROS_NETNS=1``), with a
    /dev/shm of its own: rclpy's Fast DDS and lttng-ust (bundled in the wheels) leave files there, which then go
    with the namespace instead of staying on the host."""
    ip = shutil.which("ip") or "/sbin/ip"
    script = (
        f"mount -t tmpfs -o mode=1777,size=256m tmpfs /dev/shm && {ip} link set lo up && "
        f'{ip} link set lo multicast on && UNIROS_NETNS=1 exec "$@"'
    )
    return ["unshare", "--net", "--mount", "--", "sh", "-c", script, "sh", *argv]


def start_rclpy(
    script_path: str | os.PathLike[str],
    *args: str,
    domain_id: int = 0,
    tmp_path: str | os.PathLike[str],
    stdin: bool = False,
) -> subprocess.Popen[str]:
    """Start ``ros2_python() script_path *args`` with ``rclpy_env(domain_id)``; stdout is a text pipe (read it
    with ``wait_for_line``), stdin a pipe when asked, stderr goes to ``tmp_path/<script>_<n>.stderr``. Prefer
    ``rclpy_process``, which also kills it."""
    err_path = Path(tmp_path) / f"{Path(script_path).stem}_{time.monotonic_ns()}.stderr"
    with open(err_path, "w") as stderr:
        return subprocess.Popen(  # the child keeps its own copy of the stderr file
            [str(ros2_python()), str(script_path), *args],
            env=rclpy_env(domain_id, home=Path(tmp_path) / "ros_home"),
            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=stderr,
            text=True,
            bufsize=1,
        )


@contextlib.contextmanager
def rclpy_process(
    script_path: str | os.PathLike[str],
    *args: str,
    domain_id: int = 0,
    tmp_path: str | os.PathLike[str],
    stdin: bool = False,
) -> Iterator[subprocess.Popen[str]]:
    """``start_rclpy`` for the length of the block; the process is killed and reaped when the block ends."""
    proc = start_rclpy(script_path, *args, domain_id=domain_id, tmp_path=tmp_path, stdin=stdin)
    try:
        yield proc
    finally:
        kill_process(proc)


def install_ros2_venv(path: str | os.PathLike[str] | None = None, *, python: str | None = None) -> Path:
    """Make the rclpy venv at ``path`` (default ``ros2_venv()``) with ``ROS2_PEER_PACKAGES`` from PyPI; a venv that
    already imports them is kept as it is. The wheels are cp311: ``python`` (default: this interpreter) must be 3.11.

    Raises:
        RuntimeError: venv or pip failed (with pip's last lines).
    """
    venv = Path(path) if path is not None else ros2_venv()
    if path is not None:
        os.environ["UNIROS_ROS2_VENV"] = str(venv)
    ros2_missing.cache_clear()
    if ros2_missing() is None:
        return venv
    venv.parent.mkdir(parents=True, exist_ok=True)
    steps = [
        [python or sys.executable, "-m", "venv", "--clear", str(venv)],
        [str(venv / "bin" / "pip"), "install", "-q", *ROS2_PEER_PACKAGES],
    ]
    for cmd in steps:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1800, check=False)
        if proc.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}): {proc.stderr.strip()[-1500:]}")
    ros2_missing.cache_clear()
    reason = ros2_missing()
    if reason is not None:
        raise RuntimeError(f"the rclpy venv at {venv} was made but does not work: {reason}")
    return venv


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m uniros_async.bench.ros2_peers --install [--venv PATH]``: make the rclpy venv; ``--check``: say
    whether the peers can run (exit 1 if not)."""
    parser = argparse.ArgumentParser(prog="python -m uniros_async.bench.ros2_peers")
    parser.add_argument("--install", action="store_true", help="make the rclpy venv (ROS2_PEER_PACKAGES from PyPI)")
    parser.add_argument("--check", action="store_true", help="exit 1, saying why, when the peers cannot run")
    parser.add_argument(
        "--venv", default=None, help="where (default $UNIROS_ROS2_VENV, else ~/.cache/uniros/ros2-venv)"
    )
    args = parser.parse_args(argv)
    if args.venv:
        os.environ["UNIROS_ROS2_VENV"] = args.venv
    if args.install:
        print(install_ros2_venv())
    if args.check:
        reason = ros2_missing() or netns_missing()
        if reason is not None:
            print(reason, file=sys.stderr)
            return 1
        print("ok")
    return 0


if __name__ == "__main__":
    sys.exit(main())
