"""``uniros eval --sweep`` (training/sweep.py): the committed dense policy on the accelerated sim (real MuJoCo)."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import pytest

from uniros_async.errors import ConfigError
from uniros_async.training.sweep import plot_sweep, sweep_checkpoint, write_sweep

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
    assert [p["strength"] for p in curves["backlash"]] == [0.0, 1.0]
    path = write_sweep(result, tmp_path / "sweep.json")
    assert json.loads(path.read_text())["curves"]["backlash"][1]["episodes"] == 2
    png = plot_sweep([result], tmp_path / "sweep.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


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
