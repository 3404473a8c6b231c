"""Real-time concurrent multi-task training end to end, a few steps on the wall clock (not a benchmark: it asserts
the pipeline, not timing figures): every env acts in every step, the transitions go to one replay buffer, the
evaluation steps the envs at once, and the run records wall times and the envs' action-cycle statistics."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import pytest

from uniros_async.errors import ConfigError
from uniros_async.priority import real_time_thread
from uniros_async.training.config import train_config_from_dict
from uniros_async.training.recipes import train

pytestmark = pytest.mark.slow

EPISODE_STEPS = 4
VECTOR_STEPS = 6
CYCLE_S = 0.4


def _cfg(run_dir: Path, learner: str, **over: Any) -> Any:
    return train_config_from_dict(
        {
            "name": run_dir.name,
            "run_dir": str(run_dir),
            "total_steps": 2 * VECTOR_STEPS,
            "envs": [
                {"id": "uniros/Rx200Reach-v0", "name": "rx200_sim"},
                {"id": "uniros/Ned2Reach-v0", "name": "ned2_real", "kwargs": {"robot": "emulated-real"}},
            ],
            # short episodes, so that every env ends one within the run and the evaluation is quick
            "env_defaults": {"clock": "wall", "action_cycle_s": CYCLE_S, "max_episode_steps": EPISODE_STEPS},
            "placement": "workers",
            "concurrent": True,
            "learner": learner,
            "td3": {"learning_starts": 4, "buffer_size": 1000, "batch_size": 8, "net_arch": [16, 16]},
            "eval": {"every_steps": 0, "episodes": 1, "final_episodes": 2},
            "checkpoint": {"every_steps": 0},
            "progress_bar": False,
            **over,
        }
    )


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.parametrize("learner", ["async", "sync"])
def test_four_arms_train_at_once_in_real_time(tmp_path: Path, learner: str) -> None:
    run = tmp_path / f"rt_{learner}"
    result = train(_cfg(run, learner))
    assert result.steps == 2 * VECTOR_STEPS

    # both envs acted in every step: each ended its first episode in the same vector step (2 transitions a step)
    episodes = _rows(run / "episodes.csv")
    firsts = {r["task"]: r for r in reversed(episodes)}
    assert set(firsts) == {"rx200_sim", "ned2_real"}
    assert {int(r["step"]) for r in firsts.values()} == {2 * EPISODE_STEPS}
    assert all(int(r["length"]) == EPISODE_STEPS for r in firsts.values())
    # on the wall clock: the episode took its action cycles of real time
    assert all(float(r["wall_s"]) >= (EPISODE_STEPS - 1) * CYCLE_S for r in firsts.values())

    # the final evaluation ran both envs at once, its episode count per env
    final = json.loads((run / "final_eval.json").read_text())
    assert [(r["label"], r["episodes"]) for r in final["results"]] == [("rx200_sim", 2), ("ned2_real", 2)]
    evals = _rows(run / "eval.csv")
    assert {r["task"] for r in evals} == {"rx200_sim", "ned2_real"} and all(float(r["wall_s"]) > 0 for r in evals)

    # the action cycle of every env was recorded while training, and env steps per wall hour
    timing = json.loads((run / "timing.json").read_text())
    assert timing["learner"] == learner and timing["env_steps"] == 2 * VECTOR_STEPS
    assert timing["env_steps_per_wall_hour"] > 0
    for label in ("rx200_sim", "ned2_real"):
        cycle = timing["envs"][label]["action_cycle"]
        assert cycle["count"] >= 1 and cycle["p50"] is not None
    assert {r["metric"] for r in _rows(run / "timing.csv")} >= {"action_cycle", "actuator_cycle"}

    # one replay buffer held both envs' transitions (padded to the larger sizes: ned2's 6 actions, rx200's 28 obs)
    from uniros_async.training.checkpoint import read_meta

    meta = read_meta(result.checkpoint)
    assert (meta.obs_size, meta.action_size, meta.pad_to) == (28, 6, (28, 6))

    # success against wall-clock minutes; a run whose logs have no wall times is refused for that axis
    from uniros_async.training.plot import plot_runs

    assert plot_runs([run], out=tmp_path / "minutes.png", x="minutes").stat().st_size > 0
    old = tmp_path / "old_run"
    old.mkdir()
    (old / "eval.csv").write_text("step,task,success_rate,mean_return,mean_length,episodes\n100,a,0.5,1.0,10,5\n")
    with pytest.raises(ConfigError, match="no wall_s column"):
        plot_runs([old], out=tmp_path / "old.png", x="minutes")
    assert plot_runs([old], out=tmp_path / "old_steps.png").is_file()


def test_evaluation_alongside_training_does_not_pause_it(tmp_path: Path) -> None:
    """eval.alongside: the periodic evaluations step a second set of the envs in a process while training goes on."""
    run = tmp_path / "alongside"
    steps = 4 * VECTOR_STEPS
    result = train(
        _cfg(
            run,
            "async",
            total_steps=steps,
            eval={"every_steps": 4, "episodes": 1, "final_episodes": 2, "alongside": True},
            # the evaluation process gives its envs the same one-hot index as training's (a policy that takes one
            # would refuse observations without it)
            task_id_in_obs=True,
        ),
    )
    assert result.steps == steps

    evals = _rows(run / "eval.csv")
    periodic = [r for r in evals if int(r["step"]) < steps]
    assert periodic, evals
    first = min(periodic, key=lambda r: float(r["wall_s"]))
    # training went on while that evaluation ran: a training episode ended after the evaluation's step and before
    # its results were written (an evaluation episode takes EPISODE_STEPS action cycles, a vector step one)
    episodes = _rows(run / "episodes.csv")
    assert any(int(e["step"]) > int(first["step"]) and float(e["wall_s"]) < float(first["wall_s"]) for e in episodes), (
        first,
        episodes,
    )
    # the final evaluation ran on the evaluation envs, its episode count per env
    final = json.loads((run / "final_eval.json").read_text())
    assert [(r["label"], r["episodes"]) for r in final["results"]] == [("rx200_sim", 2), ("ned2_real", 2)]
    assert {(int(r["step"]), r["task"]) for r in evals} >= {(steps, "rx200_sim"), (steps, "ned2_real")}

    # the evaluation envs' action cycles are recorded beside the training envs'
    timing = json.loads((run / "timing.json").read_text())
    assert timing["eval_alongside"] is True
    # the evaluation process acted in the real-time class, as the acting thread of training does (where permitted)
    with real_time_thread() as permitted:
        pass
    assert timing["eval_real_time"] is permitted
    for label in ("rx200_sim", "ned2_real"):
        assert timing["eval_envs"][label]["action_cycle"]["count"] >= 1
        assert timing["envs"][label]["action_cycle"]["count"] >= 1


def test_wall_budget_stops_a_run(tmp_path: Path) -> None:
    run = tmp_path / "budget"
    result = train(_cfg(run, "async", total_steps=10_000, max_wall_s=3 * CYCLE_S))
    assert 2 <= result.steps < 10_000


@pytest.mark.parametrize(
    ("over", "match"),
    [
        ({"placement": "inprocess"}, "needs placement: workers"),
        ({"drop_observation": [0]}, "does not support drop_observation"),
        ({"eval": {"envs": ["uniros/Rx200Reach-v0"]}}, "remove eval.envs"),
        ({"concurrent": False, "eval": {"alongside": True}}, "eval.alongside: .*needs concurrent: true"),
        ({"max_wall_s": 0}, "max_wall_s: must be > 0, got 0"),
        ({"eval": {"final_episodes": 0}}, "eval.final_episodes: must be >= 1, got 0"),
    ],
)
def test_concurrent_settings_are_checked(tmp_path: Path, over: dict[str, Any], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        _cfg(tmp_path / "bad", "async", **over)


def test_progress_lines_to_a_file_carry_the_timing_windows(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """With stderr not a terminal (nohup, a log file), the progress bar writes plain lines, and the per-window
    line (steps, success, action cycle per env) goes through it as through tqdm's."""
    from uniros_async.training import recipes

    monkeypatch.setattr(recipes, "TIMING_WINDOW_STEPS", 2)
    result = train(_cfg(tmp_path / "lines", "async", progress_bar=True))
    assert result.steps == 2 * VECTOR_STEPS
    err = capsys.readouterr().err
    window_lines = [line for line in err.splitlines() if "rx200_sim" in line and "ned2_real" in line]
    assert window_lines, err
    assert "\r" not in err
