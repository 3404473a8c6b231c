"""Episodes recorded while training (the config's ``record:`` key) and while evaluating (``uniros eval
--record``): real TD3 on the rx200's servo sim, on the sim clock."""

from __future__ import annotations

from pathlib import Path

import pytest

from uniros_async.bag import BagReader
from uniros_async.training.config import train_config_from_dict

pytestmark = pytest.mark.slow


def test_training_and_eval_write_their_steps(tmp_path: Path) -> None:
    from uniros_async.cli import main
    from uniros_async.training.recipes import train

    run = tmp_path / "run"
    cfg = train_config_from_dict(
        {
            "name": "rec",
            "total_steps": 40,
            "envs": [{"id": "uniros/Rx200Reach-v0", "kwargs": {"max_episode_steps": 15}}],
            "td3": {"learning_starts": 20, "buffer_size": 1000, "net_arch": [16, 16], "batch_size": 16},
            "eval": {"every_steps": 0, "episodes": 1},
            "checkpoint": {"every_steps": 0, "replay_buffer": False},
            "run_dir": str(run),
            "progress_bar": False,
            "record": {"episodes_per_file": 1},
        }
    )
    train(cfg)
    files = sorted(run.glob("episodes-*.mcap"))
    steps = [bm.message for f in files for bm in BagReader(f).messages(["/episodes/step"])]
    assert len(steps) == 40  # every training step, the final evaluation's are not the training env's
    assert len(files) == len({s.episode for s in steps}) >= 2  # a file per episode
    assert all(len(s.action) == 5 and s.observation is not None for s in steps)

    bag = tmp_path / "eval.mcap"
    assert main(["eval", str(run), "--env", "uniros/Rx200Reach-v0", "--episodes", "2", "--no-progress",
                 "--record", str(bag)]) == 0  # fmt: skip
    info = BagReader(bag).info()
    assert info.complete and info.topics["/episodes/step"].count >= 2
    assert info.topics["/episodes/joint_states"].count == info.topics["/episodes/step"].count


def test_record_is_refused_on_concurrent_runs() -> None:
    from uniros_async.errors import ConfigError

    with pytest.raises(ConfigError, match="record"):
        train_config_from_dict(
            {"envs": ["uniros/Rx200Reach-v0"], "placement": "workers", "concurrent": True, "record": {}}
        )
