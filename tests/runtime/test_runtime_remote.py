"""Workers on another host: a launcher (``uniros worker serve``) starts workers on request, the
agent side connects to them over tcp, mixed with local workers in one vector env.

"Another host" is emulated by loopback: the launcher runs in a separate process (the real CLI, spawned with
subprocess) listening on 127.0.0.1, and everything between agent, launcher and workers goes over real tcp
sockets with the shared-key handshake. The launcher's children are read from /proc to check that nothing it
started outlives the agent's close.
"""

from __future__ import annotations

import asyncio
import os
import select
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator

import numpy as np
import pytest
from _children import children

from uniros_async.errors import ConfigError, WorkerError
from uniros_async.runtime import RemoteWorker, make, make_vec, serve_launcher
from uniros_async.runtime.protocol import pack, unpack
from uniros_async.transports.base import TransportOptions, connect

pytestmark = pytest.mark.slow

RX, NED = "uniros/Rx200Reach-v0", "uniros/Ned2Reach-v0"
KEY = "loopback-test-key"


class LauncherProcess:
    """``uniros worker serve`` in its own process on 127.0.0.1 (port 0), key from $TEST_LAUNCHER_KEY."""

    def __init__(self) -> None:
        env = dict(os.environ, TEST_LAUNCHER_KEY=KEY)
        env.pop("UNIROS_WORKER_AUTH_KEY", None)
        cmd = [
            sys.executable,
            "-m",
            "uniros_async.cli",
            "worker",
            "serve",
            "--listen",
            "tcp://127.0.0.1:0",
            "--auth-key-env",
            "TEST_LAUNCHER_KEY",
        ]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, env=env)
        try:
            assert self.proc.stdout is not None
            ready, _, _ = select.select([self.proc.stdout], [], [], 30.0)
            assert ready, "the launcher did not report its URI within 30 s"
            line = self.proc.stdout.readline()
            assert "listening on tcp://" in line, line
            self.uri = line.split("listening on ")[1].split()[0]
        except BaseException:
            self.stop()
            raise

    @property
    def pid(self) -> int:
        return self.proc.pid

    def worker(self, key: str | None = KEY) -> RemoteWorker:
        return RemoteWorker(self.uri, auth_key=key)

    def workers(self) -> list[int]:
        """The launcher's child processes other than multiprocessing's resource tracker."""
        out = []
        for entry in os.listdir("/proc"):
            if not entry.isdigit():
                continue
            try:
                with open(f"/proc/{entry}/stat") as f:
                    fields = f.read().rsplit(") ", 1)[1].split()
                with open(f"/proc/{entry}/cmdline", "rb") as f:
                    cmdline = f.read()
            except (FileNotFoundError, ProcessLookupError, IndexError):
                continue
            if int(fields[1]) == self.pid and fields[0] != "Z" and b"resource_tracker" not in cmdline:
                out.append(int(entry))
        return out

    def wait_no_workers(self, timeout_s: float) -> list[int]:
        deadline = time.monotonic() + timeout_s
        while (left := self.workers()) and time.monotonic() < deadline:
            time.sleep(0.05)
        return left

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


@pytest.fixture(scope="module")
def launcher() -> Iterator[LauncherProcess]:
    lp = LauncherProcess()
    try:
        yield lp
        assert lp.proc.poll() is None, "the launcher died during the tests"
    finally:
        lp.stop()
    assert lp.proc.returncode == 0


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(") ", 1)[1][0] != "Z"
    except (FileNotFoundError, ProcessLookupError):
        return False


def test_make_and_make_vec_mix_remote_and_local_workers(launcher: LauncherProcess) -> None:
    env = make(RX, clock="sim", worker=launcher.worker())
    try:
        assert launcher.workers() == [env.pid]
        obs, info = env.reset(seed=0)
        assert obs.shape == (28,) and "env_id" not in info  # one env: its info is its own
        obs, reward, terminated, truncated, _ = env.step(np.zeros(5, np.float32))
        assert obs.shape == (28,) and isinstance(reward, float)
        # the worker stops by itself when its tcp connection to the agent goes away (EOF), the launcher's
        # connection still open: it exits cleanly (code 0) and the launcher reports it
        sup, w = env._sup, env._worker  # type: ignore[attr-defined]
        sup.call(w.transport.aclose(), 5.0)
        assert sup.call(w.remote.poll_exit(5.0), 7.0) == 0
        assert launcher.wait_no_workers(2.0) == []
    finally:
        env.close()

    venv = make_vec([(RX, {"worker": launcher.worker()}), NED], clock="sim")
    try:
        remote_pid, local_pid = venv.pids
        assert launcher.workers() == [remote_pid]
        assert local_pid in [p.pid for p in children()]
        obs, info = venv.reset(seed=0)
        assert obs.shape == (2, 28) and list(info["env_id"]) == [RX, NED]
        for _ in range(3):
            obs, rewards, terminated, truncated, info = venv.step(np.zeros((2, 6), np.float32))
        assert obs.shape == (2, 28) and rewards.shape == (2,)
    finally:
        t0 = time.monotonic()
        venv.close()
        assert time.monotonic() - t0 < 10.0
    assert launcher.wait_no_workers(5.0) == []  # nothing left behind on the launcher's side
    assert not _alive(local_pid)


def test_auth_key_mismatch_is_refused_clearly(launcher: LauncherProcess) -> None:
    t0 = time.monotonic()
    for key in ("wrong-key", None):
        with pytest.raises(WorkerError) as e:
            make(RX, clock="sim", worker=launcher.worker(key))
        assert e.value.index == 0 and launcher.uri in str(e.value) and "key" in str(e.value), str(e.value)
    assert time.monotonic() - t0 < 10.0
    assert launcher.workers() == [] and children() == []


def test_bad_env_id_bad_request_and_build_failure_through_the_launcher(launcher: LauncherProcess) -> None:
    with pytest.raises(ConfigError, match="uniros/Nope-v0") as e:  # unknown here: the launcher's registry judges
        make("uniros/Nope-v0", worker=launcher.worker())
    assert "unknown env id" in str(e.value) and launcher.uri in str(e.value)
    with pytest.raises(ConfigError, match="worker"):
        make(RX, worker="udp://127.0.0.1:7000")
    with pytest.raises(ConfigError, match="plain data"):
        make(RX, worker=launcher.worker(), clock=object())

    async def bad_requests() -> list[dict[str, object]]:
        replies = []
        for frame in (b"\xc1 not msgpack", pack({"op": "launch-missiles"}), pack({"op": "start", "env_id": 3})):
            t = await connect(launcher.uri, TransportOptions(auth_key=KEY.encode()))
            try:
                await t.send(frame)
                async with asyncio.timeout(10):
                    replies.append(unpack(await t.receive()))
            finally:
                await t.aclose()
        return replies

    replies = asyncio.run(bad_requests())
    assert [r["ok"] for r in replies] == [False, False, False]
    assert "malformed" in str(replies[0]["error"]) and "expected a start request" in str(replies[1]["error"])
    assert "env_id" in str(replies[2]["error"])

    with pytest.raises(WorkerError) as e2:  # the env fails to build in the remote worker: its traceback comes back
        make(RX, clock="sim", goal_min=[0.3, 0.0, 0.1], worker=launcher.worker())  # above the default goal_max
    assert e2.value.index == 0 and "goal_min/goal_max" in str(e2.value)
    assert "reach.py" in e2.value.remote_traceback
    assert launcher.wait_no_workers(5.0) == []
    assert launcher.proc.poll() is None  # still serving


def test_unreachable_launcher_closes_the_other_workers() -> None:
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.monotonic()
    with pytest.raises(WorkerError) as e:
        make_vec([RX, (NED, {"worker": RemoteWorker(f"tcp://127.0.0.1:{port}", connect_timeout_s=1.0)})], clock="sim")
    assert e.value.index == 1 and "unreachable" in str(e.value)
    assert time.monotonic() - t0 < 15.0
    assert children() == []


def test_remote_worker_is_restarted_through_its_launcher(launcher: LauncherProcess) -> None:
    venv = make_vec([(RX, {"worker": launcher.worker()}), NED], clock="sim", restart_on_failure=True)
    try:
        venv.reset(seed=0)
        old = venv.pids[0]
        assert old is not None
        os.kill(old, signal.SIGKILL)  # the remote worker dies (on its host)
        restarted = None
        for _ in range(3):  # the kill may land just after a reply was sent
            obs, rewards, terminated, truncated, info = venv.step(np.zeros((2, 6), np.float32))
            if info.get("_worker_restarted", np.zeros(2, bool))[0]:
                restarted = info
                break
        assert restarted is not None, "the remote worker was not restarted"
        assert "died with exit code -9" in restarted["worker_error"][0] and launcher.uri in restarted["worker_error"][0]
        assert venv.restarts == [1, 0] and venv.pids[0] != old
        assert launcher.workers() == [venv.pids[0]]
        obs, *_ = venv.step(np.zeros((2, 6), np.float32))
        assert obs.shape == (2, 28)
    finally:
        venv.close()
    assert launcher.wait_no_workers(5.0) == []


AGENT = """
import sys
from uniros_async.runtime import RemoteWorker, make
env = make("uniros/Rx200Reach-v0", clock="sim", worker=RemoteWorker(sys.argv[1], auth_key=sys.argv[2]))
env.reset(seed=0)
print(env.pid, flush=True)
sys.stdin.read()
"""


def test_a_sigkilled_agent_leaves_no_worker_on_the_launcher(launcher: LauncherProcess) -> None:
    agent = subprocess.Popen(
        [sys.executable, "-c", AGENT, launcher.uri, KEY], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert agent.stdout is not None
        ready, _, _ = select.select([agent.stdout], [], [], 30.0)
        assert ready, "the agent did not start its remote worker within 30 s"
        pid = int(agent.stdout.readline())
        assert launcher.workers() == [pid]
        agent.kill()
        agent.wait(5)
        assert launcher.wait_no_workers(5.0) == []
    finally:
        if agent.poll() is None:
            agent.kill()
            agent.wait(5)
        for f in (agent.stdin, agent.stdout):
            if f is not None:
                f.close()


def test_killed_launcher_is_reported_on_the_next_step() -> None:
    lp = LauncherProcess()
    try:
        env = make(NED, clock="sim", worker=lp.worker(), call_timeout_s=5.0)
        try:
            env.reset(seed=0)
            env.step(np.zeros(6, np.float32))
            worker_pid = env.pid
            os.kill(lp.pid, signal.SIGKILL)
            lp.proc.wait(5)
            t0 = time.monotonic()
            with pytest.raises(WorkerError) as e:
                env.step(np.zeros(6, np.float32))
            assert time.monotonic() - t0 < 5.0 + 1.0
            assert e.value.index == 0 and "remote worker" in str(e.value), str(e.value)
            print(e.value)
        finally:
            t0 = time.monotonic()
            env.close()
            assert time.monotonic() - t0 < 10.0
        deadline = time.monotonic() + 5.0  # the worker's parent-pid watchdog ended it
        while _alive(worker_pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _alive(worker_pid)
    finally:
        lp.stop()


async def _request(uri: str, request: dict[str, object]) -> tuple[dict[str, object], object]:
    t = await connect(uri)
    try:
        await t.send(pack(request))
        async with asyncio.timeout(30):
            return unpack(await t.receive()), t
    except BaseException:
        await t.aclose()
        raise


async def test_serve_launcher_refuses_bad_ids_and_extra_workers_reaps_and_frees_its_port() -> None:
    async with serve_launcher("tcp://127.0.0.1:0", max_workers=1, stop_timeout_s=0.5) as launcher:
        uri = launcher.uri
        reply, t = await _request(uri, {"op": "start", "env_id": "uniros/Nope-v0", "kwargs": {}})
        await t.aclose()  # type: ignore[attr-defined]
        assert reply["ok"] is False and reply["type"] == "ConfigError" and "uniros/Nope-v0" in str(reply["error"])
        start = {"op": "start", "env_id": RX, "kwargs": {"clock": "sim"}, "start_timeout_s": 30.0}
        first, t1 = await _request(uri, start)
        try:
            assert first["ok"] is True, first
            pid = first["result"]["pid"]  # type: ignore[index]
            assert launcher.worker_pids() == [pid]
            second, t2 = await _request(uri, start)
            await t2.aclose()  # type: ignore[attr-defined]
            assert second["ok"] is False and "max-workers 1" in str(second["error"])
        finally:
            await t1.aclose()  # type: ignore[attr-defined]
        async with asyncio.timeout(10):  # the agent left without connecting: the launcher stops and reaps it
            while launcher.worker_pids():  # noqa: ASYNC110 - polls process state, no event to wait on
                await asyncio.sleep(0.05)
        assert not _alive(pid)  # type: ignore[arg-type]
    with pytest.raises(TimeoutError):
        await connect(uri, TransportOptions(connect_timeout_s=0.3))
