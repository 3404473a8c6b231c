"""Real-time loop processes ask for SCHED_RR (else a lower nice value) when permitted: UNIROS_LOOP_PRIORITY."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest
from _processes import pid_alive, wait_gone

from uniros_async.priority import (
    ACTOR_RT_PRIORITY,
    DEFAULT_LOOP_NICE,
    LOOP_RT_PRIORITY,
    MAX_LOOP_RANK,
    cores_kept_awake,
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
    """In a fresh process: the policy asked for when permitted (root here), nothing when 'off' or not permitted."""
    code = (
        "import os; from uniros_async.priority import raise_loop_priority as r; got = r(); "
        "print(got, os.sched_getscheduler(0), os.sched_getparam(0).sched_priority, os.getpriority(0, 0)); "
        "r(3); a = os.sched_getparam(0).sched_priority; r(99); b = os.sched_getparam(0).sched_priority; "
        "print(a, b)"
    )
    env = {**os.environ, "UNIROS_LOOP_PRIORITY": mode, "UNIROS_LOOP_NICE": "-3"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60, check=True)
    got, policy, prio, nice, ranked3, ranked99 = out.stdout.split()
    base = os.getpriority(os.PRIO_PROCESS, 0)
    if mode == "off":
        assert (got, int(policy), int(nice)) == ("None", os.SCHED_OTHER, base)
    elif os.geteuid() != 0:  # not permitted: keeps its priority, no error
        assert (int(policy), int(nice)) == (os.SCHED_OTHER, base)
    elif mode == "rt":
        assert (got, int(policy), int(prio)) == ("rt", os.SCHED_RR, LOOP_RT_PRIORITY)
        assert (int(ranked3), int(ranked99)) == (LOOP_RT_PRIORITY + 3, LOOP_RT_PRIORITY + MAX_LOOP_RANK)
    else:
        assert (got, int(policy), int(nice)) == ("nice" if base > -3 else "None", os.SCHED_OTHER, min(base, -3))


def test_a_real_time_worker_runs_round_robin_and_an_accelerated_one_does_not() -> None:
    import uniros_async

    if os.geteuid() != 0:
        pytest.skip("SCHED_RR needs root or CAP_SYS_NICE; this machine's CI runs as root")
    envs = [uniros_async.make("uniros/Rx200Reach-v0"), uniros_async.make("uniros/Rx200Reach-v0", clock="sim")]
    try:
        policies = [os.sched_getscheduler(e._sup.pids()[0]) for e in envs]  # type: ignore[attr-defined]
        assert policies == [os.SCHED_RR, os.SCHED_OTHER]
        assert os.sched_getparam(envs[0]._sup.pids()[0]).sched_priority == LOOP_RT_PRIORITY  # type: ignore[attr-defined]
    finally:
        for e in envs:
            e.close()


def test_the_workers_of_a_vector_env_run_in_the_order_their_actions_are_sent() -> None:
    """Ranked real-time priorities, the first worker highest (one step's actions wake them in index order, and with
    fewer cores than workers they then run in that order every time); the acting thread above them all."""
    import threading

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
