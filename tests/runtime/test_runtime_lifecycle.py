"""Worker lifetime: a killed worker is reported, workers ignore SIGINT, nothing outlives close() or a SIGKILLed
parent (no process, no /dev/shm entry)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import gymnasium as gym
import numpy as np
import pytest

from uniros_async.errors import ConfigError, StepTimeoutError, WorkerError
from uniros_async.runtime import make_vec

pytestmark = pytest.mark.slow

RX, NED = "uniros/Rx200Reach-v0", "uniros/Ned2Reach-v0"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (exited, not yet reaped by its parent) counts as gone
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ", 1)[1][0] != "Z"
    except FileNotFoundError:
        return False


def _wait_gone(pids: list[int], timeout_s: float) -> list[int]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        left = [p for p in pids if _alive(p)]
        if not left:
            return []
        time.sleep(0.05)
    return [p for p in pids if _alive(p)]


def _shm_entries() -> set[str]:
    return {n for n in os.listdir("/dev/shm") if "uniros" in n}


def test_killed_worker_is_reported_by_index_and_close_is_bounded() -> None:
    venv = make_vec([RX, NED], clock="sim")
    try:
        venv.reset(seed=0)
        venv.step(np.zeros((2, 6), np.float32))
        victim = venv.pids[1]
        assert victim is not None
        os.kill(victim, signal.SIGKILL)
        t0 = time.monotonic()
        with pytest.raises(WorkerError) as e:
            for _ in range(3):  # the kill may land just after a reply was sent
                venv.step(np.zeros((2, 6), np.float32))
        assert time.monotonic() - t0 < 5.0
        assert e.value.index == 1
        assert "died" in str(e.value) or "broke" in str(e.value)
        with pytest.raises(WorkerError) as e2:  # stays reported
            venv.step(np.zeros((2, 6), np.float32))
        assert e2.value.index == 1
    finally:
        t0 = time.monotonic()
        venv.close()
        assert time.monotonic() - t0 < 10.0
    assert _wait_gone([p for p in venv.pids if p is not None], 1.0) == []


def test_restart_on_failure_replaces_the_worker_and_truncates_its_episode() -> None:
    venv = make_vec([RX, NED], clock="sim", restart_on_failure=True)
    try:
        venv.reset(seed=0)
        old = venv.pids[0]
        assert old is not None
        os.kill(old, signal.SIGKILL)
        restarted = None
        for _ in range(3):  # the kill may land just after a reply was sent
            obs, rewards, terminated, truncated, info = venv.step(np.zeros((2, 6), np.float32))
            if info.get("_worker_restarted", np.zeros(2, bool))[0]:
                restarted = (obs, rewards, terminated, truncated, info)
                break
        assert restarted is not None, "the dead worker was not restarted"
        obs, rewards, terminated, truncated, info = restarted
        assert truncated[0] and not terminated[0] and rewards[0] == 0.0
        assert obs.shape == (2, 28) and "died" in info["worker_error"][0]
        assert venv.restarts == [1, 0] and venv.pids[0] != old and not _alive(old)
        obs, *_ = venv.step(np.zeros((2, 6), np.float32))  # both usable again, padding restored
        assert obs.shape == (2, 28)
    finally:
        venv.close()
    assert _wait_gone([p for p in venv.pids if p is not None], 1.0) == []


def test_workers_ignore_sigint() -> None:
    venv = make_vec([RX], clock="sim")
    try:
        venv.reset(seed=0)
        pid = venv.pids[0]
        assert pid is not None
        os.kill(pid, signal.SIGINT)
        time.sleep(0.2)
        obs, *_ = venv.step(np.zeros((1, 5), np.float32))
        assert obs.shape == (1, 28)
    finally:
        venv.close()


def _reap(proc: subprocess.Popen[str]) -> None:
    """Kill ``proc`` if it still runs, wait for it, close its stdout."""
    if proc.poll() is None:
        proc.kill()
        proc.wait(5)
    if proc.stdout is not None:
        proc.stdout.close()


CHILD = textwrap.dedent(
    """
    import sys, time
    from uniros_async.runtime import make_vec
    venv = make_vec(["uniros/Rx200Reach-v0", "uniros/Ned2Reach-v0"], clock="sim")
    venv.reset(seed=0)
    print(" ".join(str(p) for p in venv.pids), flush=True)
    time.sleep(120)
    """
)


def test_no_worker_or_shm_entry_outlives_a_sigkilled_parent() -> None:
    shm_before = _shm_entries()
    proc = subprocess.Popen([sys.executable, "-c", CHILD], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()  # bounded by the child's own start timeout (and faulthandler_timeout)
        pids = [int(p) for p in line.split()]
        assert len(pids) == 2 and all(_alive(p) for p in pids), line
        proc.send_signal(signal.SIGKILL)
        proc.wait(5)
        assert _wait_gone(pids, 8.0) == []
    finally:
        _reap(proc)
    assert _shm_entries() - shm_before == set()


def test_hung_worker_times_out_and_close_stays_bounded() -> None:
    venv = make_vec([RX, NED], clock="sim", call_timeout_s=1.0)
    victim = venv.pids[0]
    assert victim is not None
    try:
        venv.reset(seed=0)
        os.kill(victim, signal.SIGSTOP)  # alive but silent: only the deadline can tell
        t0 = time.monotonic()
        with pytest.raises(StepTimeoutError) as e:
            venv.step(np.zeros((2, 6), np.float32))
        assert e.value.index == 0 and "no reply to 'step' within 1.0 s" in str(e.value)
        assert time.monotonic() - t0 < 3.0
    finally:
        t0 = time.monotonic()
        venv.close()
        assert time.monotonic() - t0 < 8.0
    assert _wait_gone([p for p in venv.pids if p is not None], 1.0) == []


def test_step_wait_with_a_timeout_can_be_called_again() -> None:
    """A step_wait that runs out of its own timeout while a worker is stopped leaves the step pending, replies and
    all; once the worker runs again, the next step_wait gets every reply, in order."""
    venv = make_vec([RX, NED], clock="sim", turn_based=True)
    victim = venv.pids[1]
    assert victim is not None
    try:
        venv.reset(seed=0)
        os.kill(victim, signal.SIGSTOP)
        venv.step_async(np.full((2, 6), 0.5, np.float32))
        t0 = time.monotonic()
        with pytest.raises(StepTimeoutError, match="worker 1: no reply to 'step' within 0.3 s") as e:
            venv.step_wait(timeout=0.3)
        assert e.value.index == 1 and isinstance(e.value, TimeoutError)
        assert 0.25 < time.monotonic() - t0 < 3.0
        with pytest.raises(gym.error.AlreadyPendingCallError):  # still pending: no new step over it
            venv.step(np.zeros((2, 6), np.float32))
        os.kill(victim, signal.SIGCONT)
        obs, rewards, terminated, truncated, info = venv.step_wait(timeout=30.0)
        assert obs.shape == (2, 28) and list(info["env_id"]) == [RX, NED]
        obs2, *_ = venv.step(np.full((2, 6), 0.5, np.float32))  # the connection is in step: the next one works
        assert obs2.shape == (2, 28)
    finally:
        os.kill(victim, signal.SIGCONT)
        venv.close()
    assert _wait_gone([p for p in venv.pids if p is not None], 1.0) == []


def test_ctrl_c_while_waiting_for_replies_marks_the_unanswered_worker_broken() -> None:
    """Ctrl-C while the agent's thread waits for a reply (outside any event loop: ``receive_blocking`` in
    ``poll(2)``) reaches the caller; the worker whose reply was still owed is broken (its next reply could not be
    matched to a request) and says so on the next step; the worker that had answered stays usable."""

    def interrupt(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    venv = make_vec([RX, NED], clock="sim", turn_based=True)
    victim = venv.pids[1]
    assert victim is not None
    old = signal.signal(signal.SIGALRM, interrupt)
    try:
        venv.reset(seed=0)
        os.kill(victim, signal.SIGSTOP)  # its reply cannot come
        signal.setitimer(signal.ITIMER_REAL, 0.3)
        t0 = time.monotonic()
        with pytest.raises(KeyboardInterrupt):
            venv.step(np.zeros((2, 6), np.float32))
        assert time.monotonic() - t0 < 3.0
        os.kill(victim, signal.SIGCONT)
        with pytest.raises(WorkerError, match="interrupted") as e:
            venv.step(np.zeros((2, 6), np.float32))
        assert e.value.index == 1
        assert venv._sup.workers[0].broken is None  # it had answered before the interrupt
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
        os.kill(victim, signal.SIGCONT)
        t0 = time.monotonic()
        venv.close()
        assert time.monotonic() - t0 < 8.0
    assert _wait_gone([p for p in venv.pids if p is not None], 1.0) == []


def test_tcp_transport_works_and_reports_a_killed_worker() -> None:
    with pytest.raises(ConfigError, match="transport"):
        make_vec([RX], transport="udp")
    venv = make_vec([RX, NED], clock="sim", transport="tcp")
    try:
        obs, info = venv.reset(seed=0)
        assert obs.shape == (2, 28) and list(info["env_id"]) == [RX, NED]
        venv.step(np.zeros((2, 6), np.float32))
        victim = venv.pids[0]
        assert victim is not None
        os.kill(victim, signal.SIGKILL)
        with pytest.raises(WorkerError) as e:
            for _ in range(3):
                venv.step(np.zeros((2, 6), np.float32))
        assert e.value.index == 0
    finally:
        venv.close()
    assert _wait_gone([p for p in venv.pids if p is not None], 1.0) == []


POLL_SYSCALLS = {7, 271}  # x86_64 poll, ppoll


def _syscall(pid: int, tid: int) -> int:
    with open(f"/proc/{pid}/task/{tid}/syscall") as f:
        first = f.read().split()[0]
    return int(first) if first.lstrip("-").isdigit() else -1


def _switches(pid: int, tid: int) -> int:
    with open(f"/proc/{pid}/task/{tid}/status") as f:
        fields = dict(line.split(":", 1) for line in f if "ctxt_switches" in line)
    return sum(int(v) for v in fields.values())


def test_the_parent_watchdog_sleeps_until_the_parent_exits() -> None:
    """The worker's watchdog thread takes no GIL while its parent lives (no wake-ups a real-time loop could wait
    behind), and still notices the parent's exit: here a middle process that starts a waiter and is killed."""
    venv = make_vec([RX], clock="sim")
    try:
        venv.reset(seed=0)
        pid = venv.pids[0]
        assert pid is not None
        polling = [t for t in map(int, os.listdir(f"/proc/{pid}/task")) if _syscall(pid, t) in POLL_SYSCALLS]
        assert polling, "no thread of the worker waits in poll(2): the watchdog is not on its pidfd"
        before = {t: _switches(pid, t) for t in polling}
        time.sleep(0.6)  # a 0.1 s poll of getppid() would have woken six times
        assert any(_switches(pid, t) == n for t, n in before.items()), before
    finally:
        venv.close()
    middle = textwrap.dedent(
        """
        import subprocess, sys, time
        waiter = subprocess.Popen([sys.executable, "-c",
            "import os, time; from uniros_async.runtime.worker import _wait_for_exit; "
            "t0 = time.monotonic(); print(os.getpid(), flush=True); _wait_for_exit(os.getppid()); "
            "print(round(time.monotonic() - t0, 3), flush=True)"])
        time.sleep(120)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", middle], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        waiter = int(proc.stdout.readline())
        time.sleep(0.3)
        assert _alive(waiter)  # still waiting: its parent lives
        proc.kill()
        proc.wait(5)
        assert _wait_gone([waiter], 5.0) == []  # it returned and exited once the parent was gone
        assert float(proc.stdout.readline()) >= 0.3  # (its clock started before it said its pid)
    finally:
        _reap(proc)
