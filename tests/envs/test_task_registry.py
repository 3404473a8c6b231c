"""The task registry: the ids that ship are exactly as before, tasks and ids from user code, refusals, close matches."""

from __future__ import annotations

import subprocess
import sys

import gymnasium as gym
import pytest

import uniros_async
from uniros_async.errors import ConfigError
from uniros_async.tasks.registry import (
    ENV_IDS,
    env_id_of,
    register_env_id,
    register_envs,
    register_task,
    task_names,
    task_spec,
)

SHIPPED = {
    "uniros/Rx200Reach-v0": ("rx200", "uniros_async.tasks.reach:ReachEnv"),
    "uniros/Rx200ReachGoal-v0": ("rx200", "uniros_async.tasks.reach:ReachGoalEnv"),
    "uniros/Ned2Reach-v0": ("ned2", "uniros_async.tasks.reach:ReachEnv"),
    "uniros/Ned2ReachGoal-v0": ("ned2", "uniros_async.tasks.reach:ReachGoalEnv"),
}


def test_the_ids_that_ship_keep_their_entry_points_kwargs_and_length() -> None:
    register_envs()  # again: nothing changes
    for env_id, (arm, entry_point) in SHIPPED.items():
        spec = gym.spec(env_id)
        assert (spec.entry_point, spec.kwargs, spec.max_episode_steps) == (entry_point, {"arm": arm}, 100)
        assert spec.disable_env_checker
        assert ENV_IDS[env_id][0] == arm
    assert {"Reach", "ReachGoal"} <= set(task_names())
    assert uniros_async.register_task is register_task and uniros_async.register_env_id is register_env_id


def test_a_task_and_ids_from_user_code() -> None:
    entry_point, sparse = "uniros_async.tasks.reach:ReachEnv", {"reward_type": "sparse"}
    task = register_task("TestReachSparse", entry_point, kwargs=sparse)
    assert register_task("TestReachSparse", entry_point, kwargs=sparse) is task  # again: nothing happens
    env_id = register_env_id("ned2", "TestReachSparse", kwargs={"reach_tolerance": 0.05}, max_episode_steps=7)
    assert env_id == "uniros/Ned2TestReachSparse-v0" == env_id_of("ned2", "TestReachSparse")
    assert register_env_id("ned2", "TestReachSparse", kwargs={"reach_tolerance": 0.05}) == env_id  # a no-op
    spec = gym.spec(env_id)
    assert spec.kwargs == {"arm": "ned2", "reward_type": "sparse", "reach_tolerance": 0.05}
    assert spec.max_episode_steps == 7 and ENV_IDS[env_id] == ("ned2", "TestReachSparse")
    with pytest.raises(ConfigError, match="already registered"):
        register_env_id("rx200", "TestReachSparse", env_id=env_id)
    with pytest.raises(ConfigError, match="already a gymnasium id"):
        register_env_id("rx200", "Reach", env_id="CartPole-v1")
    with pytest.raises(ConfigError, match="already registered"):
        register_task("TestReachSparse", "uniros_async.tasks.reach:ReachGoalEnv")
    assert env_id_of("my_arm", "Push", namespace="mine") == "mine/MyArmPush-v0"


@pytest.mark.parametrize(
    ("name", "entry_point", "match"),
    [("push", "m:C", "CamelCase"), ("Push", "no-colon", "'module:Class'"), ("Push", ":C", "'module:Class'")],
)
def test_malformed_tasks_are_refused(name: str, entry_point: str, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        register_task(name, entry_point)


def test_lookups_that_miss_name_the_closest() -> None:
    with pytest.raises(ConfigError, match=r"unknown task 'ReachGoals' \(did you mean 'ReachGoal'\?\); registered: \["):
        task_spec("ReachGoals")
    with pytest.raises(ConfigError, match=r"unknown robot 'rx2000' \(did you mean 'rx200'\?\)"):
        register_env_id("rx2000", "Reach")
    with pytest.raises(gym.error.NameNotFound, match="Did you mean: `Rx200Reach`"):
        gym.make("uniros/Rx200Reech-v0")


def test_a_users_package_may_register_ids_before_gymnasium_is_imported() -> None:
    """``import uniros_async`` registers the shipped ids right after gymnasium's first import, wherever it happens:
    also inside ``register_env_id`` of a user's package that imported nothing else yet."""
    code = (
        "import sys, uniros_async\n"
        "import uniros_async.tasks.registry as r\n"
        "assert 'gymnasium' not in sys.modules and 'Reach' in r.task_names()\n"
        "from uniros_async import register_env_id\n"
        "register_env_id('ned2', 'Reach', env_id='mine/Ned2Reach-v0')\n"
        "import gymnasium as gym\n"
        "assert gym.spec('uniros/Rx200Reach-v0').kwargs == {'arm': 'rx200'}, 'the shipped ids'\n"
        "assert set(r.ENV_IDS) >= {'uniros/Ned2ReachGoal-v0', 'mine/Ned2Reach-v0'}, sorted(r.ENV_IDS)\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr
