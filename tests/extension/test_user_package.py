"""A user's own package (acme_arms, beside this file, outside uniros_async) adds an arm, a placement, task ids and a
ROS driver through the public registries, and everything of uniros_async takes them as its own.

The robot and env checker tests of the built-in arms run on acme5 too (tests/robots, tests/envs); here: the
registrations themselves, make + reset + step on the user's placement, the arm in a sim process and in a
``make_vec`` worker (which imports the user's module itself), the CLI, and the close-match errors.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import error as gym_error

import uniros_async
from uniros_async.errors import ConfigError
from uniros_async.placements import placement_names, placement_spec
from uniros_async.robots import get_robot_spec, robot_names

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
ENV_ID = "acme_arms:acme/Acme5Reach-v0"


@pytest.fixture
def user_path(monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """``PYTHONPATH`` with the user's package: a worker or a CLI process finds ``acme_arms`` however it starts."""
    path = os.pathsep.join([str(HERE), str(REPO), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    monkeypatch.setenv("PYTHONPATH", path)
    yield path


def test_importing_the_package_registers_its_arm_placement_ids_and_driver() -> None:
    import acme_arms
    from acme_arms.robot import ACME5

    from uniros_async.adapters.drivers import ros_driver_defaults
    from uniros_async.adapters.ros1_bridge import Ros1BridgeConfig
    from uniros_async.tasks.registry import ENV_IDS

    assert "acme5" in robot_names() and get_robot_spec("acme5") is ACME5
    assert get_robot_spec("acme_arms:acme5") is ACME5
    assert ACME5.mjcf_path.parent == Path(acme_arms.__file__).parent  # the model ships in the user's package
    assert "acme-sim" in placement_names() and placement_spec("acme-sim").can_teleport
    assert ENV_IDS["acme/Acme5Reach-v0"] == ("acme5", "Reach")
    assert gym.spec("acme/Acme5ReachGoal-v0").kwargs["goal_max"] == acme_arms.GOAL_MAX
    driver = ros_driver_defaults("ros1", "acme5")
    assert driver is not None and driver.driver == "ros_control"
    bridge = Ros1BridgeConfig(robot="acme5")  # no settings: the package registered its driver's topics
    assert (bridge.joint_states, bridge.command_type) == ("/joint_states", "trajectory_msgs/JointTrajectory")
    assert not any(p.startswith(str(REPO / "uniros_async")) for p in (acme_arms.__file__, str(ACME5.mjcf_path)))


@pytest.mark.slow
def test_make_reset_and_step_on_the_users_placement() -> None:
    from acme_arms.placement import OPENED

    opened = len(OPENED)
    # goal_pool=0: the goal is drawn at reset from the seed, so the IK check below runs on the same goal every time
    env = gym.make(ENV_ID, robot="acme-sim", clock="sim", goal_pool=0)
    try:
        u = env.unwrapped
        assert u.robot_spec.name == "acme5" and u.placement.name == "acme-sim"
        assert OPENED[opened:] == ["acme5"]  # the user's factory opened the arm
        obs, info = env.reset(seed=1)
        assert env.observation_space.contains(obs)
        np.testing.assert_allclose(u.kin.ee_position(u.home_q), (0.408575, 0.0, 0.30457), atol=1e-6)
        q, ok = u.kin.ik(u.goal)
        assert ok
        action = (2 * (q - u._lower) / (u._upper - u._lower) - 1).astype(np.float32)
        for _ in range(12):  # the IK action of the goal reaches it
            obs, reward, terminated, truncated, info = env.step(action)
            assert env.observation_space.contains(obs)
            if terminated:
                break
        assert terminated and info["is_success"], info
    finally:
        env.close()


@pytest.mark.slow
def test_the_users_task_runs_on_its_arm_and_on_a_built_in_one() -> None:
    """ReachSparse: the package's task (our reach env, sparse by default), on acme5 and on uniros_async's rx200."""
    from uniros_async.tasks.registry import ENV_IDS

    for env_id, n_joints in (("acme_arms:acme/Acme5ReachSparse-v0", 5), ("acme_arms:acme/Rx200ReachSparse-v0", 5)):
        env = gym.make(env_id, clock="sim")
        try:
            assert env.unwrapped.reward_type == "sparse" and env.action_space.shape == (n_joints,)
            env.reset(seed=0)
            _, reward, _, _, _ = env.step(np.zeros(n_joints, np.float32))
            assert reward in (-1.0, 1.0)
        finally:
            env.close()
    dense = gym.make("acme_arms:acme/Rx200ReachSparse-v0", clock="sim", reward_type="dense")  # the caller's wins
    try:
        assert dense.unwrapped.reward_type == "dense"
    finally:
        dense.close()
    assert ENV_IDS["acme/Rx200ReachSparse-v0"] == ("rx200", "ReachSparse")


@pytest.mark.slow
def test_the_users_arm_runs_in_a_sim_process() -> None:
    """robot="sim-process": the child gets the arm's spec, so it needs no import of the user's package."""
    env = gym.make(ENV_ID, robot="sim-process", action_cycle_s=0.2)
    try:
        env.reset(seed=0)
        assert env.unwrapped.robot_process.is_alive()
        obs, _, _, _, _ = env.step(np.zeros(5, np.float32))
        assert env.observation_space.contains(obs)
    finally:
        env.close()


@pytest.mark.slow
def test_make_vec_runs_the_users_arm_and_placement_in_workers(user_path: str) -> None:
    """Each worker, a fresh interpreter, imports acme_arms for "acme_arms:..." and so finds acme5 and acme-sim; the
    user's 5-joint arm and the rx200 make one padded vector env, as the built-in arms do."""
    venv = uniros_async.make_vec(
        [(ENV_ID, {"robot": "acme-sim"}), "uniros/Rx200Reach-v0"], clock="sim", start_timeout_s=120
    )
    try:
        assert len(set(venv.pids)) == 2 and os.getpid() not in venv.pids
        obs, infos = venv.reset(seed=0)
        assert venv.observation_space.contains(obs)
        for _ in range(3):
            obs, rewards, terminated, truncated, infos = venv.step(venv.action_space.sample())
            assert venv.observation_space.contains(obs) and np.all(np.isfinite(rewards))
        assert infos["env_id"].tolist() == [ENV_ID, "uniros/Rx200Reach-v0"]
    finally:
        venv.close()


def test_the_cli_finds_the_users_arm_as_module_colon_name(user_path: str, tmp_path: Path) -> None:
    out = tmp_path / "acme5.png"
    run = subprocess.run(
        [sys.executable, "-m", "uniros_async.cli", "robot", "render", "acme_arms:acme5", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert run.returncode == 0, run.stderr
    assert out.stat().st_size > 1000 and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_unknown_names_give_the_closest_registered_one() -> None:
    import acme_arms  # noqa: F401  (registers acme5, acme-sim and the acme ids)

    from uniros_async.tasks.registry import register_env_id

    with pytest.raises(ConfigError, match=r"unknown robot 'acme6' \(did you mean 'acme5'\?\); registered: \["):
        get_robot_spec("acme6")
    with pytest.raises(ConfigError, match=r"no placement 'acme-sm' is registered \(did you mean 'acme-sim'\?\)"):
        gym.make(ENV_ID, robot="acme-sm")
    with pytest.raises(ConfigError, match=r"unknown task 'Reech' \(did you mean 'Reach'\?\)"):
        register_env_id("acme5", "Reech")
    with pytest.raises(ConfigError, match=r"unknown robot 'acme' \(did you mean 'acme5'\?\)"):
        register_env_id("acme", "Reach")
    with pytest.raises(gym_error.NameNotFound, match="Did you mean: `Acme5Reach`"):
        gym.make("acme_arms:acme/Acme5Reech-v0")
    with pytest.raises(ConfigError, match=r"did you mean 'acme/Acme5Reach-v0'\?"):
        uniros_async.make("acme_arms:acme/Acme5Reech-v0")


def test_the_howto_shows_the_users_package_as_it_is() -> None:
    """docs/howto/add-a-robot.md, add-a-task.md and add-a-placement.md quote this package's code: every block
    they say is from acme_arms must be the file (or a part of it) word for word."""
    names = ("add-a-robot.md", "add-a-task.md", "add-a-placement.md")
    docs = {name: (REPO / "docs" / "howto" / name).read_text() for name in names}
    sources = {p.name: p.read_text() for p in (HERE / "acme_arms").glob("*.py")}
    quoted = 0
    for name, text in docs.items():
        for block in text.split("```python\n")[1:]:
            code = block.split("```", 1)[0]
            first = code.splitlines()[0]
            if not first.startswith("# acme_arms/"):
                continue
            source = sources[first.removeprefix("# acme_arms/").strip()]
            body = code.split("\n", 1)[1]
            assert body in source, f"{name}: the block from {first} is not that file's text"
            quoted += 1
    assert quoted >= 7
