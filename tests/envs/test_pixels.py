"""Pixel observations (obs_mode) and the pixel reach task, with real rendering of the arm's sim camera."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from _processes import wait_gone

import uniros_async
from uniros_async.errors import ConfigError, RobotError


def _red_pixels(img: np.ndarray) -> int:
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return int(((r > 150) & (g < 80) & (b < 80)).sum())


@pytest.mark.slow
def test_pixel_reach_observes_the_target_only_in_the_frame() -> None:
    # gymnasium's and SB3's env checkers run on this id in tests/envs/test_reach_env.py's sweep of every id
    env = gym.make("uniros/Rx200ReachPixels-v0", clock="sim")
    try:
        space = env.observation_space
        assert isinstance(space, gym.spaces.Dict) and set(space.spaces) == {"pixels", "state"}
        assert space["pixels"].shape == (84, 84, 3) and space["pixels"].dtype == np.uint8
        assert space["state"].shape == (24,)  # the reach vector without the goal's direction and distance
        obs, info = env.reset(seed=3)
        assert _red_pixels(obs["pixels"]) > 5  # the target is in the picture, and only there
        assert info["frame_age_s"] == 0.0 and info["frame_stale"] is False
        obs, _, _, _, info = env.step(env.action_space.sample())
        assert 0 <= info["frame_age_s"] <= 0.1 and not info["frame_stale"]
        assert obs["pixels"].shape == (84, 84, 3)
    finally:
        env.close()


@pytest.mark.slow
def test_pixel_reach_on_the_emulated_real_arm_over_tcp() -> None:
    """The emulated real arm in its own process, in real time: the env renders its camera from the joint states
    that arrive over tcp, in the camera's own thread."""
    env = gym.make("uniros/Rx200ReachPixels-v0", robot="emulated-real", action_cycle_s=0.3)
    try:
        obs, info = env.reset(seed=3)
        assert _red_pixels(obs["pixels"]) > 5 and not info["frame_stale"]
        for _ in range(2):
            obs, _, _, _, info = env.step(env.action_space.sample())
        assert env.observation_space.contains(obs)
        assert 0 <= info["frame_age_s"] < 0.2 and not info["frame_stale"]  # a 30 Hz camera, rendered beside the loop
        stats = env.unwrapped._pixels.cameras.stats[0]
        assert stats.frames > 10
    finally:
        env.close()


def test_the_target_moves_in_the_image_with_the_goal() -> None:
    env = gym.make("uniros/Rx200ReachPixels-v0", clock="sim", obs_mode="pixels")
    try:
        assert set(env.observation_space.spaces) == {"pixels"}
        centres = []
        for seed in range(6):
            obs, _ = env.reset(seed=seed)
            r, g, b = (obs["pixels"][..., k].astype(int) for k in range(3))
            ys, xs = np.nonzero((r > 150) & (g < 80) & (b < 80))
            assert len(xs) > 5, f"seed {seed}: no target in the frame"
            centres.append((ys.mean(), env.unwrapped.goal[1]))
        # the scene camera looks from y = +0.6 m: a target nearer to it (greater y) is lower in the picture
        rows, ys_world = np.array(centres).T
        assert np.corrcoef(rows, ys_world)[0, 1] > 0.8
    finally:
        env.close()


def test_obs_mode_on_the_reach_task() -> None:
    env = gym.make(
        "uniros/Rx200Reach-v0", clock="sim", obs_mode="pixels+state", image_size=(48, 64), camera="wrist_camera"
    )
    try:
        assert env.observation_space["pixels"].shape == (48, 64, 3)
        assert env.observation_space["state"].shape == (28,)
        obs, info = env.reset(seed=0)
        assert obs["pixels"].shape == (48, 64, 3) and obs["pixels"].std() > 5
        assert env.observation_space.contains(obs)
        obs, *_, info = env.step(np.zeros(5, np.float32))
        assert env.observation_space.contains(obs) and "frame_age_s" in info
    finally:
        env.close()


def test_bad_obs_settings_are_named() -> None:
    with pytest.raises(ConfigError, match="obs_mode"):
        gym.make("uniros/Rx200Reach-v0", obs_mode="image")
    with pytest.raises(ConfigError, match="image_size"):
        gym.make("uniros/Rx200Reach-v0", obs_mode="pixels", image_size=(84,))
    with pytest.raises(ConfigError, match="goal-conditioned env takes obs_mode='state'"):
        gym.make("uniros/Rx200ReachGoal-v0", obs_mode="pixels")
    with pytest.raises(ConfigError, match="seen only by the camera"):
        gym.make("uniros/Rx200ReachPixels-v0", obs_mode="state")


def test_no_camera_makes_reset_raise_robot_error_naming_the_topic() -> None:
    env = gym.make("uniros/Rx200Reach-v0", clock="sim", obs_mode="pixels", sim_camera=False, camera_timeout_s=0.2)
    try:
        with pytest.raises(RobotError, match=r"no camera frame on /rx200/camera/color/image_raw .*none arrived"):
            env.reset(seed=0)
    finally:
        env.close()


@pytest.mark.slow
def test_a_camera_that_stops_flags_stale_frames_after_its_timeout() -> None:
    env = gym.make(
        "uniros/Rx200ReachPixels-v0", clock="wall", action_cycle_s=0.2, camera_timeout_s=0.3, camera_rate_hz=15
    )
    try:
        env.reset(seed=0)
        *_, info = env.step(np.zeros(5, np.float32))
        assert not info["frame_stale"] and info["frame_age_s"] < 0.3
        cams = env.unwrapped._pixels.cameras
        cams.stop()
        t0 = time.monotonic()
        stale_after = None
        for _ in range(6):
            *_, info = env.step(np.zeros(5, np.float32))
            if info["frame_stale"]:
                stale_after = time.monotonic() - t0
                break
        assert stale_after is not None and info["frame_age_s"] > 0.3
        assert stale_after < 0.3 + 0.2 * 2 + 0.2  # within a step or so of the timeout
        render_pid = cams._process.pid  # on a wall clock the camera renders in a process of its own
        assert render_pid is not None
    finally:
        env.close()
    assert wait_gone([render_pid], 10.0) == []  # and it ends with the env


@pytest.mark.slow
@pytest.mark.parametrize(("transport", "envs_per_worker"), [("tcp", 1), ("shm", 2)])  # shm: also two envs a worker
def test_make_vec_with_pixel_observations(transport: str, envs_per_worker: int) -> None:
    envs = uniros_async.make_vec(
        ["uniros/Rx200ReachPixels-v0"] * 2, clock="sim", transport=transport, envs_per_worker=envs_per_worker
    )
    try:
        obs, info = envs.reset(seed=[1, 2])
        assert obs["pixels"].shape == (2, 84, 84, 3) and obs["pixels"].dtype == np.uint8
        assert obs["state"].shape == (2, 24)
        assert all(_red_pixels(obs["pixels"][i]) > 5 for i in range(2))
        assert not np.array_equal(obs["pixels"][0], obs["pixels"][1])  # two goals, two pictures
        for _ in range(3):
            obs, reward, term, trunc, info = envs.step(envs.action_space.sample())
        assert obs["pixels"].shape == (2, 84, 84, 3) and np.all(info["frame_age_s"] <= 0.1)
    finally:
        envs.close()


@pytest.mark.slow
def test_a_script_without_a_main_guard_runs_a_wall_clock_pixel_env(tmp_path: Path) -> None:
    # the render process is a fresh interpreter (python -m), not a multiprocessing spawn that re-runs the script
    script = tmp_path / "no_guard.py"
    script.write_text(
        "import gymnasium as gym\n"
        "import uniros_async\n"
        "env = gym.make('uniros/Rx200ReachPixels-v0', action_cycle_s=0.2)\n"
        "obs, info = env.reset(seed=0)\n"
        "obs, *_, info = env.step(env.action_space.sample())\n"
        "print('ok', obs['pixels'].shape, info['frame_stale'])\n"
        "env.close()\n"
    )
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "ok (84, 84, 3) False"


def test_a_real_cameras_frames_are_converted_to_the_observations_size_and_rgb() -> None:
    from uniros_async.bus.messages import Header, Image
    from uniros_async.envs.config import EnvConfig
    from uniros_async.envs.pixels import PixelSource
    from uniros_async.robots import get_robot_spec

    src = PixelSource(EnvConfig(obs_mode="pixels", image_size=(8, 12)), get_robot_spec("rx200"))
    bgr = np.zeros((16, 24, 3), np.uint8)
    bgr[..., 0] = 200  # blue in BGR
    out = src._rgb(Image(header=Header(), encoding="bgr8", data=bgr))
    assert out is not None and out.shape == (8, 12, 3) and out[0, 0].tolist() == [0, 0, 200]
    mono = np.full((8, 12, 1), 77, np.uint8)
    out = src._rgb(Image(header=Header(), encoding="mono8", data=mono))
    assert out is not None and out.shape == (8, 12, 3) and (out == 77).all()
    assert src._rgb(Image(header=Header(), encoding="rgb8", data=np.zeros((8, 12, 4), np.uint8))) is None


@pytest.mark.slow
@pytest.mark.parametrize(
    ("env_id", "obs_mode"), [("uniros/Rx200ReachPixels-v0", "pixels"), ("uniros/Ned2Reach-v0", "pixels+state")]
)
def test_gymnasium_and_sb3_checkers_pass_the_other_pixel_modes(env_id: str, obs_mode: str) -> None:
    # the pixel task's default (pixels+state) is in tests/envs/test_reach_env.py's sweep of every id; 48x64: SB3 warns
    # below 36x36 (its CnnPolicy's smallest)
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = gym.make(env_id, clock="sim", obs_mode=obs_mode, image_size=(48, 64))
    try:
        check_env(env.unwrapped, skip_render_check=True)
        sb3_check_env(env.unwrapped, warn=True)
        obs, _ = env.reset(seed=0)
        assert obs["pixels"].shape == (48, 64, 3) and ("state" in obs) is (obs_mode == "pixels+state")
    finally:
        env.close()
