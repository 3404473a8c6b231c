"""Workers placed by Ray that die, restart, lose their node, and close: on a real multi-node Ray cluster."""

from __future__ import annotations

import os
import signal
import threading
import time
from typing import Any

import numpy as np
import pytest
from _processes import wait_gone

from uniros_async.errors import WorkerError
from uniros_async.runtime import make_vec

RX = "uniros/Rx200Reach-v0"
ARM = {"worker": {"ray": {"resources": {"rx200_arm": 1}}}}

pytestmark = pytest.mark.usefixtures("nothing_left")


def test_a_killed_worker_is_reported_with_its_index_and_node(cluster: dict[str, Any]) -> None:
    venv = make_vec([RX, (RX, ARM)], backend="ray", clock="sim")
    try:
        venv.reset(seed=0)
        pid = venv.pids[1]
        assert pid is not None
        os.kill(pid, signal.SIGKILL)
        assert not wait_gone([pid], 5.0)
        with pytest.raises(WorkerError) as err:
            for _ in range(3):  # the kill may land just after a reply was sent
                venv.step(np.zeros((2, 5), np.float32))
        assert err.value.index == 1
        msg = str(err.value)
        assert "-9" in msg and cluster["arm_id"][:12] in msg, msg
    finally:
        venv.close()


def test_restart_on_failure_restarts_through_ray_and_truncates_the_episode(cluster: dict[str, Any]) -> None:
    venv = make_vec([RX, (RX, ARM)], backend="ray", clock="sim", restart_on_failure=True)
    try:
        venv.reset(seed=0)
        old = venv.pids[1]
        assert old is not None
        os.kill(old, signal.SIGKILL)
        assert not wait_gone([old], 5.0)
        restarted = None
        for _ in range(3):
            obs, rewards, terminated, truncated, info = venv.step(np.zeros((2, 5), np.float32))
            if info.get("_worker_restarted", np.zeros(2, bool))[1]:
                restarted = (obs, rewards, terminated, truncated, info)
                break
        assert restarted is not None, "the dead worker was not restarted"
        obs, rewards, terminated, truncated, info = restarted
        assert truncated[1] and not terminated[1] and rewards[1] == 0.0
        assert venv.restarts == [0, 1] and venv.pids[1] not in (None, old)
        assert venv._sup.workers[1].process.node_id == cluster["arm_id"]  # placed by Ray again, on the arm node
        obs, *_ = venv.step(np.zeros((2, 5), np.float32))
        assert np.isfinite(obs).all()
    finally:
        venv.close()


def test_a_killed_process_of_two_envs_is_restarted_through_ray_with_both(cluster: dict[str, Any]) -> None:
    """``envs_per_worker=2``: the two arm-node envs share one process (one actor); it dies, and both are placed
    again in one new process on the arm node, both steps truncated; the env elsewhere goes on."""
    venv = make_vec([RX, (RX, ARM), (RX, ARM)], backend="ray", clock="sim", envs_per_worker=2, restart_on_failure=True)
    try:
        venv.reset(seed=0)
        old = venv.pids[1]
        assert old is not None and venv.pids[2] == old != venv.pids[0]
        os.kill(old, signal.SIGKILL)
        assert not wait_gone([old], 5.0)
        restarted = None
        for _ in range(3):
            step = venv.step(np.zeros((3, 5), np.float32))
            if step[4].get("_worker_restarted", np.zeros(3, bool)).any():
                restarted = step
                break
        assert restarted is not None, "the dead process was not restarted"
        _, rewards, terminated, truncated, info = restarted
        assert list(info["_worker_restarted"]) == [False, True, True]
        assert truncated[1:].all() and not terminated[1:].any() and (rewards[1:] == 0.0).all()
        assert venv.restarts == [0, 1, 1] and venv.pids[1] == venv.pids[2] not in (None, old)
        workers = venv._sup.workers
        assert workers[1].process is workers[2].process and workers[1].process.node_id == cluster["arm_id"]
        obs, *_ = venv.step(np.zeros((3, 5), np.float32))
        assert np.isfinite(obs).all()
    finally:
        venv.close()


def test_a_lost_node_is_reported_within_one_action_cycle(cluster: dict[str, Any]) -> None:
    """Two real-time envs (the wall clock, action cycle 0.8 s): one on the agent's node, one on a node that is lost
    while a step is in flight, 0.3 s into its cycle; the step raises the lost worker's WorkerError (its index and
    node) before the other env's reply is due, within the action cycle of the kill."""
    c = cluster["cluster"]
    spare = c.add_node(num_cpus=2, resources={"spare_pc": 1}, object_store_memory=80 * 1024 * 1024)
    c.wait_for_nodes()
    cycle_s = 0.8
    venv = make_vec(
        [
            (RX, {"worker": {"ray": {"node_id": cluster["head_id"]}}}),
            (RX, {"worker": {"ray": {"resources": {"spare_pc": 1}}}}),
        ],
        backend="ray",
        clock="wall",
        action_cycle_s=cycle_s,
        call_timeout_s=30.0,
    )
    killed: list[float] = []

    def kill_node(at: float) -> None:
        time.sleep(max(0.0, at - time.monotonic()))
        killed.append(time.monotonic())
        c.remove_node(spare, allow_graceful=False)  # the node's raylet and its processes are SIGKILLed

    try:
        venv.reset(seed=0)
        node = venv._sup.workers[1].process.node_id
        assert node == spare.node_id
        action = np.zeros((2, 5), np.float32)
        venv.step(action)
        killer = threading.Thread(target=kill_node, args=(time.monotonic() + 0.3,))
        killer.start()
        try:
            with pytest.raises(WorkerError) as err:
                for _ in range(3):
                    venv.step(action)
            raised = time.monotonic()
        finally:
            killer.join()
        took = raised - killed[0]
        assert err.value.index == 1
        msg = str(err.value)
        assert node[:12] in msg and "lost" in msg and "within" not in msg, msg  # the hang-up, not a timeout
        assert took < cycle_s, f"reported {took:.3f} s after the kill; the action cycle is {cycle_s} s"
    finally:
        venv.close()
