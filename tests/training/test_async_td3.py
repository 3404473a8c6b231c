"""AsyncTD3: updates beside collection, pacing, snapshot acting, errors, save/load, HER, TD3's update unchanged.

Real envs (``clock="sim"``, ~100 steps/s), real SB3 and torch; small networks so the file stays within ~30 s on
two busy cores. Timing figures (action-cycle IQR against SB3's TD3) belong to the latency benchmark, not here.
"""

from __future__ import annotations

import math
import signal
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3 import TD3, HerReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback, CheckpointCallback
from stable_baselines3.common.logger import configure

import uniros_async
from uniros_async.errors import ConfigError
from uniros_async.training.async_td3 import AsyncTD3
from uniros_async.training.her import LocalGoalReward

pytestmark = pytest.mark.slow

RX, RX_GOAL = "uniros/Rx200Reach-v0", "uniros/Rx200ReachGoal-v0"
SMALL = dict(learning_starts=50, batch_size=64, buffer_size=20_000, policy_kwargs=dict(net_arch=[64, 64]), seed=0)


def _learner_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "uniros-async-td3-learner"]


@pytest.fixture(autouse=True)
def _one_torch_thread_and_no_leftover_learner() -> Iterator[None]:
    torch.set_num_threads(1)
    yield
    assert _learner_threads() == [], "a learner thread outlived learn()"


@pytest.fixture(scope="module")
def env() -> Iterator[gym.Env[Any, Any]]:
    e = gym.make(RX, clock="sim")
    yield e
    e.close()


class _Pacing(BaseCallback):
    """Records, at every step (in the actor thread), env steps and the learner's updates so far."""

    def __init__(self) -> None:
        super().__init__()
        self.rows: list[tuple[int, int, int]] = []

    def _on_step(self) -> bool:
        rt = self.model._rt
        self.rows.append((self.model.num_timesteps, rt.updates, rt.swaps))
        return True


def test_learner_updates_beside_collection_and_actor_never_waits_on_a_gradient_step(env: gym.Env[Any, Any]) -> None:
    # paper-sized networks: one update takes several ms, so a wait behind one would show in the lock waits
    model = AsyncTD3(
        "MlpPolicy",
        env,
        learning_starts=30,
        batch_size=256,
        buffer_size=5_000,
        policy_kwargs=dict(net_arch=[400, 300]),
        seed=0,
        sync_every=1,
    )
    pacing = _Pacing()
    model.learn(150, callback=pacing)
    s = model.learner_stats
    assert s["env_steps"] == 150
    assert s["updates"] > 0 and s["snapshot_swaps"] > 0
    # updates happened while the actor was still stepping, not only at the end
    mid = [u for steps, u, _ in pacing.rows if steps < 140]
    assert max(mid) > 0
    assert model._n_updates == s["updates"]
    # the actor took locks every step, and never for anything near an update's duration
    assert s["actor_lock_waits"] >= 3 * 120
    assert s["actor_lock_wait_median_us"] < 100
    # a wait behind an update would take about an update's time: allow the odd one a busy host deschedules
    long_waits = sum(w > 0.5 * s["update_ms_mean"] * 1e6 for w in model._rt.waits_ns)
    assert long_waits <= 0.01 * len(model._rt.waits_ns), (long_waits, s)
    # the snapshot holds the learner's weights (it swapped at its last update, sync_every=1)
    snap = model._rt.snapshots[model._rt.current]
    for a, b in zip(snap.state_dict().values(), model.actor.state_dict().values(), strict=True):
        torch.testing.assert_close(a, b)


@pytest.mark.parametrize("updates_per_step", [0.5, 1.0])
def test_updates_follow_updates_per_step_and_never_run_ahead(env: gym.Env[Any, Any], updates_per_step: float) -> None:
    model = AsyncTD3("MlpPolicy", env, updates_per_step=updates_per_step, **SMALL)
    pacing = _Pacing()
    model.learn(200, callback=pacing)
    ls = SMALL["learning_starts"]
    for steps, updates, _ in pacing.rows:
        assert updates <= math.floor(updates_per_step * max(0, steps - ls)), (steps, updates)
    owed = math.floor(updates_per_step * (200 - ls))
    s = model.learner_stats
    assert 0.75 * owed <= s["updates"] <= owed, s
    assert s["updates_per_env_step"] == pytest.approx(s["updates"] / (200 - ls))


def test_learner_exception_is_raised_in_learn(env: gym.Env[Any, Any]) -> None:
    def schedule(progress_remaining: float) -> float:
        if progress_remaining < 1.0:  # only the learner's first update asks with progress < 1
            raise FloatingPointError("boom from the learning-rate schedule")
        return 1e-3

    model = AsyncTD3("MlpPolicy", env, learning_rate=schedule, **SMALL)
    with pytest.raises(FloatingPointError, match="boom") as info:
        model.learn(1_000)
    assert any("learner thread" in n for n in getattr(info.value, "__notes__", []))
    assert model.num_timesteps < 1_000  # collection stopped early, not at the end
    assert model.learner_stats["updates"] == 0


def test_ctrl_c_stops_actor_and_learner(env: gym.Env[Any, Any]) -> None:
    class CtrlC(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps == 70:  # the learner is busy by now
                signal.raise_signal(signal.SIGINT)
            return True

    model = AsyncTD3("MlpPolicy", env, **SMALL)
    # Python's own Ctrl-C handler, whatever an earlier test of the session left installed
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            model.learn(1_000, callback=CtrlC())
    finally:
        signal.signal(signal.SIGINT, old)
    assert model.num_timesteps == 70 and model.learner_stats["updates"] > 0
    assert not model._rt.active  # (and the autouse fixture checks the thread is gone)
    model.learn(60)  # usable again


def test_save_load_roundtrip_gives_the_same_actions(env: gym.Env[Any, Any], tmp_path: Path) -> None:
    model = AsyncTD3("MlpPolicy", env, updates_per_step=2.0, sync_every=3, **SMALL)
    # saving from a callback during learn pauses the learner for the write
    model.learn(120, callback=CheckpointCallback(save_freq=100, save_path=str(tmp_path / "ckpt"), name_prefix="m"))
    assert model.learner_stats["updates"] > 0
    model.save(tmp_path / "model.zip")
    obs = np.stack([env.observation_space.sample() for _ in range(16)])
    want, _ = model.predict(obs, deterministic=True)

    loaded = AsyncTD3.load(tmp_path / "model.zip", env=env)
    assert isinstance(loaded, AsyncTD3)
    assert (loaded.updates_per_step, loaded.sync_every) == (2.0, 3)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], want)
    np.testing.assert_array_equal(TD3.load(tmp_path / "model.zip").predict(obs, deterministic=True)[0], want)

    mid = AsyncTD3.load(tmp_path / "ckpt" / "m_100_steps.zip", env=env)
    assert mid.num_timesteps == 100 and 0 < mid._n_updates <= 2 * (100 - 50)
    loaded.learn(30, reset_num_timesteps=False)  # a loaded model learns on
    assert loaded.learner_stats["env_steps"] == 30 and loaded.learner_stats["updates"] > 0


def test_predict_during_learn_reads_the_snapshot(env: gym.Env[Any, Any]) -> None:
    seen: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    class Probe(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps in (60, 80, 95):
                model = self.model
                obs = model._last_obs
                with model.learner_paused():  # no update, so no swap, inside
                    snap = model._rt.snapshots[model._rt.current]
                    with torch.no_grad():
                        expected = model.policy.unscale_action(snap(torch.as_tensor(obs)).numpy())
                    seen.append((expected, model.predict(obs, deterministic=True)[0], model.predict(obs[0])[0]))
            return True

    model = AsyncTD3("MlpPolicy", env, **SMALL)
    model.learn(100, callback=Probe())
    assert len(seen) == 3
    for expected, batch, single in seen:
        np.testing.assert_array_equal(batch, expected)
        np.testing.assert_array_equal(single, expected[0])  # an unbatched observation gives an unbatched action


def test_her_goal_env_in_process(tmp_path: Path) -> None:
    env = gym.make(RX_GOAL, clock="sim", reward_type="sparse", max_episode_steps=25)
    try:
        model = AsyncTD3(
            "MultiInputPolicy",
            env,
            replay_buffer_class=HerReplayBuffer,
            replay_buffer_kwargs=dict(n_sampled_goal=4, goal_selection_strategy="future"),
            **SMALL,
        )
        model.learn(200)
        s = model.learner_stats
        assert s["updates"] > 0.75 * (200 - 50) and s["snapshot_swaps"] > 0
        assert not isinstance(model.replay_buffer.env, LocalGoalReward)  # DummyVecEnv: already local
    finally:
        env.close()


def test_her_over_a_worker_env_relabels_locally() -> None:
    venv = uniros_async.make_vec([(RX_GOAL, {"max_episode_steps": 20})], clock="sim").as_sb3()
    try:
        model = AsyncTD3(
            "MultiInputPolicy",
            venv,
            replay_buffer_class=HerReplayBuffer,
            replay_buffer_kwargs=dict(n_sampled_goal=4, goal_selection_strategy="future"),
            **{**SMALL, "learning_starts": 30},
        )
        model.learn(100)
        assert isinstance(model.replay_buffer.env, LocalGoalReward)
        assert model.learner_stats["updates"] > 0
    finally:
        venv.close()


def test_train_is_td3s_update(env: gym.Env[Any, Any]) -> None:
    """AsyncTD3.train copies TD3.train (plus locks): same buffer, same seeds, same weights after 6 updates."""
    kw = dict(SMALL, learning_starts=0)
    a, b = AsyncTD3("MlpPolicy", env, **kw), TD3("MlpPolicy", env, **kw)
    b.policy.load_state_dict(a.policy.state_dict())
    for m in (a, b):
        m.set_logger(configure(folder=None, format_strings=[]))
    rng = np.random.default_rng(0)
    for _ in range(100):
        o, o2 = env.observation_space.sample()[None], env.observation_space.sample()[None]
        act, r, d = rng.uniform(-1, 1, (1, 5)), rng.normal(size=1), rng.uniform(size=1) < 0.1
        for m in (a, b):
            m.replay_buffer.add(o, o2, act, r, d, [{}])
    for m in (a, b):
        m._current_progress_remaining = 0.5
        np.random.seed(1)
        torch.manual_seed(1)
        m.train(gradient_steps=6, batch_size=32)
    assert a._n_updates == b._n_updates == 6
    for x, y in zip(a.policy.state_dict().values(), b.policy.state_dict().values(), strict=True):
        torch.testing.assert_close(x, y, rtol=0, atol=0)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"updates_per_step": 0}, r"updates_per_step must be a finite number > 0, got 0"),
        ({"updates_per_step": float("nan")}, r"updates_per_step .* got nan"),
        ({"sync_every": 0}, r"sync_every must be an integer >= 1 .*got 0"),
        ({"torch_threads": 0}, r"torch_threads must be None or an integer >= 1, got 0"),
        ({"action_l2": -1.0}, r"action_l2 must be a finite number >= 0, got -1.0"),
    ],
)
def test_bad_async_settings_are_clear_errors(env: gym.Env[Any, Any], kwargs: dict[str, Any], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        AsyncTD3("MlpPolicy", env, **kwargs)
    assert issubclass(ConfigError, ValueError)


def test_learn_twice_at_once_is_refused(env: gym.Env[Any, Any]) -> None:
    errors: list[BaseException] = []

    class Reenter(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps == 5:
                try:
                    self.model.learn(10)
                except RuntimeError as exc:
                    errors.append(exc)
            return True

    AsyncTD3("MlpPolicy", env, **SMALL).learn(10, callback=Reenter())
    assert len(errors) == 1 and "already running" in str(errors[0])


@pytest.mark.parametrize("real_time_actor", [False, True])
def test_real_time_actor_raises_the_acting_thread_only_during_learn(
    env: gym.Env[Any, Any], real_time_actor: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    import os
    import sys

    monkeypatch.setenv("UNIROS_LOOP_PRIORITY", "rt")
    seen: list[tuple[float, int]] = []
    learner_policy: list[int] = []

    class _Probe(BaseCallback):
        def _on_step(self) -> bool:
            seen.append((sys.getswitchinterval(), os.sched_getscheduler(0)))
            return True

    before = (sys.getswitchinterval(), os.sched_getscheduler(0))
    model = AsyncTD3("MlpPolicy", env, real_time_actor=real_time_actor, **SMALL)  # type: ignore[arg-type]
    original = model.train

    def train(*args: Any, **kwargs: Any) -> None:
        learner_policy.append(os.sched_getscheduler(0))
        original(*args, **kwargs)

    monkeypatch.setattr(model, "train", train)
    model.learn(80, callback=_Probe())
    assert (sys.getswitchinterval(), os.sched_getscheduler(0)) == before, "restored after learn"
    switch = {s for s, _ in seen}
    if not real_time_actor:
        assert switch == {before[0]} and {p for _, p in seen} == {before[1]}
        return
    assert switch == {0.0005}
    try:  # SCHED_RR needs root or CAP_SYS_NICE: where refused, the actor keeps its class (and says nothing)
        os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(10))
        os.sched_setscheduler(0, *before[1:], os.sched_param(0))
        permitted = True
    except PermissionError:
        permitted = False
    if permitted:  # not handed on to threads or processes it starts (SCHED_RESET_ON_FORK)
        assert {p for _, p in seen} == {os.SCHED_RR | os.SCHED_RESET_ON_FORK}
    assert learner_policy and set(learner_policy) == {os.SCHED_OTHER}, "the learner computes at ordinary priority"


def test_action_l2_keeps_the_actor_out_of_saturation(env: gym.Env[Any, Any]) -> None:
    """The HER paper's action penalty: from the same weights and batches, the penalised actor's actions are smaller
    (the critic is fitted to rewards that grow with |action|, so without it the actor is pushed to the bounds)."""
    kw = dict(SMALL, learning_starts=0, policy_delay=1)
    rng = np.random.default_rng(0)
    data = []
    for _ in range(200):
        o, o2 = env.observation_space.sample()[None], env.observation_space.sample()[None]
        act = rng.uniform(-1, 1, (1, 5))
        data.append((o, o2, act, np.abs(act).sum(axis=1), np.zeros(1, bool)))
    mean_abs = {}
    for l2 in (0.0, 10.0):
        m = AsyncTD3("MlpPolicy", env, action_l2=l2, **kw)
        m.set_logger(configure(folder=None, format_strings=[]))
        for o, o2, act, r, d in data:
            m.replay_buffer.add(o, o2, act, r, d, [{}])
        m._current_progress_remaining = 0.5
        torch.manual_seed(1)
        np.random.seed(1)
        m.train(gradient_steps=150, batch_size=64)
        obs = torch.as_tensor(np.concatenate([o for o, *_ in data]))
        with torch.no_grad():
            mean_abs[l2] = float(m.actor(obs).abs().mean())
    assert mean_abs[0.0] > 0.5, mean_abs  # drawn toward the bounds by a reward that grows with |a|
    assert mean_abs[10.0] < 0.5 * mean_abs[0.0], mean_abs
