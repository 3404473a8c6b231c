"""Config validation: YAML numbers, field types in our words, key paths, close-match suggestions, env kwargs."""

from __future__ import annotations

import math
import multiprocessing
from pathlib import Path
from typing import Any, Literal

import gymnasium as gym
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import Field

import uniros_async  # noqa: F401  (registers the env ids)
from uniros_async.config import Bool, ConfigModel, Float, Int, Str, Vec3, closest, load_config, load_yaml
from uniros_async.envs.config import EnvConfig
from uniros_async.envs.safety import SafetyConfig
from uniros_async.errors import ConfigError
from uniros_async.tasks.reach import ReachConfig
from uniros_async.training.config import TD3Config, config_to_dict, train_config_from_dict

RX = "uniros/Rx200Reach-v0"


class Inner(ConfigModel):
    count: Int = 1
    mode: Literal["fast", "slow"] = "fast"


class Outer(ConfigModel):
    rate: Float = Field(default=1.0, gt=0)
    flag: Bool = False
    label: Str = "x"
    point: Vec3 = (0.0, 0.0, 0.0)
    inner: Inner = Inner()
    items: tuple[Inner, ...] = ()


def _error(cls: type[ConfigModel], data: dict[str, Any]) -> str:
    with pytest.raises(ConfigError) as e:
        cls.from_data(data)
    return str(e.value)


# ---- YAML


def test_yaml_reads_exponent_and_underscore_numbers_as_numbers(tmp_path: Path) -> None:
    p = tmp_path / "n.yaml"
    p.write_text("a: 3e-4\nb: 1e4\nc: 1_000\nd: -2E+3\ne: 1.5\nf: 1e\ng: e4\nh: '1e4'\ni: 0x10\n")
    assert yaml.safe_load(p.read_text())["a"] == "3e-4"  # what plain PyYAML (YAML 1.1) gives
    assert load_yaml(p) == {
        "a": 3e-4,
        "b": 1e4,
        "c": 1000,
        "d": -2000.0,
        "e": 1.5,
        "f": "1e",
        "g": "e4",
        "h": "1e4",
        "i": 16,
    }


@settings(max_examples=60, deadline=None)
@given(n=st.integers(min_value=1, max_value=10**12))
def test_any_integer_in_any_notation_loads_as_that_integer(tmp_path_factory: pytest.TempPathFactory, n: int) -> None:
    notations = [str(n), f"{n:_}", f"'{n}'"]
    mantissa, exp = n, 0
    while mantissa % 10 == 0:
        mantissa, exp = mantissa // 10, exp + 1
    if exp:
        notations += [f"{mantissa}e{exp}", f"{mantissa}E+{exp}", f"'{mantissa}e{exp}'"]
    p = tmp_path_factory.mktemp("n") / "c.yaml"
    for text in notations:
        p.write_text(f"count: {text}\n")
        got = load_config(p, Inner).count
        assert got == n and type(got) is int, (text, got)


@settings(max_examples=60, deadline=None)
@given(x=st.floats(min_value=1e-12, max_value=1e12, allow_nan=False))
def test_any_positive_float_as_python_writes_it_loads_as_that_float(
    tmp_path_factory: pytest.TempPathFactory, x: float
) -> None:
    p = tmp_path_factory.mktemp("f") / "c.yaml"
    for text in (repr(x), f"'{x!r}'", f"{x:e}"):
        p.write_text(f"rate: {text}\n")
        got = load_config(p, Outer).rate
        assert got == float(text.strip("'")), (text, got)


# ---- field types, in our words


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"inner": {"count": 128.5}}, "inner.count: expected an integer, got 128.5"),
        ({"inner": {"count": True}}, "inner.count: expected an integer, got True"),
        ({"inner": {"count": "1e-4"}}, "inner.count: expected an integer, got '1e-4'"),
        ({"inner": {"count": "ten"}}, "inner.count: expected an integer, got 'ten'"),
        ({"inner": {"count": [1]}}, "inner.count: expected an integer, got [1]"),
        ({"inner": {"count": math.inf}}, "inner.count: expected an integer, got inf"),
        ({"rate": True}, "rate: expected a number, got True"),
        ({"rate": "fast"}, "rate: expected a number, got 'fast'"),
        ({"rate": 0}, "rate: must be > 0, got 0"),
        ({"rate": "nan"}, "rate: expected a number (not NaN), got 'nan'"),
        ({"flag": 1}, "flag: expected true or false, got 1"),
        ({"flag": "yes"}, "flag: expected true or false, got 'yes'"),
        ({"label": 3}, "label: expected a string, got 3"),
        ({"point": [1, 2]}, "point: expected 3 numbers [x, y, z], got [1, 2]"),
        ({"point": [1, 2, "z"]}, "point[2]: expected a number, got 'z'"),
        ({"inner": {"mode": "fats"}}, "inner.mode: expected one of 'fast', 'slow', got 'fats'; did you mean 'fast'?"),
        ({"inner": 3}, "inner: expected a mapping, got 3"),
        ({"items": [{}, {"count": 2.5}]}, "items[1].count: expected an integer, got 2.5"),
        ({"items": [{}, {"cuont": 2}]}, "items[1].cuont: unknown key; did you mean 'count'?"),
        ({"inner": {"cont": 2}}, "inner.cont: unknown key; did you mean 'count'?"),
        ({"zzz": 2}, "zzz: unknown key (valid keys: rate, flag, label, point, inner, items)"),
    ],
)
def test_problems_are_described_in_our_words_with_the_key_path(data: dict[str, Any], message: str) -> None:
    assert _error(Outer, data) == message


def test_construction_from_python_raises_config_error_too() -> None:
    with pytest.raises(ConfigError, match=r"^inner\.count: expected an integer, got 1\.5$"):
        Outer(inner={"count": 1.5})
    with pytest.raises(ConfigError, match=r"^batch_size: expected an integer, got 128\.5$"):
        TD3Config(batch_size=128.5)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=r"^batch_size: must be <= buffer_size \(10\), got 20$"):
        TD3Config(batch_size=20, buffer_size=10)
    assert issubclass(ConfigError, ValueError)


def test_several_problems_one_line_each_and_a_where() -> None:
    with pytest.raises(ConfigError) as e:
        Outer.from_data({"rate": -1, "inner": {"count": "x", "extra": 1}}, where="my.yaml")
    assert str(e.value).splitlines() == [
        "my.yaml: 3 problems:",
        "  rate: must be > 0, got -1",
        "  inner.count: expected an integer, got 'x'",
        "  inner.extra: unknown key (valid keys: count, mode)",
    ]
    with pytest.raises(ConfigError, match=r"^my\.yaml: expected a mapping of Outer keys, got \[1\]$"):
        Outer.from_data([1], where="my.yaml")


@settings(max_examples=50, deadline=None)
@given(x=st.floats(allow_nan=False, allow_infinity=False).filter(lambda v: not v.is_integer()))
def test_a_fractional_number_is_never_an_integer(x: float) -> None:
    assert _error(Inner, {"count": x}) == f"count: expected an integer, got {x!r}"


@settings(max_examples=30, deadline=None)
@given(
    lr=st.floats(min_value=1e-6, max_value=1.0),
    batch=st.integers(min_value=1, max_value=512),
    arch=st.lists(st.integers(min_value=1, max_value=1024), min_size=1, max_size=4),
    tau=st.floats(min_value=1e-4, max_value=1.0),
)
def test_plain_data_round_trips(lr: float, batch: int, arch: list[int], tau: float) -> None:
    cfg = train_config_from_dict(
        {
            "envs": [RX, {"id": RX, "name": "b", "kwargs": {"goal_min": [0.1, 0.0, 0.1]}}],
            "td3": {"learning_rate": lr, "batch_size": batch, "net_arch": arch, "tau": tau},
        }
    )
    data = config_to_dict(cfg)
    assert yaml.safe_load(yaml.safe_dump(data)) == data  # plain YAML-able data, tuples as lists
    assert train_config_from_dict(data) == cfg


def test_closest_name() -> None:
    assert closest("rewrd_type", ["reward_type", "robot"]) == "reward_type"
    assert closest("lr", ["learning_rate", "batch_size"]) == "learning_rate"
    assert closest("colour", ["reward_type", "robot"]) is None


def test_env_and_safety_configs_are_frozen_models_with_their_attribute_names() -> None:
    cfg = EnvConfig(clock="sim", action_cycle_s="0.4")  # type: ignore[arg-type]
    assert (cfg.clock, cfg.action_cycle_s, cfg.turn_based) == ("sim", 0.4, False)
    assert EnvConfig().clock == "wall" and EnvConfig(turn_based=True).clock == "sim"
    with pytest.raises(ValueError, match="frozen"):
        cfg.clock = "wall"  # type: ignore[misc]
    assert SafetyConfig(workspace_min_m=[0, 0, 0]).workspace_min_m == (0.0, 0.0, 0.0)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=r"^workspace_max_m: must be above workspace_min_m"):
        SafetyConfig(workspace_min_m=(0.0, 0.0, 1.0), workspace_max_m=(1.0, 1.0, 0.5))
    with pytest.raises(ConfigError, match=r"^goal_max: must be >= goal_min \[0\.3, 0\.0, 0\.1\] on every axis"):
        ReachConfig(goal_min=(0.3, 0.0, 0.1), goal_max=(0.2, 0.1, 0.2))


# ---- env kwargs: gym.make, make, make_vec


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (
            {"rewrd_type": "sparse"},
            "ReachEnv: rewrd_type: unknown keyword argument; did you mean 'reward_type'?",
        ),
        (
            {"reward_type": "spars"},
            "ReachEnv: reward_type: expected one of 'dense', 'sparse', got 'spars'; did you mean",
        ),
        ({"action_cycle_s": "fast"}, "ReachEnv: action_cycle_s: expected a number, got 'fast'"),
        ({"action_cycle_s": 61}, "ReachEnv: action_cycle_s: must be <= 60, got 61"),
        ({"turn_based": 1}, "ReachEnv: turn_based: expected true or false, got 1"),
        ({"emulation_seed": 1.5}, "ReachEnv: emulation_seed: expected an integer, got 1.5"),
        ({"goal_min": [0.1, 0.2]}, "ReachEnv: goal_min: expected 3 numbers [x, y, z], got [0.1, 0.2]"),
        ({"agent_latency_s": "soon"}, "ReachEnv: agent_latency_s: expected a number >= 0 or 'measured', got 'soon'"),
        ({"clock": "sim", "robot": "sim-process"}, "ReachEnv: clock='sim' needs robot='sim' or 'emulated-real'"),
    ],
)
def test_gym_make_kwargs_errors_name_the_key_and_the_expectation(kwargs: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as e:
        gym.make(RX, **kwargs)
    assert str(e.value).startswith(message), str(e.value)


def test_gym_make_reports_every_bad_kwarg_at_once() -> None:
    with pytest.raises(ConfigError) as e:
        gym.make("uniros/Ned2ReachGoal-v0", reward_type="shaped", reach_tolerance=True, colour=1)
    lines = str(e.value).splitlines()
    assert lines[0] == "ReachGoalEnv: 3 problems:"
    assert [line.split(":")[0].strip() for line in lines[1:]] == ["colour", "reward_type", "reach_tolerance"]


def test_gym_make_takes_numbers_as_strings_and_keeps_the_settings() -> None:
    env = gym.make(RX, clock="sim", action_cycle_s="4e-1", reach_tolerance="0.03", reward_type="sparse")
    try:
        u: Any = env.unwrapped
        assert u.config.action_cycle_s == 0.4 and u.reach_tolerance == 0.03 and u.reward_type == "sparse"
        assert u.goal_min.tolist() == [0.15, -0.15, 0.05]  # the arm's goal box, the default
    finally:
        env.close()


@pytest.mark.slow
def test_make_and_make_vec_raise_the_same_error_in_the_caller_before_any_process() -> None:
    from uniros_async.runtime import make, make_vec

    before = set(multiprocessing.active_children())
    with pytest.raises(ConfigError) as e:
        make(RX, clock="sim", reward_type="spars")
    assert (
        str(e.value) == "ReachEnv: reward_type: expected one of 'dense', 'sparse', got 'spars'; did you mean 'sparse'?"
    )
    with pytest.raises(ConfigError) as e:
        make_vec([RX, ("uniros/Ned2Reach-v0", {"action_cycle_s": True})], clock="sim")
    assert str(e.value) == "ReachEnv: action_cycle_s: expected a number, got True"
    with pytest.raises(
        ConfigError, match=r"^ReachEnv: delta_cof: unknown keyword argument; did you mean 'delta_coeff'"
    ):
        make_vec([RX], clock="sim", delta_cof=0.1)
    assert set(multiprocessing.active_children()) == before


def test_numpy_scalars_and_arrays_are_numbers_but_numpy_bools_are_not() -> None:
    import numpy as np

    cfg = EnvConfig(emulation_seed=np.int64(3), action_cycle_s=np.float32(0.5))  # type: ignore[arg-type]
    assert (cfg.emulation_seed, cfg.action_cycle_s) == (3, 0.5) and type(cfg.emulation_seed) is int
    assert ReachConfig(goal_min=np.array([0.1, 0.0, 0.1])).goal_min == (0.1, 0.0, 0.1)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=r"^emulation_seed: expected an integer, got np\.True_$"):
        EnvConfig(emulation_seed=np.bool_(True))  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=r"^emulation_seed: expected an integer, got np\.float64\(2\.5\)$"):
        EnvConfig(emulation_seed=np.float64(2.5))  # type: ignore[arg-type]
