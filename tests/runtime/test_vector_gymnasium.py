"""Gymnasium's own vector-env tests, run against ``make_vec``.

Adapted from Gymnasium's tests/vector/ (test_vector_env.py, test_autoreset_mode.py, test_async_vector_env.py;
https://github.com/Farama-Foundation/Gymnasium, MIT License, Copyright (c) 2016 OpenAI, (c) 2022 Farama
Foundation). Where a reference implementation is at hand, ``make_vec`` is compared with gymnasium's SyncVectorEnv in
the same test (same seeds, same actions: observations, rewards, flags and infos must be equal), over shm and tcp.

Differences on purpose, each said where it is tested:
- envs are given by id (each worker builds its env from its id; test_gymnasium_async_vector_env.py gives env
  factories, as Gymnasium's own tests do); the test envs are registered by ``_vector_envs`` and named
  ``"_vector_envs:Id"``;
- envs whose spaces differ are refused with ConfigError naming the envs and their spaces (gymnasium raises a
  RuntimeError), unless they can be padded;
- a real-time uniros env (wall clock) returns on its action cycle's deadline, not when stepped; these tests use
  turn-based envs, as gymnasium's do.
"""

from __future__ import annotations

import re

import gymnasium as gym
import numpy as np
import pytest
from _vector_envs import (
    GENERIC,
    count_reset,
    count_step,
    debug_step_func,
    final_obs_reset,
    final_obs_step,
)
from gymnasium.spaces import (
    Box,
    Dict,
    Discrete,
    Graph,
    MultiBinary,
    MultiDiscrete,
    OneOf,
    Sequence,
    Text,
    Tuple,
)
from gymnasium.utils.env_checker import data_equivalence
from gymnasium.vector import AutoresetMode, SyncVectorEnv

from uniros_async.errors import ConfigError
from uniros_async.runtime import make_vec

pytestmark = pytest.mark.slow

# tests/spaces/utils.py's TESTING_SPACES (fundamental and composite), without the duplicates of one kind
TESTING_SPACES = [
    Discrete(3),
    Discrete(3, start=-1),
    Discrete(n=4, dtype=np.int32, start=1),
    Box(low=0.0, high=1.0),
    Box(low=0.0, high=np.inf, shape=(2, 2)),
    Box(low=np.array([-10.0, 0.0]), high=np.array([10.0, 10.0]), dtype=np.float64),
    Box(low=0, high=255, shape=(2, 2, 3), dtype=np.uint8),
    Box(low=np.array([0, 0, 1]), high=np.array([1, 0, 1]), dtype=np.bool_),
    Box(low=np.array([-np.inf, -np.inf, 0, -10]), high=np.array([np.inf, 0, np.inf, 10]), dtype=np.int32),
    MultiDiscrete([2, 2]),
    MultiDiscrete([[2, 3], [3, 2]]),
    MultiDiscrete([2, 2], start=[10, 10]),
    MultiDiscrete([2, 3], dtype=np.int8),
    MultiBinary(8),
    MultiBinary([2, 3]),
    Text(6),
    Text(min_length=3, max_length=6),
    Text(6, charset="abcdef"),
    Tuple([Discrete(5), Discrete(4)]),
    Tuple((Discrete(5), Tuple((Box(low=0.0, high=1.0, shape=(3,)), Discrete(2))))),
    Tuple((Discrete(3), Dict(position=Box(low=0.0, high=1.0), velocity=Discrete(2)))),
    Tuple((Graph(node_space=Box(-1, 1, shape=(2, 1)), edge_space=None), Discrete(2))),
    Dict(position=Discrete(6), velocity=Box(low=np.array([0.0, 0.0]), high=np.array([1.0, 5.0]), dtype=np.float64)),
    Dict(
        {
            "a": Box(low=0, high=1, shape=(3, 3)),
            "b": Dict({"b_1": Box(low=-100, high=100, shape=(2,)), "b_2": Box(low=-1, high=1, shape=(2,))}),
            "c": Discrete(4),
        }
    ),
    Graph(node_space=Box(low=-100, high=100, shape=(3, 4)), edge_space=Discrete(5)),
    Sequence(Discrete(4)),
    Sequence(Box(low=np.array([0.0, 0.0]), high=np.array([1.0, 5.0]), dtype=np.float64)),
    Sequence(Tuple((Discrete(5), Box(low=0.0, high=1.0, shape=(3,))))),
    OneOf([Discrete(3), Box(low=0.0, high=1.0)]),
]
TESTING_SPACES_IDS = [str(s) for s in TESTING_SPACES]


@pytest.fixture(params=["shm", "tcp"])
def transport(request: pytest.FixtureRequest) -> str:
    return str(request.param)


def _sync(env_id: str, n: int, **kwargs: object) -> SyncVectorEnv:
    return SyncVectorEnv([lambda: gym.make(env_id, disable_env_checker=True) for _ in range(n)], **kwargs)  # type: ignore[arg-type]


# ---------------------------------------------------------------- test_vector_env.py


@pytest.mark.parametrize("autoreset_mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_vector_env_equal(transport: str, autoreset_mode: AutoresetMode) -> None:
    """make_vec and SyncVectorEnv agree step by step (both autoreset modes; episodes end within 100 steps)."""
    num_steps = 100
    uniros_env = make_vec(["CartPole-v1"] * 4, transport=transport, autoreset_mode=autoreset_mode)
    sync_env = _sync("CartPole-v1", 4, autoreset_mode=autoreset_mode)
    try:
        assert uniros_env.num_envs == sync_env.num_envs
        assert uniros_env.observation_space == sync_env.observation_space
        assert uniros_env.single_observation_space == sync_env.single_observation_space
        assert uniros_env.action_space == sync_env.action_space
        assert uniros_env.single_action_space == sync_env.single_action_space
        assert uniros_env.metadata["autoreset_mode"] == autoreset_mode

        uniros_obs, uniros_infos = uniros_env.reset(seed=0)
        sync_obs, sync_infos = sync_env.reset(seed=0)
        assert np.all(uniros_obs == sync_obs)
        assert data_equivalence(uniros_infos, sync_infos)
        uniros_env.action_space.seed(0)
        ended = 0
        for _ in range(num_steps):
            actions = uniros_env.action_space.sample()
            assert actions in sync_env.action_space
            u = uniros_env.step(actions)
            s = sync_env.step(actions)
            assert np.all(u[0] == s[0])
            assert np.all(u[1] == s[1])
            assert np.all(u[2] == s[2])
            assert np.all(u[3] == s[3])
            assert data_equivalence(u[4], s[4]), (u[4], s[4])
            ended += int(np.sum(u[2] | u[3]))
        assert ended > 0  # the autoreset paths ran
    finally:
        uniros_env.close()
        sync_env.close()


@pytest.mark.parametrize("autoreset_mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_dict_of_boxes_equal(transport: str, autoreset_mode: AutoresetMode) -> None:
    """A Dict of Boxes (a goal env's observation, batched key by key by make_vec itself) equals SyncVectorEnv's,
    step by step, across an episode's end (the env's episodes are 200 steps)."""
    from uniros_async.bench.envs import DICT_ID

    uniros_env = make_vec([DICT_ID] * 2, transport=transport, autoreset_mode=autoreset_mode)
    sync_env = _sync(DICT_ID, 2, autoreset_mode=autoreset_mode)
    try:
        u_obs, u_info = uniros_env.reset(seed=3)
        s_obs, s_info = sync_env.reset(seed=3)
        assert data_equivalence(u_obs, s_obs) and data_equivalence(u_info, s_info)
        uniros_env.action_space.seed(3)
        for _ in range(205):
            actions = uniros_env.action_space.sample()
            u = uniros_env.step(actions)
            s = sync_env.step(actions)
            for a, b in zip(u, s, strict=True):
                assert data_equivalence(a, b), (a, b)
    finally:
        uniros_env.close()
        sync_env.close()


@pytest.mark.parametrize("space", TESTING_SPACES, ids=TESTING_SPACES_IDS)
def test_vector_obs_action_spaces(space: gym.Space[object]) -> None:
    """Every kind of space crosses the wire: the observations are in the batched space, the actions reach each
    env in its own (debug_step_func asserts it in the worker), and the spaces equal SyncVectorEnv's."""
    envs = make_vec([GENERIC] * 2, action_space=space, observation_space=space, step_func=debug_step_func)
    try:
        sync = SyncVectorEnv([lambda: gym.make(GENERIC, action_space=space, observation_space=space)] * 2)
        assert envs.observation_space == sync.observation_space and envs.action_space == sync.action_space
        sync.close()
        assert envs.observation_space == envs.action_space
        obs, _ = envs.reset(seed=0)
        assert obs in envs.observation_space
        for _ in range(3):
            obs, _, _, _, _ = envs.step(envs.action_space.sample())
            assert obs in envs.observation_space
    finally:
        envs.close()


@pytest.mark.parametrize(
    "space",
    [
        TESTING_SPACES[22],  # Dict of a Discrete and a float64 Box
        TESTING_SPACES[21],  # Tuple of a Graph and a Discrete
        TESTING_SPACES[17],  # Text with a charset
        TESTING_SPACES[6],  # Box of uint8 images
    ],
    ids=lambda s: str(s),
)
def test_vector_obs_action_spaces_over_tcp(space: gym.Space[object]) -> None:
    """test_vector_obs_action_spaces's composite, text and image cases, with the workers over tcp."""
    envs = make_vec(
        [GENERIC] * 2, action_space=space, observation_space=space, step_func=debug_step_func, transport="tcp"
    )
    try:
        obs, _ = envs.reset(seed=0)
        assert obs in envs.observation_space
        for _ in range(3):
            obs, _, _, _, _ = envs.step(envs.action_space.sample())
            assert obs in envs.observation_space
    finally:
        envs.close()


def test_final_obs_info() -> None:
    """NEXT_STEP: the step after the end resets (its info is the reset's); as gymnasium's test_final_obs_info."""
    env = make_vec([GENERIC], action_space=Discrete(4), observation_space=Discrete(4), reset_func=final_obs_reset,
                   step_func=final_obs_step)  # fmt: skip
    try:
        obs, info = env.reset()
        assert obs == np.array([0]) and data_equivalence(info, {"reset": np.array([True]), "_reset": np.array([True])})
        obs, _, termination, _, info = env.step([1])
        assert obs == np.array([1]) and termination == np.array([False])
        assert data_equivalence(info, {"action": np.array([1]), "_action": np.array([True])})
        obs, _, termination, _, info = env.step([2])
        assert obs == np.array([2]) and termination == np.array([False])
        obs, _, termination, _, info = env.step([3])
        assert obs == np.array([0]) and termination == np.array([True]) and info["action"] == 3
        obs, _, termination, _, info = env.step([4])
        assert obs == np.array([0]) and termination == np.array([False]) and info["reset"] == np.array([True])
    finally:
        env.close()


def test_random_seeding_basics() -> None:
    vector_env = make_vec(["CartPole-v1"] * 3)
    try:
        vector_env.reset(seed=42)
        assert vector_env.np_random_seed == tuple(42 + i for i in range(vector_env.num_envs))
        vector_env.reset(seed=None)  # the seeds stay
        assert vector_env.np_random_seed == tuple(42 + i for i in range(vector_env.num_envs))
    finally:
        vector_env.close()


def test_partial_reset(transport: str) -> None:
    """DISABLED autoreset: reset(options={"reset_mask": ...}) resets only the masked envs."""
    envs = make_vec(["CartPole-v1"] * 3, autoreset_mode=AutoresetMode.DISABLED, transport=transport)
    try:
        reset_obs, _ = envs.reset(seed=[0, 1, 2])
        envs.action_space.seed(123)
        envs.step(envs.action_space.sample())
        envs.step(envs.action_space.sample())
        step_obs, *_ = envs.step(envs.action_space.sample())
        reset_mask_obs, info = envs.reset(seed=[0, 1, 0], options={"reset_mask": np.array([True, True, False])})
        assert np.all(reset_mask_obs[:2] == reset_obs[:2])
        assert np.all(reset_mask_obs[2] == step_obs[2])
    finally:
        envs.close()


def test_partial_reset_failure() -> None:
    envs = make_vec(["CartPole-v1"] * 3, autoreset_mode=AutoresetMode.DISABLED)
    try:
        envs.reset(options={"reset_mask": np.array([True, True, True])})
        for mask, shape in [([True], "(1,)"), ([True, True, False, False], "(4,)"), ([[True, True, True]], "(1, 3)")]:
            with pytest.raises(
                ValueError, match=re.escape(f"`options['reset_mask']` must have shape `(3,)`, got {shape}")
            ):
                envs.reset(options={"reset_mask": np.array(mask)})
        with pytest.raises(ValueError, match=re.escape("must contain a boolean array with at least one True value")):
            envs.reset(options={"reset_mask": np.array([False, False, False])})
        with pytest.raises(TypeError, match=re.escape("`options['reset_mask']` must have `dtype=np.bool_`, got int64")):
            envs.reset(options={"reset_mask": np.array([1, 1, 0])})
    finally:
        envs.close()


def test_action_count_compatibility() -> None:
    num_envs = 4
    envs = make_vec(["CartPole-v1"] * num_envs, autoreset_mode=AutoresetMode.DISABLED)
    try:
        envs.reset()
        correct_actions = envs.action_space.sample()
        obs, rewards, terminations, truncations, _ = envs.step(correct_actions)
        assert len(obs) == len(rewards) == len(terminations) == len(truncations) == num_envs
        with pytest.raises(ValueError):
            envs.step(correct_actions[: num_envs - 1])
        with pytest.raises(ValueError):
            envs.step(np.concatenate([correct_actions, correct_actions[:1]]))
        with pytest.raises(TypeError):
            envs.step(0)
    finally:
        envs.close()


def test_spaces_that_differ_are_refused_naming_the_envs() -> None:
    """On purpose: gymnasium raises RuntimeError for CartPole beside FrozenLake; make_vec raises ConfigError naming
    each env and its spaces (they cannot be padded: FrozenLake's observation is Discrete)."""
    with pytest.raises(ConfigError) as e:
        make_vec(["CartPole-v1", "FrozenLake-v1"])
    msg = str(e.value)
    assert "0:CartPole-v1" in msg and "1:FrozenLake-v1" in msg and "Discrete(16)" in msg and "Box(" in msg


# ---------------------------------------------------------------- test_autoreset_mode.py


def _count_envs(mode: AutoresetMode) -> object:
    envs = make_vec([GENERIC] * 3, action_space=Discrete(5), observation_space=Discrete(5), reset_func=count_reset,
                    step_func=count_step, autoreset_mode=mode)  # fmt: skip
    assert envs.metadata["autoreset_mode"] == mode
    envs.set_attr("max_count", [2, 3, 3])
    return envs


def test_autoreset_next_step() -> None:
    envs = _count_envs(AutoresetMode.NEXT_STEP)
    try:
        obs, info = envs.reset()  # type: ignore[attr-defined]
        assert np.all(obs == [0, 0, 0]) and info == {}
        expected = [
            ([1, 1, 1], [1, 2, 3], [False, False, False]),
            ([2, 2, 2], [1, 2, 3], [True, False, False]),
            ([0, 3, 3], [0, 2, 3], [False, True, True]),
            ([1, 0, 0], [1, 0, 0], [False, False, False]),
        ]
        for exp_obs, exp_rewards, exp_terms in expected:
            obs, rewards, terminations, truncations, info = envs.step([1, 2, 3])  # type: ignore[attr-defined]
            assert np.all(obs == exp_obs) and np.all(rewards == exp_rewards)
            assert np.all(terminations == exp_terms) and not np.any(truncations) and info == {}
    finally:
        envs.close()  # type: ignore[attr-defined]


def test_autoreset_within_step() -> None:
    envs = _count_envs(AutoresetMode.SAME_STEP)
    try:
        obs, info = envs.reset()  # type: ignore[attr-defined]
        assert np.all(obs == [0, 0, 0]) and info == {}
        obs, rewards, terminations, truncations, info = envs.step([1, 2, 3])  # type: ignore[attr-defined]
        assert np.all(obs == [1, 1, 1]) and np.all(rewards == [1, 2, 3]) and not np.any(terminations) and info == {}
        obs, rewards, terminations, truncations, info = envs.step([1, 2, 3])  # type: ignore[attr-defined]
        assert np.all(obs == [0, 2, 2]) and np.all(rewards == [1, 2, 3])
        assert np.all(terminations == [True, False, False]) and not np.any(truncations)
        assert data_equivalence(
            info,
            {
                "final_obs": np.array([2, None, None], dtype=object),
                "final_info": {},
                "_final_obs": np.array([True, False, False]),
                "_final_info": np.array([True, False, False]),
            },
        )
        obs, rewards, terminations, truncations, info = envs.step([1, 2, 3])  # type: ignore[attr-defined]
        assert np.all(obs == [1, 0, 0]) and np.all(rewards == [1, 2, 3])
        assert np.all(terminations == [False, True, True])
        assert data_equivalence(
            info,
            {
                "final_obs": np.array([None, 3, 3], dtype=object),
                "final_info": {},
                "_final_obs": np.array([False, True, True]),
                "_final_info": np.array([False, True, True]),
            },
        )
    finally:
        envs.close()  # type: ignore[attr-defined]


# ---------------------------------------------------------------- test_async_vector_env.py


def test_metadata() -> None:
    envs_1 = make_vec(["CartPole-v1"], autoreset_mode=AutoresetMode.NEXT_STEP)
    envs_2 = make_vec(["CartPole-v1"], autoreset_mode="SameStep")
    try:
        assert envs_1.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
        assert envs_2.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
        assert envs_1.metadata["render_fps"] == gym.make("CartPole-v1").metadata["render_fps"]
    finally:
        envs_1.close()
        envs_2.close()


def test_render() -> None:
    envs = make_vec(["CartPole-v1"] * 3, render_mode="rgb_array")
    try:
        assert envs.render_mode == "rgb_array"
        envs.reset(seed=0)
        frames = envs.render()
        assert isinstance(frames, tuple) and len(frames) == envs.num_envs
        assert all(isinstance(f, np.ndarray) and f.shape == (400, 600, 3) and f.dtype == np.uint8 for f in frames)
    finally:
        envs.close()
    envs = make_vec(["CartPole-v1"] * 3)
    try:
        assert envs.render_mode is None
    finally:
        envs.close()


def test_step_types(transport: str) -> None:
    envs = make_vec(["CartPole-v1"] * 8, transport=transport)
    try:
        envs.reset()
        assert isinstance(envs.single_action_space, Discrete) and isinstance(envs.action_space, MultiDiscrete)
        for actions in ([envs.single_action_space.sample() for _ in range(8)], envs.action_space.sample()):
            observations, rewards, terminations, truncations, _ = envs.step(actions)
            assert isinstance(observations, np.ndarray) and observations.dtype == envs.observation_space.dtype
            assert observations.shape == (8, *envs.single_observation_space.shape) == envs.observation_space.shape
            assert isinstance(rewards, np.ndarray) and isinstance(rewards[0], float | np.floating)
            assert rewards.ndim == 1 and rewards.size == 8
            for flags in (terminations, truncations):
                assert flags.dtype == np.bool_ and flags.ndim == 1 and flags.size == 8
    finally:
        envs.close()


def test_call_and_set_attr() -> None:
    envs = make_vec(["CartPole-v1"] * 4, render_mode="rgb_array_list")
    try:
        envs.reset()
        images = envs.call("render")
        gravity = envs.call("gravity")
        assert isinstance(images, tuple) and len(images) == 4
        assert all(len(i) == 1 and isinstance(i[0], np.ndarray) for i in images)
        assert gravity == (9.8, 9.8, 9.8, 9.8) and all(isinstance(g, float) for g in gravity)
        envs.set_attr("gravity", [9.81, 3.72, 8.87, 1.62])
        assert envs.get_attr("gravity") == (9.81, 3.72, 8.87, 1.62)
        assert envs.get_attr("observation_space") == (envs.single_observation_space,) * 4  # spaces cross as spaces
    finally:
        envs.close()


def test_already_closed() -> None:
    env = make_vec(["CartPole-v1"] * 2)
    env.close()
    with pytest.raises(gym.error.ClosedEnvironmentError):
        env.reset()
