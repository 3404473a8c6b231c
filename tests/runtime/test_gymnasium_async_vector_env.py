"""Gymnasium's own AsyncVectorEnv tests, with ``make_vec(env_fns)`` where they construct an AsyncVectorEnv.

Copied from Gymnasium's tests/vector/test_async_vector_env.py (https://github.com/Farama-Foundation/Gymnasium, commit
3f0476a8c; MIT License, Copyright (c) 2016 OpenAI, (c) 2022 Farama Foundation) and adapted as little as makes them
run here:
- ``AsyncVectorEnv(env_fns, shared_memory=..., copy=..., autoreset_mode=...)`` below builds ``make_vec(env_fns,
  autoreset_mode=...)`` from the same env factories; ``shared_memory`` and ``copy`` are taken and not used (make_vec's
  workers always reply over shared memory, into a fresh array);
- a step that runs out of ``step_wait``'s timeout raises StepTimeoutError, a builtin TimeoutError, where
  AsyncVectorEnv raises multiprocessing's (the import of multiprocessing's TimeoutError is dropped);
- envs whose spaces cannot be combined raise ConfigError (a ValueError) naming them, where AsyncVectorEnv raises a
  RuntimeError (test_check_spaces_async_vector_env);
- a sub-env's exception comes back as WorkerError with the worker's traceback, not re-raised as itself after
  AsyncVectorEnv's warnings (test_async_vector_subenv_error checks the error and its text, not the warnings);
- left out: the tests of ``reset_async``/``reset_wait`` (test_reset_timeout_async_vector_env,
  test_reset_out_of_order_async_vector_env and the half of test_step_out_of_order_async_vector_env that calls them),
  AsyncVectorEnv's own pair, not gymnasium.vector.VectorEnv's; and the tests of CustomSpace
  (test_custom_space_async_vector_env, ..._shared_memory): make_vec's workers describe their spaces as plain data,
  which covers gymnasium's spaces only;
- this module's functions are pickled by value (``cloudpickle.register_pickle_by_value``), as gymnasium's
  CloudpickleWrapper pickles a factory defined in ``__main__``; the helpers are imported from copies of Gymnasium's
  tests/testing_env.py and tests/vector/testing_utils.py;
- ``shared_memory`` is parametrized with True only (the tests ran twice, for a parameter that is not used here);
- ``pytestmark``: the tests start worker processes; ruff's style checks are off for the copied text.
"""

# ruff: noqa

import re
import sys
import warnings

import cloudpickle
import numpy as np
import pytest

from gymnasium.error import (
    AlreadyPendingCallError,
    ClosedEnvironmentError,
    NoAsyncCallError,
)
from gymnasium.spaces import Box, Discrete, MultiDiscrete, Tuple
from gymnasium.vector import AutoresetMode
from _gym_testing_env import GenericTestEnv
from _gym_vector_testing_utils import (
    make_env,
    make_slow_env,
)

from uniros_async.errors import ConfigError, WorkerError
from uniros_async.runtime import make_vec

pytestmark = pytest.mark.slow
cloudpickle.register_pickle_by_value(sys.modules[__name__])


def AsyncVectorEnv(env_fns, shared_memory=True, copy=True, autoreset_mode=AutoresetMode.NEXT_STEP):
    """The vector env under test where Gymnasium's test constructs an AsyncVectorEnv: make_vec over the same
    factories."""
    return make_vec(env_fns, autoreset_mode=autoreset_mode)


@pytest.mark.parametrize("shared_memory", [True])
def test_create_async_vector_env(shared_memory):
    """Test creating an async vector environment with or without shared memory."""
    env_fns = [make_env("CartPole-v1", i) for i in range(8)]

    env = AsyncVectorEnv(env_fns, shared_memory=shared_memory)
    assert env.num_envs == 8
    env.close()


def test_metadata_async_vector_env():
    """Tests that the vector env's metadata doesn't mutate the sub-environment's (class-level) metadata."""
    envs_1 = AsyncVectorEnv([make_env("CartPole-v1", 0)], autoreset_mode=AutoresetMode.NEXT_STEP)
    envs_2 = AsyncVectorEnv([make_env("CartPole-v1", 1)], autoreset_mode=AutoresetMode.SAME_STEP)

    assert envs_1.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    assert envs_2.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP

    env = make_env("CartPole-v1", 0)()
    assert "autoreset_mode" not in env.metadata

    env.close()
    envs_1.close()
    envs_2.close()


@pytest.mark.parametrize("shared_memory", [True])
def test_reset_async_vector_env(shared_memory):
    """Test the reset of async vector environment with or without shared memory."""
    env_fns = [make_env("CartPole-v1", i) for i in range(8)]

    env = AsyncVectorEnv(env_fns, shared_memory=shared_memory)
    observations, infos = env.reset()

    env.close()

    assert isinstance(env.observation_space, Box)
    assert isinstance(observations, np.ndarray)
    assert observations.dtype == env.observation_space.dtype
    assert observations.shape == (8,) + env.single_observation_space.shape
    assert observations.shape == env.observation_space.shape

    try:
        env = AsyncVectorEnv(env_fns, shared_memory=shared_memory)
        observations, infos = env.reset()
    finally:
        env.close()

    assert isinstance(env.observation_space, Box)
    assert isinstance(observations, np.ndarray)
    assert observations.dtype == env.observation_space.dtype
    assert observations.shape == (8,) + env.single_observation_space.shape
    assert observations.shape == env.observation_space.shape
    assert isinstance(infos, dict)
    assert all([isinstance(info, dict) for info in infos])


def test_render_async_vector():
    envs = AsyncVectorEnv([make_env("CartPole-v1", i, render_mode="rgb_array") for i in range(3)])
    assert envs.render_mode == "rgb_array"

    envs.reset()
    rendered_frames = envs.render()
    assert isinstance(rendered_frames, tuple)
    assert len(rendered_frames) == envs.num_envs
    assert all(isinstance(frame, np.ndarray) for frame in rendered_frames)
    envs.close()

    envs = AsyncVectorEnv([make_env("CartPole-v1", i) for i in range(3)])
    assert envs.render_mode is None
    envs.close()


@pytest.mark.parametrize("shared_memory", [True])
@pytest.mark.parametrize("use_single_action_space", [True, False])
def test_step_async_vector_env(shared_memory, use_single_action_space):
    """Test the step async vector environment with and without shared memory."""
    env_fns = [make_env("CartPole-v1", i) for i in range(8)]

    env = AsyncVectorEnv(env_fns, shared_memory=shared_memory)
    env.reset()

    assert isinstance(env.single_action_space, Discrete)
    assert isinstance(env.action_space, MultiDiscrete)

    if use_single_action_space:
        actions = [env.single_action_space.sample() for _ in range(8)]
    else:
        actions = env.action_space.sample()
    observations, rewards, terminations, truncations, _ = env.step(actions)

    env.close()

    assert isinstance(env.observation_space, Box)
    assert isinstance(observations, np.ndarray)
    assert observations.dtype == env.observation_space.dtype
    assert observations.shape == (8,) + env.single_observation_space.shape
    assert observations.shape == env.observation_space.shape

    assert isinstance(rewards, np.ndarray)
    assert isinstance(rewards[0], (float, np.floating))
    assert rewards.ndim == 1
    assert rewards.size == 8

    assert isinstance(terminations, np.ndarray)
    assert terminations.dtype == np.bool_
    assert terminations.ndim == 1
    assert terminations.size == 8

    assert isinstance(truncations, np.ndarray)
    assert truncations.dtype == np.bool_
    assert truncations.ndim == 1
    assert truncations.size == 8


@pytest.mark.parametrize("shared_memory", [True])
def test_call_async_vector_env(shared_memory):
    """Test call with async vector environment."""
    env_fns = [make_env("CartPole-v1", i, render_mode="rgb_array_list") for i in range(4)]

    env = AsyncVectorEnv(env_fns, shared_memory=shared_memory)
    env.reset()
    images = env.call("render")
    gravity = env.call("gravity")

    env.close()

    assert isinstance(images, tuple)
    assert len(images) == 4
    for i in range(4):
        assert len(images[i]) == 1
        assert isinstance(images[i][0], np.ndarray)

    assert isinstance(gravity, tuple)
    assert len(gravity) == 4
    for i in range(4):
        assert isinstance(gravity[i], float)
        assert gravity[i] == 9.8


@pytest.mark.parametrize("shared_memory", [True])
def test_set_attr_async_vector_env(shared_memory):
    """Test `set_attr_` for async vector environment with or without shared memory."""
    env_fns = [make_env("CartPole-v1", i) for i in range(4)]

    env = AsyncVectorEnv(env_fns, shared_memory=shared_memory)
    env.set_attr("gravity", [9.81, 3.72, 8.87, 1.62])
    gravity = env.get_attr("gravity")
    assert gravity == (9.81, 3.72, 8.87, 1.62)

    env.close()


@pytest.mark.parametrize("shared_memory", [True])
def test_copy_async_vector_env(shared_memory):
    """Test observations are a copy of the true observation with and without shared memory."""
    env_fns = [make_env("CartPole-v1", i) for i in range(8)]

    # TODO, these tests do nothing, understand the purpose of the tests and fix them
    env = AsyncVectorEnv(env_fns, shared_memory=shared_memory, copy=True)
    observations, infos = env.reset()
    observations[0] = 0

    env.close()


@pytest.mark.parametrize("shared_memory", [True])
def test_no_copy_async_vector_env(shared_memory):
    """Test observation are not a copy of the true observation with and without shared memory."""
    env_fns = [make_env("CartPole-v1", i) for i in range(8)]

    # TODO, these tests do nothing, understand the purpose of the tests and fix them
    env = AsyncVectorEnv(env_fns, shared_memory=shared_memory, copy=False)
    observations, infos = env.reset()
    observations[0] = 0

    env.close()


@pytest.mark.parametrize("shared_memory", [True])
def test_step_timeout_async_vector_env(shared_memory):
    """Test timeout error on step with and without shared memory."""
    env_fns = [make_slow_env(0.0, i) for i in range(4)]

    env = AsyncVectorEnv(env_fns, shared_memory=shared_memory)
    with pytest.raises(TimeoutError):
        env.reset()
        env.step_async(np.array([0.1, 0.1, 0.3, 0.1]))
        observations, rewards, terminations, truncations, _ = env.step_wait(timeout=0.1)
    env.close(terminate=True)


@pytest.mark.parametrize("shared_memory", [True])
def test_step_out_of_order_async_vector_env(shared_memory):
    """Test step out of order with and without shared memory."""
    env_fns = [make_env("CartPole-v1", i) for i in range(4)]

    env = AsyncVectorEnv(env_fns, shared_memory=shared_memory)
    with pytest.raises(
        NoAsyncCallError,
        match=re.escape("Calling `step_wait` without any prior call to `step_async`."),
    ):
        env.action_space.sample()
        env.reset()
        env.step_wait()

    env.close(terminate=True)


@pytest.mark.parametrize("shared_memory", [True])
def test_already_closed_async_vector_env(shared_memory):
    """Test the error if a function is called if environment is already closed."""
    env_fns = [make_env("CartPole-v1", i) for i in range(4)]
    with pytest.raises(ClosedEnvironmentError):
        env = AsyncVectorEnv(env_fns, shared_memory=shared_memory)
        env.close()
        env.reset()


@pytest.mark.parametrize("shared_memory", [True])
def test_check_spaces_async_vector_env(shared_memory):
    """Test check spaces for async vector environment with and without shared memory."""
    # CartPole-v1 - observation_space: Box(4,), action_space: Discrete(2)
    env_fns = [make_env("CartPole-v1", i) for i in range(8)]
    # FrozenLake-v1 - Discrete(16), action_space: Discrete(4)
    env_fns[1] = make_env("FrozenLake-v1", 1)
    with pytest.raises(ConfigError):
        env = AsyncVectorEnv(env_fns, shared_memory=shared_memory)
        env.close(terminate=True)


def test_float16_async_vector_env_shared_memory():
    """Test observation dtypes without an `array` typecode (e.g. float16) with shared memory."""
    obs_space = Box(low=-1.0, high=1.0, shape=(3,), dtype=np.float16)
    envs = AsyncVectorEnv([lambda: GenericTestEnv(observation_space=obs_space)] * 2, shared_memory=True)

    observations, _ = envs.reset(seed=0)
    assert observations.dtype == np.float16
    assert observations.shape == (2, 3)

    observations, *_ = envs.step(envs.action_space.sample())
    assert observations.dtype == np.float16
    assert observations.shape == (2, 3)

    envs.close()


def raise_error_reset(self, seed, options):
    super(GenericTestEnv, self).reset(seed=seed, options=options)
    if seed == 1:
        raise ValueError("Error in reset")
    return self.observation_space.sample(), {}


def raise_error_step(self, action):
    if action >= 1:
        raise ValueError(f"Error in step with {action}")

    return self.observation_space.sample(), 0, False, False, {}


def test_async_vector_subenv_error():
    envs = AsyncVectorEnv([lambda: GenericTestEnv(reset_func=raise_error_reset, step_func=raise_error_step)] * 2)

    with warnings.catch_warnings(record=True) as caught_warnings:
        envs.reset(seed=[0, 0])
    assert len(caught_warnings) == 0

    with pytest.raises(WorkerError, match="Error in reset") as e:
        envs.reset(seed=[1, 0])
    assert e.value.index == 0
    assert (
        'in raise_error_reset\n    raise ValueError("Error in reset")\nValueError: Error in reset'
        in e.value.remote_traceback
    )

    envs.close()

    envs = AsyncVectorEnv([lambda: GenericTestEnv(reset_func=raise_error_reset, step_func=raise_error_step)] * 3)

    with pytest.raises(WorkerError, match="Error in step with 1") as e:
        envs.step([0, 1, 2])
    assert e.value.index == 1
    assert re.search(r"in raise_error_step(?s:.)*ValueError: Error in step with 1", e.value.remote_traceback)

    envs.close()
