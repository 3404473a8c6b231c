"""RecordEpisodes on real reach envs (MuJoCo servo sims on the sim clock): every step's observation, action,
reward, goal, success, the env loop's joint states, commands and ticks, and a pixel env's camera frames."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import uniros_async  # noqa: F401  (registers the env ids)
from uniros_async.bag import BagReader, RecordEpisodes
from uniros_async.errors import ConfigError

pytestmark = pytest.mark.slow


def run(env: gym.Env[Any, Any], episodes: int, steps: int) -> list[dict[str, Any]]:
    done = []
    for ep in range(episodes):
        env.reset(seed=ep)
        for k in range(steps):
            action = env.action_space.sample()
            obs, reward, terminated, truncated, info = env.step(action)
            done.append({"episode": ep, "step": k, "action": action, "obs": obs, "reward": reward, "info": info})
            if terminated or truncated:
                break
    return done


def test_every_step_is_recorded_with_the_env_loops_states_commands_and_ticks(tmp_path: Path) -> None:
    env = RecordEpisodes(gym.make("uniros/Rx200ReachGoal-v0", clock="sim"), tmp_path / "run.mcap", episodes_per_file=2)
    env.action_space.seed(0)
    try:
        done = run(env, 3, 4)
    finally:
        env.close()
    assert env.files == [tmp_path / "run-00000.mcap", tmp_path / "run-00001.mcap"]
    got = [bm for f in env.files for bm in BagReader(f).messages()]
    steps = [bm.message for bm in got if bm.topic == "/episodes/step"]
    assert len(steps) == len(done)
    for s, d in zip(steps, done, strict=True):
        assert (s.episode, s.step) == (d["episode"], d["step"])
        assert np.array_equal(s.action, np.asarray(d["action"], np.float64))
        assert np.array_equal(s.observation, d["obs"]["observation"].astype(np.float64))
        assert np.array_equal(s.desired_goal, d["obs"]["desired_goal"].astype(np.float64))
        assert s.reward == pytest.approx(d["reward"]) and s.success == d["info"].get("is_success")
        # the rx200's loop ticks at 10 Hz: an action cycle of 0.8 s holds 8 ticks, each sending a command
        assert len(s.tick_ns) >= 7 and np.all(np.diff(s.tick_ns) == 100_000_000)
        assert s.observation_age_ns is not None and s.step_wall_ns > 0
    states = [bm.message for bm in got if bm.topic == "/episodes/joint_states"]
    commands = [bm.message for bm in got if bm.topic == "/episodes/command"]
    assert len(states) == len(commands) == len(done)
    for s, c, st in zip(states, commands, steps, strict=True):
        assert s.header.stamp_ns <= st.header.stamp_ns and len(s.position) == 8
        assert c.header.stamp_ns == st.command_ns[-1] and c.position.shape == (5,)
    # a process that never imported the wrapper (nor gymnasium) reads the whole bag
    code = (
        "import sys; from uniros_async.bag import BagReader; "
        f"print(len(list(BagReader({str(env.files[0])!r}).messages()))); print('gymnasium' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True).stdout
    assert out.split() == [str(len(list(BagReader(env.files[0]).messages()))), "False"]


def test_a_pixel_env_records_its_camera_frames(tmp_path: Path) -> None:
    env = RecordEpisodes(
        gym.make("uniros/Rx200Reach-v0", clock="sim", obs_mode="pixels+state", image_size=(32, 40)),
        tmp_path / "px.mcap",
    )
    try:
        done = run(env, 1, 3)
    finally:
        env.close()
    frames = [bm.message for bm in BagReader(tmp_path / "px.mcap").messages(["/episodes/camera"])]
    assert len(frames) == len(done)
    for f, d in zip(frames, done, strict=True):
        assert f.data.shape == (32, 40, 3) and np.array_equal(f.data, d["obs"]["pixels"])


def test_bad_settings_are_named(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="episodes_per_file"):
        RecordEpisodes(gym.make("CartPole-v1"), tmp_path / "x.mcap", episodes_per_file=0)
