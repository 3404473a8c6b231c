"""stable-baselines3's own VecEnv tests, run against ``make_vec(...).as_sb3()``, with SB3's wrappers on top.

Adapted from stable-baselines3's tests/test_vec_envs.py (https://github.com/DLR-RM/stable-baselines3, MIT License,
Copyright (c) 2019 Antonin Raffin). Each test runs on ``.as_sb3()`` and, where it compares, on SB3's DummyVecEnv
made of the same envs in the same test.

Differences on purpose, each said where it is tested:
- envs are given by id (each worker builds its env from it), so the test envs are registered by ``_sb3_envs``
  (test_sb3_vec_envs.py runs SB3's tests with their env factories);
- SubprocVecEnv's start methods are not tested: ``make_vec`` starts its workers its own way
  (``python -m uniros_async.runtime``);
- a real-time uniros env (wall clock) returns on its action cycle's deadline, not when stepped; these tests use
  turn-based envs, as SB3's do.
"""

from __future__ import annotations

import collections
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from _sb3_envs import CUSTOM, MONITORED, STEP, CustomGymEnv, StepEnv
from gymnasium import spaces
from gymnasium.utils.env_checker import data_equivalence
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import (
    DummyVecEnv,
    VecFrameStack,
    VecMonitor,
    VecNormalize,
    VecVideoRecorder,
)

from uniros_async.runtime import make_vec

pytestmark = pytest.mark.slow

N_ENVS = 3
VEC_ENV_WRAPPERS = [None, VecNormalize, VecFrameStack]
BOX2 = spaces.Box(low=np.zeros(2, np.float32), high=np.ones(2, np.float32))


def _sb3(env_id: str, n: int = N_ENVS, **kwargs: Any) -> Any:
    return make_vec([env_id] * n, **kwargs).as_sb3()


def _wrap(vec_env: Any, wrapper: Any) -> Any:
    if wrapper is None:
        return vec_env
    if wrapper is VecFrameStack:
        return wrapper(vec_env, n_stack=2)
    return wrapper(vec_env)


@pytest.mark.parametrize("vec_env_wrapper", VEC_ENV_WRAPPERS)
def test_vecenv_custom_calls(vec_env_wrapper: Any) -> None:
    """Methods and attributes through the VecEnv: seed, render, set_attr/get_attr/has_attr, env_method with
    indices (negative ones too), options."""
    vec_env = _wrap(_sb3(MONITORED, space=BOX2), vec_env_wrapper)
    try:
        vec_env.seed(0)
        array_explicit_mode = vec_env.render(mode="rgb_array")
        array_implicit_mode = vec_env.render()
        assert array_explicit_mode is not None and np.array_equal(array_implicit_mode, array_explicit_mode)
        with pytest.warns(UserWarning):
            vec_env.render(mode="something_else")

        assert not vec_env.has_attr("dummy")
        vec_env.set_attr("dummy", 12)
        assert vec_env.get_attr("dummy") == [12] * N_ENVS
        assert not vec_env.has_attr("dummy2")
        vec_env.env_method("set_wrapper_attr", "dummy2", 2)
        assert vec_env.get_attr("dummy2") == [2] * N_ENVS

        env_method_results = vec_env.env_method("custom_method", 1, indices=None, dim_1=2)
        setattr_results = [vec_env.set_attr("dummy1", env_idx, indices=env_idx) for env_idx in range(N_ENVS)]
        assert vec_env.has_attr("dummy1")
        getattr_results = vec_env.get_attr("dummy1")
        assert len(env_method_results) == len(setattr_results) == len(getattr_results) == N_ENVS
        for env_idx in range(N_ENVS):
            assert (env_method_results[env_idx] == np.ones((1, 2))).all()
            assert setattr_results[env_idx] is None
            assert getattr_results[env_idx] == env_idx

        env_method_subset = vec_env.env_method("custom_method", 1, indices=[0, 2], dim_1=3)
        assert len(env_method_subset) == 2 and all((r == np.ones((1, 3))).all() for r in env_method_subset)
        assert vec_env.set_attr("dummy1", 42, indices=None) is None
        assert vec_env.get_attr("dummy1") == [42] * N_ENVS

        vec_env.reset()
        assert vec_env.env_method("set_wrapper_attr", "current_step", 12, indices=[0, 1]) == [True, True]
        assert vec_env.get_attr("current_step") == [12, 12] + [0] * (N_ENVS - 2)
        assert vec_env.get_attr("current_step", indices=[0, 1]) == [12, 12]
        assert vec_env.get_attr("current_step", indices=[0, 2]) == [12, 0]
        assert vec_env.get_attr("current_step", indices=[2, 0]) == [0, 12]  # in the order asked
        vec_env.reset()
        assert vec_env.env_method("set_wrapper_attr", "current_step", 12, indices=[0, -1]) == [True, True]
        assert vec_env.get_attr("current_step") == [12] + [0] * (N_ENVS - 2) + [12]
        assert vec_env.get_attr("current_step", indices=[-1]) == [12]

        assert vec_env.get_attr("current_options")[0] is None
        options = {"hello": 1}
        vec_env.set_options(options)
        assert vec_env.get_attr("current_options")[0] is None
        vec_env.reset()
        assert vec_env.get_attr("current_options") == [options] * N_ENVS
        vec_env.reset()
        assert vec_env.get_attr("current_options")[0] is None
        options_list = [{"hello": 1}] * N_ENVS
        options_list[0] = {"other_option": 2}
        vec_env.set_options(options_list)
        vec_env.reset()
        assert vec_env.get_attr("current_options") == options_list
    finally:
        vec_env.close()


@pytest.mark.parametrize("vec_env_wrapper", VEC_ENV_WRAPPERS)
def test_vecenv_terminal_obs(vec_env_wrapper: Any) -> None:
    """'terminal_observation' is in the info of the step that ended the episode (and only there)."""
    step_nums = [i + 5 for i in range(N_ENVS)]
    vec_env = _wrap(make_vec([(STEP, {"max_steps": n}) for n in step_nums]).as_sb3(), vec_env_wrapper)
    try:
        zero_acts = np.zeros((N_ENVS,), dtype="int")
        prev_obs_b = vec_env.reset()
        for step_num in range(1, max(step_nums) + 1):
            obs_b, _, done_b, info_b = vec_env.step(zero_acts)
            assert len(obs_b) == len(done_b) == len(info_b) == N_ENVS
            for prev_obs, obs, done, info, final_step_num in zip(prev_obs_b, obs_b, done_b, info_b, step_nums):  # noqa: B905
                assert done == (step_num == final_step_num)
                if not done:
                    assert "terminal_observation" not in info
                else:
                    terminal_obs = info["terminal_observation"]
                    assert np.all(prev_obs < terminal_obs)
                    assert np.all(obs < prev_obs)
                    assert info["TimeLimit.truncated"] is True
                    if not isinstance(vec_env, VecNormalize):
                        assert np.all(prev_obs + 1 == terminal_obs)
                        assert np.all(obs == 0)
            prev_obs_b = obs_b
    finally:
        vec_env.close()


def test_terminal_obs_and_infos_equal_dummy_vec_env() -> None:
    """The same envs under DummyVecEnv and .as_sb3(): equal observations, rewards, dones, infos and reset_infos."""
    step_nums = [i + 2 for i in range(N_ENVS)]
    ours = make_vec([(STEP, {"max_steps": n}) for n in step_nums]).as_sb3()
    dummy = DummyVecEnv([lambda n=n: StepEnv(n) for n in step_nums])  # type: ignore[misc]
    try:
        assert np.array_equal(ours.reset(), dummy.reset())
        for _ in range(7):
            a = np.zeros((N_ENVS,), dtype="int")
            o1, r1, d1, i1 = ours.step(a)
            o2, r2, d2, i2 = dummy.step(a)
            assert np.array_equal(o1, o2) and np.array_equal(r1, r2) and np.array_equal(d1, d2)
            assert r1.dtype == r2.dtype and d1.dtype == d2.dtype
            assert data_equivalence(i1, i2), (i1, i2)
            assert ours.reset_infos == dummy.reset_infos
    finally:
        ours.close()
        dummy.close()


SPACES = collections.OrderedDict(
    [
        ("discrete", spaces.Discrete(2)),
        ("multidiscrete", spaces.MultiDiscrete([2, 3])),
        ("multibinary", spaces.MultiBinary(3)),
        ("continuous", spaces.Box(low=np.zeros(2, dtype=np.float32), high=np.ones(2, dtype=np.float32))),
    ]
)


def _check_vecenv_spaces(space: spaces.Space[Any], obs_assert: Any) -> None:
    vec_env = _sb3(CUSTOM, space=space)
    try:
        obs = vec_env.reset()
        obs_assert(obs)
        dones = [False] * N_ENVS
        while not any(dones):
            actions = [vec_env.action_space.sample() for _ in range(N_ENVS)]
            obs, _rews, dones, _infos = vec_env.step(actions)
            obs_assert(obs)
    finally:
        vec_env.close()


def _check_vecenv_obs(obs: Any, space: spaces.Space[Any]) -> None:
    assert obs.shape[0] == N_ENVS
    for value in obs:
        assert space.contains(value)


@pytest.mark.parametrize("space", SPACES.values(), ids=list(SPACES))
def test_vecenv_single_space(space: spaces.Space[Any]) -> None:
    _check_vecenv_spaces(space, lambda obs: _check_vecenv_obs(obs, space))


def test_vecenv_dict_spaces() -> None:
    space = spaces.Dict(SPACES)

    def obs_assert(obs: Any) -> None:
        assert isinstance(obs, dict) and obs.keys() == space.spaces.keys()
        for key, values in obs.items():
            _check_vecenv_obs(values, space.spaces[key])

    _check_vecenv_spaces(space, obs_assert)


def test_vecenv_tuple_spaces() -> None:
    space = spaces.Tuple(tuple(SPACES.values()))

    def obs_assert(obs: Any) -> None:
        assert isinstance(obs, tuple) and len(obs) == len(space.spaces)
        for values, inner_space in zip(obs, space.spaces, strict=True):
            _check_vecenv_obs(values, inner_space)

    _check_vecenv_spaces(space, obs_assert)


def test_framestack_vecenv() -> None:
    """VecFrameStack stacks on the channel axis of an image observation."""
    image_space_shape = [12, 8, 3]
    image_space = spaces.Box(low=0, high=255, shape=image_space_shape, dtype=np.uint8)
    vec_env = VecFrameStack(_sb3(CUSTOM, space=image_space), n_stack=2)
    try:
        obs, _, _, _ = vec_env.step(np.zeros([N_ENVS, *image_space_shape]))
        assert obs.shape[-1] == image_space_shape[-1] * 2
    finally:
        vec_env.close()


def test_vec_env_is_wrapped() -> None:
    """Answered by each worker's env: only the second is under Monitor."""
    vec_env = make_vec([(CUSTOM, {"space": BOX2}), (MONITORED, {"space": BOX2})]).as_sb3()
    try:
        assert vec_env.env_is_wrapped(Monitor) == [False, True]
        assert vec_env.env_is_wrapped(Monitor, indices=-1) == [True]
        vec_env = VecFrameStack(vec_env, n_stack=2)
        assert vec_env.env_is_wrapped(Monitor) == [False, True]
    finally:
        vec_env.close()


def test_vec_deterministic() -> None:
    vec_env = _sb3(CUSTOM, space=BOX2)
    try:
        vec_env.seed(3)
        obs = vec_env.reset()
        vec_env.seed(3)
        new_obs = vec_env.reset()
        assert np.allclose(new_obs, obs)
        vec_normalize = VecNormalize(vec_env)
        vec_normalize.seed(3)
        obs = vec_env.reset()
        vec_normalize.seed(3)
        new_obs = vec_env.reset()
        assert np.allclose(new_obs, obs)
    finally:
        vec_env.close()
    vec_env_1 = _sb3("Pendulum-v1")
    vec_env_2 = _sb3("Pendulum-v1")
    try:
        vec_env_1.seed(0)
        vec_env_2.seed(0)
        assert np.allclose(vec_env_1.reset(), vec_env_2.reset())
        random_actions = [vec_env_1.action_space.sample() for _ in range(N_ENVS)]
        assert np.allclose(vec_env_1.step(random_actions)[0], vec_env_2.step(random_actions)[0])
    finally:
        vec_env_1.close()
        vec_env_2.close()


def test_vec_seeding() -> None:
    vec_env = _sb3(CUSTOM, space=BOX2)
    try:
        vec_env.seed()
        obs = vec_env.reset()
        _, rewards, _, _ = vec_env.step(np.array([vec_env.action_space.sample() for _ in range(N_ENVS)]))
        assert not np.allclose(obs[0], obs[1]) and not np.allclose(obs[1], obs[2])
        assert not np.allclose(rewards[0], rewards[1]) and not np.allclose(rewards[1], rewards[2])
    finally:
        vec_env.close()


def test_render_rgb_array_under_wrappers() -> None:
    """SB3's test_render, rgb_array half (the human half needs an X server there too)."""
    vec_env = _sb3("Pendulum-v1", n=2, render_mode="rgb_array")
    try:
        vec_env.reset()
        images = vec_env.get_images()
        assert len(images) == 2 and all(isinstance(i, np.ndarray) and i.ndim == 3 for i in images)
        tiled = vec_env.render()
        assert isinstance(tiled, np.ndarray) and tiled.ndim == 3
        with pytest.warns(UserWarning):
            vec_env.render(mode="blah")
        for _ in range(3):
            vec_env.step([vec_env.action_space.sample() for _ in range(2)])
            vec_env.render()
        vec_env = VecFrameStack(vec_env, 2)
        vec_env.render()
        assert vec_env.render_mode == "rgb_array"
        vec_env = VecNormalize(vec_env)
        assert vec_env.render_mode == "rgb_array"
        vec_env.render()
    finally:
        vec_env.close()


def test_vec_monitor_and_video_recorder(tmp_path: Path) -> None:
    """VecMonitor counts the episodes; VecVideoRecorder writes a video of the frames get_images returns."""
    vec_env = VecMonitor(_sb3(CUSTOM, space=BOX2))
    try:
        vec_env.reset()
        infos: list[dict[str, Any]] = []
        for _ in range(4):
            _, _, _, infos = vec_env.step(np.zeros((N_ENVS, 2)))
        assert all(info["episode"]["l"] == 4 for info in infos)  # CustomGymEnv's episodes are 4 steps
    finally:
        vec_env.close()
    pendulum = _sb3("Pendulum-v1", n=2, render_mode="rgb_array")
    rec_env = VecVideoRecorder(pendulum, str(tmp_path), lambda step: step == 0, video_length=5)
    try:
        rec_env.reset()
        for _ in range(6):
            rec_env.step(np.zeros((2, 1), np.float32))
    finally:
        rec_env.close()
    videos = list(tmp_path.glob("*.mp4"))
    assert len(videos) == 1 and videos[0].stat().st_size > 1000


def test_custom_gym_env_is_the_one_sb3_tests() -> None:
    """The env the workers build is SB3's test env (its class, its episode length)."""
    vec_env = _sb3(CUSTOM, n=1, space=BOX2)
    try:
        assert vec_env.get_attr("ep_length") == [CustomGymEnv(BOX2).ep_length]
    finally:
        vec_env.close()
