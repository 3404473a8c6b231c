"""``uniros eval --sweep`` (training/sweep.py): the committed dense policy on the accelerated sim (real MuJoCo)."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import pytest

from uniros_async.errors import ConfigError
from uniros_async.training.sweep import main, plot_compare, plot_sweep, sweep_checkpoint, wilson, write_sweep

ROOT = Path(__file__).resolve().parents[2]
DENSE = ROOT / "docs" / "results" / "checkpoints" / "rx200_reach_dense_td3_uniros"
KWARGS = {"reward_type": "dense", "action_mode": "delta", "robot": "sim", "clock": "sim"}


@pytest.mark.slow
def test_sweep_writes_json_and_plot(tmp_path: Path) -> None:
    """Two curves, two strengths, two episodes each (a few seconds)."""
    result = sweep_checkpoint(
        DENSE, "uniros/Rx200Reach-v0", KWARGS, episodes=2, curves=("all", "backlash"), strengths=(0.0, 1.0)
    )
    curves = result["curves"]
    assert set(curves) == {"all", "backlash"}
    assert curves["all"][0] is curves["backlash"][0]  # strength 0 is one env, evaluated once
    assert curves["all"][0]["success_rate"] == 1.0 and curves["all"][0]["episodes"] == 2
    assert curves["all"][0]["wilson95"] == list(wilson(2, 2))
    assert [p["strength"] for p in curves["backlash"]] == [0.0, 1.0]
    path = write_sweep(result, tmp_path / "sweep.json")
    assert json.loads(path.read_text())["curves"]["backlash"][1]["episodes"] == 2
    png = plot_sweep([result], tmp_path / "sweep.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main([str(path), str(path), "--labels", "a", "b", "--out", str(tmp_path / "cmp.png")]) == 0
    assert (tmp_path / "cmp.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ConfigError, match=r"has no curve 'sag'; it has \['all', 'backlash'\]"):
        plot_compare([result], tmp_path / "x.png", curve="sag")


def test_wilson_interval() -> None:
    # the textbook figures: 0/10 -> [0, 0.278], 10/10 -> [0.722, 1], 5/10 -> [0.237, 0.763]
    assert wilson(0, 10) == (0.0, pytest.approx(0.2775, abs=1e-4))
    assert wilson(10, 10) == (pytest.approx(0.7225, abs=1e-4), 1.0)
    assert wilson(5, 10) == (pytest.approx(0.2366, abs=1e-4), pytest.approx(0.7634, abs=1e-4))
    lo, hi = wilson(190, 200)
    assert lo < 0.95 < hi
    with pytest.raises(ConfigError, match=r"wilson: expected 0 <= successes <= n and n >= 1, got 3/2"):
        wilson(3, 2)


@pytest.mark.slow
def test_each_episode_of_a_sweep_point_is_a_new_arm_at_that_strength() -> None:
    """A sweep point's env: randomize at [s, s], so every reset draws a new arm of strength s (about 2 s)."""
    import uniros_async  # noqa: F401  (registers the envs)

    env = gym.make("uniros/Rx200Reach-v0", **KWARGS, randomize={"offsets": [1.5, 1.5], "dynamics": [1.5, 1.5]})
    try:
        _, a = env.reset(seed=0)
        _, b = env.reset()
    finally:
        env.close()
    assert a["imperfections"]["offsets"] == b["imperfections"]["offsets"] == 1.5
    assert a["imperfections"]["sag"] == 0.0
    assert a["imperfections_seed"] != b["imperfections_seed"]  # another arm: offsets and dynamics drawn anew


def test_sweep_bad_input_is_named() -> None:
    with pytest.raises(ConfigError, match=r"--sweep-knobs: unknown \['backlsh'\]"):
        sweep_checkpoint(DENSE, "uniros/Rx200Reach-v0", KWARGS, curves=("backlsh",))
    with pytest.raises(ConfigError, match=r"--strengths: expected values in \[0, 3.0\], got \[5.0\]"):
        sweep_checkpoint(DENSE, "uniros/Rx200Reach-v0", KWARGS, strengths=(5.0,))
    with pytest.raises(ConfigError, match="leave it out of --env-kwargs"):
        sweep_checkpoint(DENSE, "uniros/Rx200Reach-v0", {**KWARGS, "imperfections": 1.0})


def test_env_key_checks_the_knobs() -> None:
    with pytest.raises(ConfigError, match=r"unknown knob\(s\) \['backlsh'\]"):
        gym.make("uniros/Rx200Reach-v0", **{**KWARGS, "imperfections": {"backlsh": 1.0}})


def test_train_config_randomize_reaches_every_training_env() -> None:
    from uniros_async.training.config import TrainConfig

    cfg = TrainConfig(
        envs=["uniros/Rx200Reach-v0", {"id": "uniros/Ned2Reach-v0", "kwargs": {"randomize": {"noise": [0, 1]}}}],
        randomize={"sag": [0.0, 2.0]},
    )
    (_, _, rx), (_, _, ned) = cfg.env_specs()
    assert rx["randomize"] == {"sag": (0.0, 2.0)} and rx["clock"] == "sim"
    assert ned["randomize"] == {"noise": [0, 1]}  # an env's own setting wins


@pytest.mark.slow
def test_randomized_envs_in_make_vec_workers() -> None:
    """Two rx200s in worker processes, the same goals and actions: randomized, their arms differ (a few s)."""
    import numpy as np

    import uniros_async

    def run(randomize: dict[str, list[float]] | None) -> np.ndarray:
        specs = [
            ("uniros/Rx200Reach-v0", {**KWARGS, "emulation_seed": i, **({"randomize": randomize} if randomize else {})})
            for i in (0, 1)
        ]
        venv = uniros_async.make_vec(specs, envs_per_worker=1)
        try:
            venv.reset(seed=[0, 0])
            obs, *_ = venv.step(np.full((2, 5), 0.5, np.float32))
            obs, *_ = venv.step(np.full((2, 5), 0.5, np.float32))
            return np.asarray(obs)
        finally:
            venv.close()

    nominal, randomized = run(None), run({"sag": [1.0, 3.0], "offsets": [1.0, 3.0]})
    assert np.array_equal(nominal[0], nominal[1])
    assert not np.allclose(randomized[0], randomized[1])
