"""make_vec(..., backend="ray") on a real two-node Ray cluster: placement, the step link, bad input."""

from __future__ import annotations

import os
import subprocess
import sys
from typing import Any

import numpy as np
import pytest
from _processes import pid_alive

from uniros_async.errors import ConfigError, WorkerError
from uniros_async.runtime import make, make_vec

RX, NED = "uniros/Rx200Reach-v0", "uniros/Ned2Reach-v0"
ARM = {"worker": {"ray": {"resources": {"rx200_arm": 1}}}}

pytestmark = pytest.mark.usefixtures("nothing_left")


def test_rx200_pinned_to_the_arm_node_and_ned2_placed_by_ray(cluster: dict[str, Any]) -> None:
    venv = make_vec([(RX, ARM), NED], backend="ray", clock="sim")
    try:
        workers = venv._sup.workers
        assert workers[0].process.node_id == cluster["arm_id"]  # the resource only the arm node has
        # the arm node is not the agent's: tcp with the vector env's key; any worker on the agent's node: shm
        assert workers[0].process.worker_uri.startswith("tcp://127.0.0.1:")
        for w in workers:
            expected = "shm://" if w.process.node_id == cluster["head_id"] else "tcp://"
            assert w.process.worker_uri.startswith(expected)
            assert w.process.placement.auth_key is not None and len(w.process.placement.auth_key) == 32
        obs, _ = venv.reset(seed=0)
        assert obs.shape == (2, 28)  # padded to the larger of the two
        for _ in range(5):
            obs, rewards, terminated, truncated, info = venv.step(np.zeros((2, 6), np.float32))
        assert obs.shape == (2, 28) and np.isfinite(obs).all() and np.isfinite(rewards).all()
        pids = [p for p in venv.pids if p is not None]
        assert len(pids) == 2 and all(pid_alive(p) for p in pids)
    finally:
        venv.close()
    assert not any(pid_alive(p) for p in pids)


def test_a_node_id_pins_a_worker_and_make_takes_the_backend(cluster: dict[str, Any]) -> None:
    env = make("CartPole-v1", backend="ray", worker={"ray": {"node_id": cluster["head_id"]}})
    try:
        assert env._worker.process.node_id == cluster["head_id"]
        assert env._worker.process.worker_uri.startswith("shm://")  # the agent's own node
        env.reset(seed=0)
        _, reward, *_ = env.step(0)
        assert reward == 1.0
    finally:
        env.close()


def test_a_resource_no_node_has_is_named_with_the_nodes_resources_before_anything_starts() -> None:
    with pytest.raises(ConfigError) as err:
        make_vec(["CartPole-v1", ("CartPole-v1", {"worker": {"ray": {"resources": {"ur5_arm": 1}}}})], backend="ray")
    msg = str(err.value)
    assert "ur5_arm" in msg and "rx200_arm" in msg and "CPU" in msg


def test_a_wrong_env_id_or_kwarg_is_the_local_error_raised_in_the_caller() -> None:
    for bad in [("uniros/NoSuchArm-v0", {}), (RX, {"no_such_kwarg": 1})]:
        with pytest.raises(ConfigError) as local:
            make_vec([bad], clock="sim")
        with pytest.raises(ConfigError) as on_ray:
            make_vec([bad], clock="sim", backend="ray")
        assert str(on_ray.value) == str(local.value)


def test_a_module_the_node_cannot_import_is_named_with_the_node() -> None:
    with pytest.raises(ConfigError) as err:
        make_vec([("uniros_no_such_module:Thing-v0", ARM)], backend="ray")
    msg = str(err.value)
    assert "uniros_no_such_module" in msg and "Ray node" in msg and "127.0.0.1" in msg


def test_no_cluster_at_the_address_fails_fast_naming_it() -> None:
    code = (
        "from uniros_async.runtime import make_vec\n"
        "try:\n"
        "    make_vec([('CartPole-v1', {'worker': {'ray': {'address': '127.0.0.1:1'}}})])\n"
        "except Exception as exc:\n"
        "    print(type(exc).__name__, exc)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=env, check=True)
    assert "ConfigError" in out.stdout and "127.0.0.1:1" in out.stdout, out.stdout + out.stderr


def test_a_resource_that_is_taken_fails_after_the_start_timeout_naming_it(cluster: dict[str, Any]) -> None:
    # the arm node has one rx200_arm: the second spec's actor can never be placed while the first holds it
    with pytest.raises(WorkerError) as err:
        make_vec([("CartPole-v1", ARM), ("CartPole-v1", ARM)], backend="ray", start_timeout_s=5.0)
    msg = str(err.value)
    assert "within 5" in msg and "rx200_arm" in msg and cluster["arm_id"][:12] in msg, msg


def test_envs_grouped_in_one_ray_placed_process_each_over_its_own_connection(cluster: dict[str, Any]) -> None:
    venv = make_vec([(RX, ARM), (RX, ARM), RX], backend="ray", clock="sim", envs_per_worker=2)
    try:
        workers = venv._sup.workers
        first, second, third = workers
        assert first.process is second.process and third.process is not first.process  # one actor, one process
        assert first.process.node_id == cluster["arm_id"]
        uris = first.process.worker_uris
        assert len(uris) == 2 and uris[0] != uris[1] and all(u.startswith("tcp://127.0.0.1:") for u in uris)
        assert venv.pids[0] == venv.pids[1] != venv.pids[2]
        venv.reset(seed=0)
        for _ in range(3):
            obs, rewards, *_ = venv.step(np.zeros((3, 5), np.float32))
        assert obs.shape[0] == 3 and np.isfinite(obs).all() and np.isfinite(rewards).all()
        pids = [p for p in set(venv.pids) if p is not None]
        assert len(pids) == 2 and all(pid_alive(p) for p in pids)
    finally:
        venv.close()
    assert not any(pid_alive(p) for p in pids)


def test_pixel_envs_on_the_arm_node_and_placed_by_ray_batch_their_frames(cluster: dict[str, Any]) -> None:
    pix = "uniros/Rx200ReachPixels-v0"  # each env renders its arm's scene camera where Ray placed it
    venv = make_vec([(pix, ARM), pix], backend="ray", clock="sim", image_size=(48, 48))
    try:
        workers = venv._sup.workers
        assert workers[0].process.node_id == cluster["arm_id"]
        for w in workers:
            expected = "shm://" if w.process.node_id == cluster["head_id"] else "tcp://"
            assert w.process.worker_uri.startswith(expected)
        obs, info = venv.reset(seed=[1, 2])
        assert obs["pixels"].shape == (2, 48, 48, 3) and obs["pixels"].dtype == np.uint8
        assert obs["state"].shape == (2, 24)
        px = obs["pixels"].astype(int)
        red = (px[..., 0] > 150) & (px[..., 1] < 80) & (px[..., 2] < 80)
        assert red.reshape(2, -1).sum(axis=1).min() > 2  # each frame shows its episode's target
        assert not np.array_equal(obs["pixels"][0], obs["pixels"][1])  # two goals, two pictures
        for _ in range(3):
            obs, rewards, terminated, truncated, info = venv.step(venv.action_space.sample())
        assert obs["pixels"].shape == (2, 48, 48, 3) and np.isfinite(rewards).all()
        assert np.all(info["frame_age_s"] <= 0.1) and not np.any(info["frame_stale"])
    finally:
        venv.close()
