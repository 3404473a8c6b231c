"""What ``make_vec`` is given (ids, pairs, env factories) and ``envs_per_worker="auto"`` (runtime/specs.py).

The rule is checked against this machine's own cores (``cores.usable_cpus``); the factories run in real worker
processes, and the processes ``"auto"`` makes are counted by their pids."""

from __future__ import annotations

import threading

import gymnasium as gym
import numpy as np
import pytest
from _children import children

from uniros_async.errors import ConfigError, WorkerError
from uniros_async.runtime import make_vec
from uniros_async.runtime.cores import usable_cpus
from uniros_async.runtime.specs import FACTORY_KWARG, is_realtime, normalize_specs, plan_envs_per_worker

CART, RX = "CartPole-v1", "uniros/Rx200Reach-v0"


def _cartpole() -> gym.Env:  # type: ignore[type-arg]
    return gym.make(CART)


def test_auto_is_one_process_per_core_when_accelerated_envs_outnumber_the_cores() -> None:
    from uniros_async.tasks.registry import register_envs

    register_envs()
    cores = len(usable_cpus())
    for n in (1, cores, cores + 1, 2 * cores, 4 * cores):
        specs = normalize_specs([CART] * n, {})
        most, alone = plan_envs_per_worker(specs, [False] * n, "auto")
        assert most == (-(-n // cores) if n > cores else 1) and alone == [False] * n, n
    # a real-time env (the wall clock: EnvConfig's default unless turn_based) is alone and not counted
    sim = (RX, {"clock": "sim"})
    specs = normalize_specs([RX, sim, (RX, {"turn_based": True}), *[CART] * (2 * cores)], {})
    assert [is_realtime(e, kw) for e, kw in specs[:3]] == [True, False, False]
    most, alone = plan_envs_per_worker(specs, [False] * len(specs), "auto")
    assert alone[:3] == [True, False, False] and most == -(-(2 * cores + 2) // cores)
    # a Ray-placed spec is alone (its node's cores are not known here); a count is taken as given
    assert plan_envs_per_worker(specs[:2], [True, False], "auto")[1] == [True, False]
    assert plan_envs_per_worker(specs, [False] * len(specs), 3) == (3, [False] * len(specs))
    with pytest.raises(ConfigError, match="envs_per_worker must be an int >= 1 or 'auto', got 'cores'"):
        plan_envs_per_worker(specs, [False] * len(specs), "cores")


def test_specs_of_every_form_and_what_is_refused() -> None:
    specs = normalize_specs([CART, (CART, {"render_mode": "rgb_array"}), _cartpole], {})
    assert specs[0] == (CART, {}) and specs[1] == (CART, {"render_mode": "rgb_array"})
    assert specs[2][0] == "_cartpole()" and set(specs[2][1]) == {FACTORY_KWARG}
    assert normalize_specs([(CART, {"a": 1})], {"a": 0, "b": 2}) == [(CART, {"a": 1, "b": 2})]  # its own win
    with pytest.raises(ConfigError, match=r"spec 0: keyword arguments \['sutton_barto_reward'\] go to env ids"):
        normalize_specs([_cartpole], {"sutton_barto_reward": True})
    lock = threading.Lock()
    with pytest.raises(ConfigError, match=r"spec 1: the env factory \S*<lambda>\(\) cannot be pickled .*lock"):
        normalize_specs([CART, lambda: lock], {})
    with pytest.raises(ConfigError, match="spec 0: expected an env id, an .env id, kwargs. pair or an env factory"):
        normalize_specs([3], {})  # type: ignore[list-item]
    # one id as a string, as gymnasium.make_vec has it: num_envs copies of it (not its letters)
    assert normalize_specs(CART, {"a": 1}, 3) == [(CART, {"a": 1})] * 3
    assert normalize_specs(CART, {}) == [(CART, {})]
    with pytest.raises(ConfigError, match=r"num_envs=2 goes with one spec .* \(here 1\): repeat the list"):
        normalize_specs([CART], {}, 2)
    # one pair or one factory, alone, as one id
    assert normalize_specs((CART, {"a": 1}), {}, 2) == [(CART, {"a": 1})] * 2
    factories = normalize_specs(_cartpole, {}, 2)
    assert len(factories) == 2 and all(name == "_cartpole()" for name, _ in factories)
    assert normalize_specs((CART for _ in range(2)), {}) == [(CART, {})] * 2  # a generator of specs
    with pytest.raises(ConfigError, match="specs: expected a list of env ids, .* got int"):
        normalize_specs(5, {})  # type: ignore[arg-type]
    for bad in (0, 1.5, True):
        with pytest.raises(ConfigError, match="num_envs must be an int >= 1, got"):
            normalize_specs(CART, {}, bad)  # type: ignore[arg-type]


@pytest.mark.slow
def test_factories_and_ids_mix_and_auto_hosts_one_process_per_core() -> None:
    cores = len(usable_cpus())
    n = 2 * cores
    factories = [lambda i=i: gym.make(CART, max_episode_steps=1 + i) for i in range(n - 1)]
    venv = make_vec([*factories, CART])
    try:
        assert len(set(venv.pids)) == cores  # 2 envs per process, one process per core
        assert venv.env_ids[-1] == CART and venv.env_ids[0].endswith(".<lambda>()")  # its qualified name
        obs, info = venv.reset(seed=0)
        assert obs.shape == (n, 4) and list(info["env_id"]) == [*venv.env_ids]
        # each factory's own argument reached its worker: the first one's time limit ends its episode at once
        obs, rewards, terminated, truncated, _ = venv.step(np.zeros(n, np.int64))
        assert rewards.tolist() == [1.0] * n and truncated.tolist() == [True] + [False] * (n - 1)
    finally:
        venv.close()
    assert children() == []


def test_one_id_with_num_envs_as_gymnasium_make_vec_takes_it() -> None:
    venv = make_vec(CART, num_envs=2, max_episode_steps=1)
    try:
        assert venv.num_envs == 2 and list(venv.env_ids) == [CART, CART]
        venv.reset(seed=0)
        _, _, _, truncated, _ = venv.step(np.zeros(2, np.int64))
        assert truncated.tolist() == [True, True]  # the common keyword reached both copies
    finally:
        venv.close()
    assert children() == []


@pytest.mark.slow
def test_a_factory_that_makes_no_env_and_one_for_ray_are_refused_by_name() -> None:
    with pytest.raises(WorkerError, match="worker 1: .*the env factory returned int, expected a gymnasium.Env"):
        make_vec([_cartpole, lambda: 5])
    assert children() == []
    with pytest.raises(ConfigError, match="backend='ray' places workers built from env ids"):
        make_vec([_cartpole], backend="ray")
    from uniros_async.runtime.supervisor import Supervisor

    ((name, kwargs),) = normalize_specs([_cartpole], {})
    with pytest.raises(ConfigError, match="an env factory is built by a worker on this machine"):
        Supervisor([(name, {**kwargs, "worker": "ray"})])  # a factory given a Ray placement by hand
    assert children() == []
