"""eval.alongside evaluates in a process of its own (training/eval_process.py): its results come back, its arms step
while the asynchronous learner learns, the policy's weights and observation statistics go with each request, errors
come back named, and closing it (also by Ctrl-C of `uniros train`) leaves no process behind."""

from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import yaml

from uniros_async.errors import ConfigError, UnirosError
from uniros_async.priority import LOOP_RT_PRIORITY, RESET_ON_FORK
from uniros_async.training.alongside import open_alongside, phase_bases, phased, policy_request, rank_bases
from uniros_async.training.eval_process import _load, _PolicyCopy

CYCLE_S = 0.2
EPISODE_STEPS = 3
ENV = {"clock": "wall", "action_cycle_s": CYCLE_S, "max_episode_steps": EPISODE_STEPS}
SPECS = [("rx200_sim", "uniros/Rx200Reach-v0", ENV)]


def _running(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie waiting for its parent counts as ended)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError, IndexError):
        return False
    return state not in ("Z", "X")


def _descendants(pid: int) -> list[int]:
    out: list[int] = []
    todo = [pid]
    while todo:
        p = todo.pop()
        try:
            tids = os.listdir(f"/proc/{p}/task")
        except FileNotFoundError:
            continue
        for tid in tids:
            try:
                kids = [int(c) for c in Path(f"/proc/{p}/task/{tid}/children").read_text().split()]
            except FileNotFoundError:
                continue
            out += kids
            todo += kids
    return out


def _rr_priorities(pids: list[int]) -> set[int]:
    """The SCHED_RR priorities of the threads of ``pids`` (a worker's env loop is its only real-time thread)."""
    from uniros_async.priority import thread_scheduling

    threads = [t for pid in pids for t in thread_scheduling(pid).values()]
    return {prio for policy, prio in threads if policy & ~RESET_ON_FORK == os.SCHED_RR}


def _uniros_shm() -> set[str]:
    return {n for n in os.listdir("/dev/shm") if "uniros" in n}


def test_a_request_carries_the_live_weights_and_frozen_statistics() -> None:
    """No process: the request's weights rebuild a policy that acts as the live one; the statistics are a frozen
    copy that later training does not move."""
    from stable_baselines3 import TD3
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    vec = VecNormalize(DummyVecEnv([lambda: gym.make("Pendulum-v1")]), norm_reward=False)
    model = TD3(
        "MlpPolicy",
        vec,
        policy_kwargs={"net_arch": [16, 16]},
        learning_starts=10,
        buffer_size=200,
        seed=3,
        device="cpu",
    )
    model.learn(40)
    request = policy_request(model, episodes=2, seed=5, with_skeleton=True)
    assert (request.episodes, request.seed) == (2, 5)
    assert set(request.weights) == set(model.policy.actor.state_dict())
    copy = _PolicyCopy(_load(None, request), request.obs_stats)
    obs = np.random.default_rng(0).normal(size=(8, 3)).astype(np.float32)
    np.testing.assert_allclose(copy.predict(obs)[0], model.policy.predict(obs, deterministic=True)[0], rtol=1e-6)
    stats = copy.get_vec_normalize_env()
    assert stats is not None and stats.training is False
    mean = stats.obs_rms.mean.copy()
    model.learn(40, reset_num_timesteps=False)  # training goes on: the live statistics move, the copy's do not
    assert not np.allclose(vec.obs_rms.mean, mean) and np.allclose(stats.obs_rms.mean, mean)
    # a later request without the skeleton loads into the policy the process already has
    again = _load(copy.policy, policy_request(model, episodes=1, seed=0, with_skeleton=False))
    np.testing.assert_allclose(again.predict(obs)[0], model.policy.predict(obs, deterministic=True)[0], rtol=1e-6)
    with pytest.raises(UnirosError, match="without the policy's class"):
        _load(None, policy_request(model, episodes=1, seed=0, with_skeleton=False))


def test_errors_of_the_evaluation_process_come_back_as_raised() -> None:
    """Through the pipe: a WorkerError (keyword-only arguments: no plain pickle round trip) keeps its class and
    index; an error that pickles is itself, with the process's traceback as a note; any other is named."""
    from uniros_async.errors import StepTimeoutError
    from uniros_async.training.eval_process import _portable, _rebuilt

    def through_pipe(exc: BaseException) -> BaseException:
        return _rebuilt(pickle.loads(pickle.dumps(_portable(exc))))

    timeout = through_pipe(StepTimeoutError(2, "no reply to step within 1.5 s", remote_traceback="tb"))
    assert type(timeout) is StepTimeoutError and timeout.index == 2
    assert str(timeout).startswith("worker 2: no reply to step within 1.5 s")
    bad = through_pipe(ConfigError("unknown key 'x'"))
    assert type(bad) is ConfigError and str(bad) == "unknown key 'x'" and "evaluation process" in bad.__notes__[0]

    class Odd(Exception):
        def __init__(self, a: str, *, b: int) -> None:
            super().__init__(a)

    odd = through_pipe(Odd("x", b=1))
    assert type(odd) is UnirosError and "Odd: x" in str(odd)


@pytest.mark.slow
def test_alongside_evaluates_in_its_own_process_while_the_learner_learns() -> None:
    from uniros_async.training.async_td3 import AsyncTD3
    from uniros_async.training.concurrent import open_concurrent_env

    shm_before = _uniros_shm()
    train_base, eval_base = rank_bases("training", len(SPECS))  # eval.alongside_rank's default, as train opens them
    train_venv = open_concurrent_env(
        SPECS, rt_rank_base=train_base, loop_phase_base=phase_bases("training", len(SPECS))[0]
    )
    alongside = open_alongside(SPECS, real_time=True, rank="training")
    pids: list[int] = []
    try:
        pid = alongside.process.pid
        assert pid is not None and pid != os.getpid() and _running(pid)
        pids = [pid, *_descendants(pid)]
        assert len(pids) > 1, "the evaluation arms' workers are the evaluation process's children"
        if os.geteuid() == 0:  # SCHED_RR needs root or CAP_SYS_NICE (CI runs as root): the loops' ranks
            training_workers = [p for p in _descendants(os.getpid()) if p not in pids]
            assert _rr_priorities(training_workers) == {LOOP_RT_PRIORITY + 1}, "the training arm's loop ranks above"
            assert _rr_priorities(pids[1:]) == {LOOP_RT_PRIORITY}
        model = AsyncTD3(
            "MlpPolicy",
            train_venv,
            learning_starts=2,
            batch_size=4,
            buffer_size=500,
            policy_kwargs={"net_arch": [16, 16]},
            seed=0,
            device="cpu",
        )
        seen: list[tuple[int, int]] = []  # (learner updates, evaluation progress) at every training step
        results: list[Any] = []

        from stable_baselines3.common.callbacks import BaseCallback

        class Evaluate(BaseCallback):
            def _on_step(self) -> bool:
                step = self.num_timesteps
                if not alongside.busy():
                    alongside.request(self.model, step, 1, seed=step)
                done = alongside.take(self.model, step, 1, seed=step)
                if done is not None:
                    results.append(done)
                seen.append((int(self.model._n_updates), int(alongside.process._progress.value)))
                return len(results) < 2  # two evaluations back: enough (the step cap: 60 s of action cycles)

        model.learn(total_timesteps=300, callback=Evaluate())
        assert len(results) == 2, "two evaluations did not come back within 300 action cycles"
        at, took_s, first = results[0]
        assert [(r.label, r.episodes, r.mean_length) for r in first] == [("rx200_sim", 1, EPISODE_STEPS)]
        assert took_s >= (EPISODE_STEPS - 1) * CYCLE_S
        # between two training steps the learner made updates and the evaluation arms stepped, both
        pairs = zip(seen, seen[1:], strict=False)
        assert any(u1 > u0 > 0 and p1 > p0 for (u0, p0), (u1, p1) in pairs), seen
        # the evaluation arms' action cycles came back with the results, as timing.json reports them
        assert len(alongside.samples["rx200_sim"]["action_cycle"]) >= len(results)
        # a running evaluation stopped, then the final one: to its end
        alongside.request(model, 300, 1, seed=0)
        assert alongside.busy()
        alongside.cancel()
        assert not alongside.busy() and alongside.take(model, 300, 1, seed=0) is None
        final = alongside.evaluate(model, 2, seed=1)
        assert [(r.label, r.episodes) for r in final] == [("rx200_sim", 2)]
    finally:
        alongside.close()
        train_venv.close()
    assert not [p for p in pids if _running(p)], "a process of the evaluation outlived close()"
    assert _uniros_shm() <= shm_before
    alongside.close()  # idempotent


def test_alongside_rank_sets_which_arms_loops_rank_higher() -> None:
    from uniros_async.training.config import train_config_from_dict

    def order(**eval_cfg: Any) -> str:
        cfg = {
            "envs": [{"id": "CartPole-v1"}],
            "placement": "workers",
            "concurrent": True,
            "eval": {"alongside": True, **eval_cfg},
        }
        return str(train_config_from_dict(cfg).eval.alongside_rank)

    # (training, evaluation) rt_rank_base: the set ranked higher starts above the other's n_envs loops
    assert order() == "training" and rank_bases(order(), 4) == (4, 0)
    assert rank_bases(order(alongside_rank="evaluation"), 4) == (0, 4)
    # (training, evaluation) loop_phase_base: the set ranked higher ticks first, the other in the phases after it
    assert phase_bases("training", 4) == (0, 4) and phase_bases("evaluation", 4) == (4, 0)
    with pytest.raises(ConfigError, match="eval.alongside_rank: expected one of 'training', 'evaluation', got 'eval'"):
        order(alongside_rank="eval")
    with pytest.raises(ConfigError, match="eval.alongside_rank must be one of training, evaluation, got 'both'"):
        rank_bases("both", 4)
    with pytest.raises(ConfigError, match="the number of envs must be an int >= 1, got 0"):
        rank_bases("training", 0)
    with pytest.raises(ConfigError, match="eval.alongside_rank must be one of training, evaluation, got 'both'"):
        phase_bases("both", 4)
    before = set(_descendants(os.getpid()))
    with pytest.raises(ConfigError, match="alongside_rank must be one of"):
        open_alongside(SPECS, real_time=False, rank="both")
    assert set(_descendants(os.getpid())) <= before, "a bad rank started a process"


def test_alongside_phase_moves_the_evaluation_arms_cycles_off_the_training_arms() -> None:
    from uniros_async.training.config import train_config_from_dict

    def phase(**eval_cfg: Any) -> float:
        cfg = {"envs": [{"id": "CartPole-v1"}], "placement": "workers", "concurrent": True}
        cfg["eval"] = {"alongside": True, **eval_cfg}
        return float(train_config_from_dict(cfg).eval.alongside_phase)

    assert phase() == 0.5
    with pytest.raises(ConfigError, match="eval.alongside_phase"):
        phase(alongside_phase=1.0)
    specs = [
        ("a", "uniros/Rx200Reach-v0", {"robot": "sim"}),
        ("b", "uniros/Ned2Reach-v0", {"action_cycle_phase": 0.75}),
    ]
    # after the training envs' own phase, wrapping round the cycle; the training envs' kwargs are left alone
    assert phased(specs, 0.5) == [
        ("a", "uniros/Rx200Reach-v0", {"robot": "sim", "action_cycle_phase": 0.5}),
        ("b", "uniros/Ned2Reach-v0", {"action_cycle_phase": 0.25}),
    ]
    assert specs[0][2] == {"robot": "sim"}
    for bad in (1.0, -0.1, True, "half"):
        with pytest.raises(ConfigError, match=r"eval.alongside_phase must be a number in \[0, 1\), got"):
            phased(specs, bad)  # type: ignore[arg-type]
    before = set(_descendants(os.getpid()))
    with pytest.raises(ConfigError, match="eval.alongside_phase must be"):
        open_alongside(SPECS, real_time=True, phase=2.0)
    assert set(_descendants(os.getpid())) <= before, "a bad phase started a process"


def test_a_negative_rank_base_is_refused_before_anything_starts() -> None:
    from uniros_async.runtime import make_vec

    before = set(_descendants(os.getpid()))
    with pytest.raises(ConfigError, match="rt_rank_base must be an int >= 0, got -1"):
        make_vec(["CartPole-v1"], rt_rank_base=-1)
    with pytest.raises(ConfigError, match="loop_phase_base must be None or an int >= 0, got -1"):
        make_vec(["CartPole-v1"], loop_phase_base=-1)
    assert set(_descendants(os.getpid())) <= before


@pytest.mark.slow
def test_a_bad_env_is_named_and_leaves_no_process() -> None:
    before = set(_descendants(os.getpid()))
    with pytest.raises(ConfigError, match="max_episode_stepz"):
        open_alongside([("rx200_sim", "uniros/Rx200Reach-v0", {**ENV, "max_episode_stepz": 3})], real_time=False)
    deadline = time.monotonic() + 10.0
    while set(_descendants(os.getpid())) - before and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not set(_descendants(os.getpid())) - before


def _train_config(run_dir: Path) -> dict[str, Any]:
    return {
        "name": "alongside_signal",
        "run_dir": str(run_dir),
        "total_steps": 100_000,
        "envs": [{"id": "uniros/Rx200Reach-v0", "name": "rx200_sim"}],
        "env_defaults": ENV,
        "placement": "workers",
        "concurrent": True,
        "learner": "async",
        "td3": {"learning_starts": 2, "buffer_size": 1000, "batch_size": 4, "net_arch": [16, 16]},
        "eval": {"every_steps": 2, "episodes": 1, "final_episodes": 1, "alongside": True},
        "checkpoint": {"every_steps": 0},
        "progress_bar": False,
    }


@pytest.mark.slow
def test_ctrl_c_of_uniros_train_leaves_no_evaluation_process(tmp_path: Path) -> None:
    """Ctrl-C while an evaluation alongside runs: SIGINT to the whole process group, so the evaluation process and
    its workers get it too (they ignore it: `train` closes them). train stops, and every process it started ends.
    (SIGTERM to `train` alone takes the same way out: its handler raises KeyboardInterrupt in `train`.) With
    ``eval.alongside_rank: evaluation`` (not the default), the evaluation arm's loop ranks above the training arm's."""
    cfg = tmp_path / "cfg.yaml"
    config = _train_config(tmp_path / "run")
    config["eval"]["alongside_rank"] = "evaluation"
    cfg.write_text(yaml.safe_dump(config))
    proc = subprocess.Popen(
        [sys.executable, "-m", "uniros_async.cli", "train", str(cfg)],
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
        start_new_session=True,  # its own process group, as a terminal's foreground job
    )
    lines: list[str] = []
    evaluated = threading.Event()

    def read() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            lines.append(line)
            if "evaluated alongside training" in line:
                evaluated.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    family: list[int] = []
    try:
        assert evaluated.wait(180.0), "".join(lines[-30:])
        family = _descendants(proc.pid)
        assert len(family) >= 3, family  # the training worker, the evaluation process and its worker at least
        if os.geteuid() == 0:  # SCHED_RR needs root or CAP_SYS_NICE (CI runs as root): the order train gave them
            children = [int(c) for c in Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split()]
            evaluation = [p for c in children for p in _descendants(c)]  # the evaluation process's workers
            training = [c for c in children if not _descendants(c)]
            assert _rr_priorities(evaluation) == {LOOP_RT_PRIORITY + 1}, "the evaluation arm's loop ranks above"
            assert _rr_priorities(training) == {LOOP_RT_PRIORITY}
        os.killpg(proc.pid, signal.SIGINT)
        code = proc.wait(120.0)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10.0)
        reader.join(10.0)
        assert proc.stderr is not None
        proc.stderr.close()
    assert code != 0 and any("interrupted at step" in line for line in lines), "".join(lines[-30:])
    deadline = time.monotonic() + 10.0
    while [p for p in family if _running(p)] and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not [p for p in family if _running(p)], "".join(lines[-30:])


AGENT_SCRIPT = """
import time
from uniros_async.training.alongside import open_alongside
alongside = open_alongside({specs!r}, real_time=False)
print("ready", alongside.process.pid, flush=True)
time.sleep(120)
"""


@pytest.mark.slow
def test_an_agent_killed_leaves_no_evaluation_process(tmp_path: Path) -> None:
    """A script with no ``if __name__ == "__main__":`` opens an evaluation process (it is not re-imported there),
    then dies by SIGKILL: the evaluation process sees the agent's end of the connection close, closes its envs and
    exits, its workers with it."""
    script = tmp_path / "agent.py"
    script.write_text(AGENT_SCRIPT.format(specs=SPECS))
    with subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True) as agent:
        try:
            assert agent.stdout is not None
            line = agent.stdout.readline()  # the script's only line, or "" if it died
            assert line.startswith("ready"), line
            family = _descendants(agent.pid)
            assert int(line.split()[1]) in family and len(family) >= 2, family  # the process and its worker
        finally:
            agent.kill()
            agent.wait(10.0)
    deadline = time.monotonic() + 30.0
    while [p for p in family if _running(p)] and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not [p for p in family if _running(p)]
