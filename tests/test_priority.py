"""Real-time loop processes ask for SCHED_RR (else a lower nice value) when permitted: UNIROS_LOOP_PRIORITY."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from _processes import pid_alive, wait_gone

from uniros_async.priority import (
    ACTOR_RT_PRIORITY,
    DEFAULT_LOOP_NICE,
    LOOP_RT_PRIORITY,
    MAX_LOOP_RANK,
    PM_QOS_DEVICE,
    RESET_ON_FORK,
    cores_kept_awake,
    cores_kept_from_halting,
    cores_kept_polling,
    loop_nice,
    loop_priority_mode,
)


def test_settings_parsing(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("UNIROS_LOOP_NICE", raising=False)
    monkeypatch.delenv("UNIROS_LOOP_PRIORITY", raising=False)
    assert (loop_priority_mode(), loop_nice()) == ("rt", DEFAULT_LOOP_NICE)
    monkeypatch.setenv("UNIROS_LOOP_NICE", "-5")
    assert loop_nice() == -5
    monkeypatch.setenv("UNIROS_LOOP_NICE", "off")
    assert loop_nice() is None
    for bad in ("fast", "-21", "20"):
        monkeypatch.setenv("UNIROS_LOOP_NICE", bad)
        with pytest.raises(ValueError, match="UNIROS_LOOP_NICE must be an integer in \\[-20, 19\\] or 'off'"):
            loop_nice()
    monkeypatch.setenv("UNIROS_LOOP_PRIORITY", "fifo")
    with pytest.raises(ValueError, match="UNIROS_LOOP_PRIORITY must be one of \\('rt', 'nice', 'off'\\)"):
        loop_priority_mode()


@pytest.mark.parametrize("mode", ["rt", "nice", "off"])
def test_raise_loop_priority_in_a_child(mode: str) -> None:
    """In a fresh process: the policy asked for when permitted (root here), nothing when 'off' or not permitted;
    a thread and a process started after it begin in the ordinary class at nice 0 (SCHED_RESET_ON_FORK)."""
    code = (
        "import os, subprocess, sys, threading; from uniros_async.priority import raise_loop_priority as r\n"
        "got = r()\n"
        "print(got, os.sched_getscheduler(0), os.sched_getparam(0).sched_priority, os.getpriority(0, 0))\n"
        "seen = []\n"
        "t = threading.Thread(target=lambda: seen.append((os.sched_getscheduler(0), os.getpriority(0, 0))))\n"
        "t.start(); t.join()\n"
        "child = subprocess.run([sys.executable, '-c', 'import os; print(os.sched_getscheduler(0), "
        "os.getpriority(0, 0))'], capture_output=True, text=True, check=True).stdout.split()\n"
        "print(*seen[0], *child)\n"
        "r(3); a = os.sched_getparam(0).sched_priority; r(99); b = os.sched_getparam(0).sched_priority\n"
        "print(a, b)\n"
    )
    env = {**os.environ, "UNIROS_LOOP_PRIORITY": mode, "UNIROS_LOOP_NICE": "-3"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60, check=True)
    got, policy, prio, nice, t_policy, t_nice, p_policy, p_nice, ranked3, ranked99 = out.stdout.split()
    base = os.getpriority(os.PRIO_PROCESS, 0)
    started = (int(t_policy), int(t_nice), int(p_policy), int(p_nice))
    if mode == "off":
        assert (got, int(policy), int(nice)) == ("None", os.SCHED_OTHER, base)
    elif os.geteuid() != 0:  # not permitted: keeps its priority, no error
        assert (int(policy) & ~RESET_ON_FORK, int(nice)) == (os.SCHED_OTHER, base)
    elif mode == "rt":
        assert (got, int(policy), int(prio)) == ("rt", os.SCHED_RR | RESET_ON_FORK, LOOP_RT_PRIORITY)
        assert (int(ranked3), int(ranked99)) == (LOOP_RT_PRIORITY + 3, LOOP_RT_PRIORITY + MAX_LOOP_RANK)
        assert started == (os.SCHED_OTHER, 0, os.SCHED_OTHER, 0)  # the kernel resets them to nice 0
    else:
        raised = base > -3
        assert (got, int(nice)) == ("nice" if raised else "None", min(base, -3))
        assert int(policy) == os.SCHED_OTHER | (RESET_ON_FORK if raised else 0)
        if raised:  # a negative nice value is not handed on either
            assert started == (os.SCHED_OTHER, 0, os.SCHED_OTHER, 0)


_FRESH_TORCH_CHECK = """
import json, os, subprocess, sys, threading
import torch
from uniros_async.priority import real_time_thread, thread_scheduling
torch.set_num_threads(2)
me = threading.get_native_id()
a = torch.randn(512, 512)
started = []
with real_time_thread() as rt:
    before = set(thread_scheduling())
    (a @ a).relu_().sum()  # parallel: the pool's workers start now, from this thread
    pool = set(thread_scheduling()) - before
    t = threading.Thread(target=lambda: started.append(os.sched_getscheduler(0)))
    t.start()
    t.join()
    child = subprocess.run([sys.executable, "-c", "import os; print(os.sched_getscheduler(0))"],
                           capture_output=True, text=True, timeout=60, check=True)
    classes = thread_scheduling()
print(json.dumps({"rt": rt, "me": list(classes[me]), "pool": [list(classes[tid]) for tid in pool],
                  "thread": started, "child": int(child.stdout)}))
"""


def test_threads_and_processes_a_real_time_thread_starts_begin_in_the_ordinary_class() -> None:
    """An acting thread in the real-time class: torch's intra-op pool, which its first parallel operation creates,
    a thread and a process it starts all compute at normal priority, below every env loop. In an interpreter of
    its own: torch makes its pool once per process, and in a test session an earlier test may have made it."""
    import json

    if os.geteuid() != 0:
        pytest.skip("SCHED_RR needs root or CAP_SYS_NICE; this machine's CI runs as root")
    out = subprocess.run(
        [sys.executable, "-c", _FRESH_TORCH_CHECK], capture_output=True, text=True, timeout=120, check=True
    )
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["rt"]
    assert tuple(got["me"]) == (os.SCHED_RR | RESET_ON_FORK, ACTOR_RT_PRIORITY)
    assert got["pool"], "torch started no pool thread (the test's parallel operation should need one)"
    assert {tuple(c) for c in got["pool"]} == {(os.SCHED_OTHER, 0)}
    assert got["thread"] == [os.SCHED_OTHER] and got["child"] == os.SCHED_OTHER


def test_raise_loop_priority_of_the_threads_an_env_started_leaves_the_caller_alone() -> None:
    """An env on the synchronous API runs its loop on a thread of its own, which its build started: a worker (or
    the fault tests' env process) that holds such an env puts the threads its build started in the real-time class
    by their ids (``thread_ids`` before and after)."""
    import gymnasium as gym

    import uniros_async  # noqa: F401  (registers the ids)
    from uniros_async.priority import raise_loop_priority, thread_ids, thread_scheduling

    if os.geteuid() != 0:
        pytest.skip("SCHED_RR needs root or CAP_SYS_NICE; this machine's CI runs as root")
    me = threading.get_native_id()
    mine = thread_scheduling()[me]
    before = thread_ids()
    env = gym.make("uniros/Rx200Reach-v0")
    try:
        started = thread_ids() - before
        (loop,) = [t.native_id for t in threading.enumerate() if t.name == "rx200 env loop"]
        assert loop in started and me not in started
        assert all(raise_loop_priority(2, thread_id=tid) == "rt" for tid in started)
        after = thread_scheduling()
        assert {after[tid] for tid in started} == {(os.SCHED_RR | RESET_ON_FORK, LOOP_RT_PRIORITY + 2)}
        assert after[me] == mine
    finally:
        env.close()


def _children(pid: int) -> list[int]:
    out: list[int] = []
    for tid in os.listdir(f"/proc/{pid}/task"):
        with contextlib.suppress(FileNotFoundError):
            out += [int(c) for c in Path(f"/proc/{pid}/task/{tid}/children").read_text().split()]
    return out


def test_a_real_time_worker_runs_round_robin_and_an_accelerated_or_loopless_one_does_not() -> None:
    """The loop's thread alone is real-time, with SCHED_RESET_ON_FORK; every other thread of the worker, and of
    the processes it started, is ordinary, but the emulated arm's serving thread (rank 0)."""
    import uniros_async
    from uniros_async.priority import thread_scheduling

    if os.geteuid() != 0:
        pytest.skip("SCHED_RR needs root or CAP_SYS_NICE; this machine's CI runs as root")
    envs = [
        uniros_async.make("uniros/Rx200Reach-v0", robot="emulated-real"),
        uniros_async.make("uniros/Rx200Reach-v0", clock="sim"),
        uniros_async.make("CartPole-v1"),  # no env loop: stepped as fast as its agent asks
    ]
    try:
        real_time, accelerated, loopless = (e._sup.pids()[0] for e in envs)  # type: ignore[attr-defined]
        rr = (os.SCHED_RR | RESET_ON_FORK, LOOP_RT_PRIORITY)
        ordinary = (os.SCHED_OTHER, 0)
        worker = thread_scheduling(real_time)
        assert worker.pop(real_time) == rr  # the main thread: the event loop that ticks and serves steps
        assert worker and set(worker.values()) == {ordinary}
        arms = {pid: thread_scheduling(pid) for pid in _children(real_time)}
        serving = [pid for pid, threads in arms.items() if threads[pid] == rr]
        assert len(serving) == 1, f"one emulated arm process should serve in the real-time class: {arms}"
        others = [c for pid, threads in arms.items() for tid, c in threads.items() if tid not in serving]
        assert others and set(others) == {ordinary}
        assert set(thread_scheduling(accelerated).values()) == {ordinary}
        assert set(thread_scheduling(loopless).values()) == {ordinary}
        assert not _children(accelerated)
    finally:
        for e in envs:
            e.close()


def test_the_workers_of_a_vector_env_run_in_the_order_their_actions_are_sent() -> None:
    """Ranked real-time priorities, the first worker highest (one step's actions wake them in index order, and with
    fewer cores than workers they then run in that order every time); the acting thread above them all."""
    from uniros_async import make_vec
    from uniros_async.priority import real_time_thread

    if os.geteuid() != 0:
        pytest.skip("SCHED_RR needs root or CAP_SYS_NICE; this machine's CI runs as root")
    venv = make_vec(["uniros/Rx200Reach-v0", "uniros/Ned2Reach-v0", "uniros/Rx200Reach-v0"])
    try:
        prios = [os.sched_getparam(p).sched_priority for p in venv._sup.pids()]
        assert prios == [LOOP_RT_PRIORITY + 2, LOOP_RT_PRIORITY + 1, LOOP_RT_PRIORITY]
    finally:
        venv.close()
    tid = threading.get_native_id()
    with real_time_thread() as rt:
        assert rt and os.sched_getparam(tid).sched_priority == ACTOR_RT_PRIORITY > LOOP_RT_PRIORITY + MAX_LOOP_RANK
        assert os.sched_getscheduler(tid) == os.SCHED_RR | RESET_ON_FORK
    assert os.sched_getscheduler(tid) == os.SCHED_OTHER


def _stat(pid: int) -> list[str]:
    with open(f"/proc/{pid}/stat") as f:
        return f.read().split(") ")[1].split()


def test_cores_kept_awake_runs_one_idle_class_poller_per_core_and_stops_them() -> None:
    cpus = sorted(os.sched_getaffinity(0))
    with cores_kept_awake() as pids:
        assert len(pids) == len(cpus)
        assert all(os.sched_getscheduler(p) == os.SCHED_IDLE for p in pids)
        assert sorted(min(os.sched_getaffinity(p)) for p in pids) == cpus  # one per core, pinned
        t0 = [int(_stat(p)[11]) for p in pids]  # utime, in clock ticks
        deadline = time.monotonic() + 5.0  # within 5 s even when other work keeps the cores busy
        while time.monotonic() < deadline and not all(int(_stat(p)[11]) > t for p, t in zip(pids, t0, strict=True)):
            time.sleep(0.1)
        assert all(int(_stat(p)[11]) > t for p, t in zip(pids, t0, strict=True)), "the pollers should burn idle CPU"
    assert not any(pid_alive(p) for p in pids)


def _fds_on(device: str) -> list[str]:
    fds = Path("/proc/self/fd")
    return [fd.name for fd in fds.iterdir() if os.path.realpath(fd) == device]


def test_cores_kept_polling_holds_a_zero_wake_up_latency_limit_for_the_block_and_drops_it_after() -> None:
    if not os.access(PM_QOS_DEVICE, os.W_OK):
        pytest.skip(f"{PM_QOS_DEVICE} is not writable here (it needs root); cores_kept_polling yields False there")
    with cores_kept_polling() as held:
        assert held
        assert len(_fds_on(PM_QOS_DEVICE)) == 1  # the limit lasts as long as this file stays open
        with open(PM_QOS_DEVICE, "rb") as f:  # reading gives the limit in force: the least of every holder's
            assert int.from_bytes(f.read(4), sys.byteorder) == 0
    assert _fds_on(PM_QOS_DEVICE) == []


def test_cores_kept_polling_yields_false_where_the_device_cannot_be_opened(tmp_path: Path) -> None:
    with cores_kept_polling(str(tmp_path / "no_such_device")) as held:
        assert held is False


def test_cores_kept_from_halting_holds_the_pm_qos_limit_where_it_can_and_starts_no_poller() -> None:
    if not os.access(PM_QOS_DEVICE, os.W_OK):
        pytest.skip(f"{PM_QOS_DEVICE} is not writable here (it needs root)")
    before = set(_children(os.getpid()))
    with cores_kept_from_halting() as how:
        assert how == "pm_qos"
        assert len(_fds_on(PM_QOS_DEVICE)) == 1
        assert set(_children(os.getpid())) == before
    assert _fds_on(PM_QOS_DEVICE) == []


def test_cores_kept_from_halting_falls_back_to_the_pollers_without_the_limit(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    import functools

    from uniros_async import priority

    monkeypatch.setattr(priority, "cores_kept_polling", functools.partial(cores_kept_polling, str(tmp_path / "none")))
    before = set(_children(os.getpid()))  # a pytest worker may have children of its own
    with cores_kept_from_halting() as how:
        assert how == "pollers"
        pollers = set(_children(os.getpid())) - before
        assert len(pollers) == len(os.sched_getaffinity(0))
        assert all(os.sched_getscheduler(p) == os.SCHED_IDLE for p in pollers)
    assert not any(pid_alive(p) for p in pollers)


def test_cores_kept_awake_pollers_die_with_a_sigkilled_parent() -> None:
    code = (
        "import sys, time; from uniros_async.priority import cores_kept_awake\n"
        "with cores_kept_awake() as pids:\n"
        "    print(*pids, flush=True); time.sleep(60)\n"
    )
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert parent.stdout is not None
        pids = [int(x) for x in parent.stdout.readline().split()]
        assert pids and all(pid_alive(p) for p in pids)
    finally:
        parent.kill()
        parent.wait(timeout=10)
        if parent.stdout is not None:
            parent.stdout.close()
    assert not wait_gone(pids, 5.0), "a poller outlived its SIGKILLed parent"
