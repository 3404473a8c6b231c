"""make(): one env in a worker process; bad input in the caller; worker exceptions as WorkerError."""

from __future__ import annotations

import os
import time

import gymnasium as gym
import numpy as np
import pytest
from _children import children

from uniros_async.errors import ConfigError, WorkerError
from uniros_async.runtime import ProxyEnv, make, make_vec
from uniros_async.tasks.registry import ENV_IDS

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("env_id", list(ENV_IDS))
def test_make_resets_steps_and_closes_every_id(env_id: str) -> None:
    env = make(env_id, clock="sim")
    try:
        assert isinstance(env, ProxyEnv)
        reference = gym.make(env_id, clock="sim")
        try:
            assert env.observation_space == reference.observation_space
            assert env.action_space == reference.action_space
        finally:
            reference.close()
        obs, info = env.reset(seed=0)
        assert env.observation_space.contains(obs), obs
        assert "env_id" not in info  # the env's own info: one env needs no tag saying which it is
        for _ in range(3):
            obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
            assert env.observation_space.contains(obs)
            assert isinstance(reward, float) and isinstance(terminated, bool) and isinstance(truncated, bool)
        pid = env.pid
    finally:
        t0 = time.monotonic()
        env.close()
        env.close()  # idempotent
        assert time.monotonic() - t0 < 10.0
    assert pid is not None
    assert not any(p.pid == pid for p in children())
    with pytest.raises(gym.error.ClosedEnvironmentError):
        env.step(env.action_space.sample())


def test_in_process_returns_the_plain_env() -> None:
    env = make("uniros/Rx200Reach-v0", in_process=True, clock="sim")
    try:
        assert not isinstance(env, ProxyEnv)
        assert env.unwrapped.__class__.__name__ == "ReachEnv"
    finally:
        env.close()


def test_unknown_id_and_kwarg_fail_in_the_caller_before_any_process() -> None:
    before = set(children())
    with pytest.raises(ConfigError, match="uniros/Rx200Reach-v0") as e:
        make("uniros/Rx300Reach-v0")
    assert "unknown env id" in str(e.value)
    with pytest.raises(ConfigError, match="reward_type") as e:
        make("uniros/Rx200Reach-v0", rewardtype="dense")
    assert "rewardtype" in str(e.value)
    with pytest.raises(ConfigError, match="clock"):
        make("uniros/Rx200Reach-v0", clock="fast")
    assert set(children()) == before


def test_a_worker_placement_other_than_ray_fails_in_the_caller_pointing_at_the_cluster_howto() -> None:
    before = set(children())
    with pytest.raises(ConfigError, match="run on Ray") as e:  # a worker on another host is Ray's job
        make("uniros/Rx200Reach-v0", worker="tcp://127.0.0.1:7000")
    assert "tcp://127.0.0.1:7000" in str(e.value) and "docs/howto/cluster.md" in str(e.value)
    with pytest.raises(ConfigError, match="run on Ray"):
        make_vec([("CartPole-v1", {"worker": "tcp://10.0.0.5:7000"}), "CartPole-v1"])
    with pytest.raises(ConfigError, match="worker must be None") as e:
        make("CartPole-v1", worker={"uri": "tcp://127.0.0.1:7000"})
    assert "docs/howto/cluster.md" in str(e.value) and "'uri'" in str(e.value)
    # kwargs that go to another node must be plain data: checked before Ray is asked for anything
    with pytest.raises(ConfigError, match="plain data") as e:
        make("uniros/Rx200Reach-v0", worker="ray", clock=object())
    assert "'clock'" in str(e.value)
    assert set(children()) == before


def test_env_construction_error_comes_back_with_traceback() -> None:
    with pytest.raises(WorkerError) as e:
        make("uniros/Rx200Reach-v0", clock="sim", goal_min=[0.3, 0.0, 0.1])  # above the arm's default goal_max
    assert e.value.index == 0
    assert "goal_min/goal_max: min must be <= max on every axis" in str(e.value)
    assert "ConfigError" in e.value.remote_traceback and "reach.py" in e.value.remote_traceback
    assert children() == []


def test_step_error_comes_back_and_the_env_stays_usable() -> None:
    env = make("uniros/Rx200Reach-v0", clock="sim")
    try:
        env.reset(seed=1)
        with pytest.raises(WorkerError) as e:
            env.step(np.zeros(3, dtype=np.float32))
        assert e.value.index == 0
        assert "InvalidAction" in str(e.value)
        assert "Traceback" in e.value.remote_traceback and "_validate_action" in e.value.remote_traceback
        obs, *_ = env.step(np.zeros(5, dtype=np.float32))
        assert obs.shape == (28,)
    finally:
        env.close()


def test_a_synchronous_envs_step_errors_come_back_and_the_worker_keeps_serving() -> None:
    """The worker's step lane for an env it steps synchronously (CartPole): an action the env refuses and a
    malformed step frame each come back as an error reply, and the next step is served as usual."""
    from uniros_async.runtime import make_vec
    from uniros_async.runtime.protocol import STEP_TAG, unpack

    venv = make_vec(["CartPole-v1"], pad=False)
    try:
        venv.reset(seed=0)
        with pytest.raises(WorkerError, match="step failed: AssertionError") as e:
            venv.step(np.array([5]))  # Discrete(2)
        assert e.value.index == 0 and "cartpole" in e.value.remote_traceback.lower()
        w = venv._sup.workers[0]

        async def raw(frame: bytes) -> dict:
            await w.transport.send(frame)
            return unpack(await w.transport.receive())

        reply = venv._sup.call(raw(bytes([STEP_TAG, 1, 0])))
        assert reply["ok"] is False and "bad request" in reply["error"] and "malformed step frame" in reply["error"]
        obs, rew, term, trunc, info = venv.step(np.array([1]))
        assert obs.shape == (1, 4) and rew[0] == 1.0 and "env_id" not in info
    finally:
        venv.close()


def test_a_users_own_env_as_module_colon_id_runs_in_its_worker() -> None:
    """gymnasium's "module:Id" form: the module, which registers Id, is imported in the caller (to check the id) and
    in the worker (a fresh interpreter, where only the uniros ids are registered by themselves)."""
    from uniros_async.runtime import make_vec

    venv = make_vec(["_custom_env:UnirosTestMarkedCartPole-v0", "CartPole-v1"], pad=False)
    try:
        venv.reset(seed=0)
        _, _, _, _, infos = venv.step(np.array([0, 1]))
        assert infos["_stepped_by_pid"].tolist() == [True, False]  # only the custom env has the key
        assert infos["stepped_by_pid"][0] == venv.pids[0]  # and it ran in its own worker
        assert infos["env_id"].tolist() == ["_custom_env:UnirosTestMarkedCartPole-v0", "CartPole-v1"]
    finally:
        venv.close()


def test_a_worker_freezes_what_it_built_out_of_the_collectors_reach() -> None:
    """A full collection walks only what a worker made after its env was built: on a worker that runs a real-time
    env loop, a walk of the whole heap (~15 ms for a reach env) would delay the ticks due meanwhile."""
    from uniros_async.runtime import make_vec

    venv = make_vec(["_custom_env:UnirosTestMarkedCartPole-v0"], pad=False)
    try:
        venv.reset(seed=0)
        venv.step(np.array([0]))
        ((frozen, walked),) = venv.call("gc_state")
        assert frozen > 10_000, f"only {frozen} objects frozen in the worker"  # the modules, the env
        assert walked < frozen / 4, f"the collector still walks {walked} objects beside {frozen} frozen"
    finally:
        venv.close()


def test_a_module_colon_id_whose_module_is_missing_fails_in_the_caller() -> None:
    before = set(children())
    with pytest.raises(ConfigError, match=r"cannot import 'no_such_module_here'.*'Thing-v0'"):
        make("no_such_module_here:Thing-v0")
    with pytest.raises(ConfigError, match=r"unknown env id '_custom_env:Nope-v0'.*'module:Id'"):
        make("_custom_env:Nope-v0")  # the module imports, but registers no such id
    assert set(children()) == before


def test_an_env_registered_only_in_the_caller_is_registered_in_its_worker_too() -> None:
    """An id registered in this process only (here, inside the test), with an entry point in an importable module:
    the worker, a fresh interpreter where the id does not exist, registers it as this process has it (its
    max_episode_steps included) and steps it."""
    from gymnasium.envs.classic_control.cartpole import CartPoleEnv

    env_id = "UnirosTestRegisteredHereOnly-v0"
    gym.register(env_id, entry_point=CartPoleEnv, max_episode_steps=3)
    try:
        before = set(children())
        env = make(env_id)
        try:
            env.reset(seed=0)
            truncated = [env.step(0)[3] for _ in range(3)]
            assert truncated == [False, False, True]  # the caller's max_episode_steps, applied in the worker
            assert env.pid != os.getpid()
        finally:
            env.close()
        assert set(children()) == before  # the worker is gone
    finally:
        del gym.registry[env_id]
