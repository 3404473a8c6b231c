"""Randomized imperfections per episode: drawn by the sim at every reset, from the env's seed, reported in the
reset's info; in the env's process, in make_vec workers, in a servo sim process on the wall clock, and under the
concurrent trainer (real MuJoCo, real worker and sim processes)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from uniros_async.bus import open_domain, open_node
from uniros_async.bus.messages import Data
from uniros_async.envs.randomize import draw_episode
from uniros_async.errors import RobotError
from uniros_async.sim.imperfections import KNOBS, Randomization
from uniros_async.sim.node import open_servo_sim
from uniros_async.sim.servo import ServoSimConfig
from uniros_async.sim_clock import SimClock

RANGES = {"sag": (0.0, 1.0), "offsets": (0.5, 2.0), "noise": (0.0, 2.0)}
KWARGS = {"reward_type": "dense", "action_mode": "delta", "randomize": {k: list(v) for k, v in RANGES.items()}}


def _in_ranges(strengths: dict[str, float]) -> bool:
    return set(strengths) == set(KNOBS) and all(
        RANGES[k][0] <= s <= RANGES[k][1] if k in RANGES else s == 0.0 for k, s in strengths.items()
    )


async def test_new_episode_service_draws_from_its_seed_and_reset_keeps_the_draw() -> None:
    async with open_domain("memory://") as domain:
        async with open_servo_sim(
            "rx200",
            domain=domain,
            clock=SimClock(time_scale=None),
            config=ServoSimConfig(command_timeout_s=None),
            randomize=Randomization(ranges=RANGES, seed=7),
        ) as node:
            async with open_node("client", domain=domain, namespace="/rx200") as client_node:
                cli = client_node.create_client(Data, Data, "new_episode")
                first = await draw_episode(cli, 11, timeout_s=5.0)
                assert _in_ranges(first["imperfections"]) and isinstance(first["imperfections_seed"], int)
                gains = node.sim.model.actuator_gainprm[:5, 0].copy()
                node.reset()  # the episode starts with the draw new_episode made: no second draw
                assert node.imperfections is not None and node.imperfections.strengths == first["imperfections"]
                assert np.array_equal(node.sim.model.actuator_gainprm[:5, 0], gains)
                node.reset()  # a reset without new_episode draws afresh
                assert node.imperfections.strengths != first["imperfections"]
                assert (await draw_episode(cli, 11, timeout_s=5.0)) == first  # the same seed, the same draw
                assert (await draw_episode(cli, 12, timeout_s=5.0)) != first
                for bad in ({"seed": -1}, {"seed": "x"}, {"sede": 1}, [1]):
                    reply = await cli.call(Data(value=bad), timeout_s=5.0)
                    assert "expected None or {'seed': int >= 0}" in reply.value["error"]
                # the node still serves after bad input
                assert (await draw_episode(cli, 11, timeout_s=5.0)) == first
                nothing = client_node.create_client(Data, Data, "/ned2/new_episode")
                with pytest.raises(RobotError, match="randomize: no service '/ned2/new_episode'.*expected a servo sim"):
                    await draw_episode(nothing, 1, timeout_s=0.5)


async def test_a_sim_without_randomize_draws_nothing() -> None:
    async with open_domain("memory://") as domain:
        async with open_servo_sim("rx200", domain=domain, clock=SimClock(time_scale=None)):
            async with open_node("client", domain=domain, namespace="/rx200") as client_node:
                cli = client_node.create_client(Data, Data, "new_episode")
                with pytest.raises(RobotError, match="drew no imperfections: {}"):
                    await draw_episode(cli, 1, timeout_s=5.0)


@pytest.mark.slow
def test_make_vec_workers_draw_per_episode_reproducibly_from_the_seed() -> None:
    """Two arms in two worker processes, three resets, twice (about 10 s)."""
    import uniros_async

    def draws(seed: int) -> list[tuple[list[dict[str, float]], list[int]]]:
        venv = uniros_async.make_vec(
            [("uniros/Rx200Reach-v0", {**KWARGS, "clock": "sim"}), ("uniros/Ned2Reach-v0", {**KWARGS, "clock": "sim"})],
            envs_per_worker=1,
        )
        out = []
        try:
            for i in range(3):
                _, info = venv.reset(seed=seed if i == 0 else None)
                imp = info["imperfections"]
                per_env = [{k: float(imp[k][j]) for k in KNOBS} for j in range(2)]
                out.append((per_env, [int(s) for s in info["imperfections_seed"]]))
                venv.step(np.zeros((2, 6), np.float32))
        finally:
            venv.close()
        return out

    first, again = draws(5), draws(5)
    assert first == again  # reproducible from the reset's seed
    assert all(_in_ranges(s) for per_env, _ in first for s in per_env)
    assert len({tuple(s.values()) for per_env, _ in first for s in per_env}) == 6  # every env, every episode anew


@pytest.mark.slow
def test_a_servo_sim_process_on_the_wall_clock_draws_per_episode() -> None:
    """robot='sim-process': the sim in its own process, real time (about 5 s)."""
    import gymnasium as gym

    env = gym.make("uniros/Rx200Reach-v0", **KWARGS, robot="sim-process", clock="wall", action_cycle_s=0.2)
    try:
        assert env.unwrapped.robot_process.is_alive()
        _, a = env.reset(seed=3)
        env.step(env.action_space.sample())
        _, b = env.reset()
        _, c = env.reset(seed=3)
    finally:
        env.close()
    assert _in_ranges(a["imperfections"]) and _in_ranges(b["imperfections"])
    assert a["imperfections"] != b["imperfections"]
    assert (c["imperfections"], c["imperfections_seed"]) == (a["imperfections"], a["imperfections_seed"])


@pytest.mark.slow
def test_the_concurrent_trainer_runs_randomized(tmp_path: Path) -> None:
    """Two arms (the sim and the emulated arm) as one vector env of workers, accelerated, 8 steps (about 15 s)."""
    from uniros_async.training.config import train_config_from_dict
    from uniros_async.training.recipes import train

    run = tmp_path / "randomized"
    cfg: dict[str, Any] = {
        "name": run.name,
        "run_dir": str(run),
        "total_steps": 8,
        "envs": [
            {"id": "uniros/Rx200Reach-v0", "name": "rx200_sim"},
            {"id": "uniros/Ned2Reach-v0", "name": "ned2_real", "kwargs": {"robot": "emulated-real"}},
        ],
        "env_defaults": {"clock": "sim", "max_episode_steps": 4, "reward_type": "dense", "action_mode": "delta"},
        "randomize": {"latency": [0, 2], "noise": [0, 2], "dynamics": [0, 1], "backlash": [0, 2]},
        "placement": "workers",
        "concurrent": True,
        "learner": "sync",
        "td3": {"learning_starts": 4, "buffer_size": 1000, "batch_size": 8, "net_arch": [16, 16]},
        "eval": {"every_steps": 0, "episodes": 1, "final_episodes": 1},
        "checkpoint": {"every_steps": 0},
        "progress_bar": False,
    }
    result = train(train_config_from_dict(cfg))
    assert result.steps == 8
    episodes = (run / "episodes.csv").read_text().splitlines()[1:]
    assert {line.split(",")[1] for line in episodes} == {"rx200_sim", "ned2_real"}
    assert "randomize" in (run / "config.yaml").read_text()
