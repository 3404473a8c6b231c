"""The pixel reach recipe: TD3 from the camera and the arm's state (training/pixel_drq.py), with checkpoints.

``python -m uniros_async.training.pixel_train configs/rx200_reach_pixels_drq.yaml`` trains one env made by its id
in this process (accelerated sim by the config's ``env_kwargs``) and writes ``runs/<name>/``: ``episodes.csv`` and
``eval.csv`` in ``uniros plot``'s columns, ``checkpoints/`` (networks, optimisers, replay buffer, random states)
and ``final_eval.json``. A run stops at ``total_steps``, at ``--max-minutes`` (after a checkpoint), or once an
evaluation of ``eval.final_episodes`` episodes finds ``eval.stop_success`` (checked when a periodic evaluation of
``eval.episodes`` reaches it). ``--resume`` goes on from the newest complete checkpoint: the interrupted episode is
dropped, and the logs are cut back to the checkpoint's step.

Costs that make it fit a CPU at one thread: the frame at ``image_size`` of 48x48 rendered once per action cycle
(``camera_rate_hz`` of 1.25 Hz on the sim clock), a two-layer encoder, and one update every ``update_every`` env
steps. The replay buffer keeps each frame once (the next observation is the next row), as uint8.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pydantic
import torch
from pydantic import Field

from uniros_async.config import Bool, ConfigModel, Float, Int, Str, load_config
from uniros_async.errors import ConfigError
from uniros_async.training.checkpoint import write_atomic
from uniros_async.training.pixel_drq import DrQConfig, PixelTD3
from uniros_async.training.run_state import EPISODE_FIELDS, EVAL_FIELDS, CsvLog

__all__ = [
    "POLICY_FILE",
    "PixelReplay",
    "PixelTrainConfig",
    "evaluate",
    "export_policy",
    "load_policy",
    "main",
    "train",
]

logger = logging.getLogger(__name__)

POLICY_FILE = "policy.pt"


class PixelEvalConfig(ConfigModel):
    """Periodic evaluation of the deterministic policy on a second env, on fresh episodes."""

    every_steps: Int = Field(default=5000, gt=0)
    episodes: Int = Field(default=20, ge=1)
    final_episodes: Int = Field(default=100, ge=1)
    stop_success: Float | None = Field(default=0.9, gt=0, le=1)
    """Stop once ``final_episodes`` episodes reach this success rate (unset: train to ``total_steps``)."""


class PixelTrainConfig(ConfigModel):
    """One pixel training run (see the module docstring; the agent's keys: training/pixel_drq.py)."""

    name: Str = "rx200_reach_pixels_drq"
    seed: Int = 0
    env_id: Str = "uniros/Rx200ReachPixels-v0"
    env_kwargs: dict[str, Any] = Field(default_factory=dict)
    total_steps: Int = Field(default=100_000, gt=0)
    learning_starts: Int = Field(default=1000, ge=0)
    """Uniform random actions before the first update."""
    update_every: Int = Field(default=2, ge=1)
    """Env steps per gradient update."""
    batch_size: Int = Field(default=64, gt=0)
    buffer_size: Int = Field(default=120_000, gt=0)
    """Rows of the replay buffer (a transition's row, plus one per episode for its last observation)."""
    n_step: Int = Field(default=3, ge=1)
    action_noise_std: Float = Field(default=0.1, ge=0)
    channels: Int = Field(default=16, ge=2)
    hidden: Int = Field(default=256, gt=0)
    learning_rate: Float = Field(default=3e-4, gt=0)
    gamma: Float = Field(default=0.99, gt=0, le=1)
    tau: Float = Field(default=0.01, gt=0, le=1)
    encoder_tau: Float = Field(default=0.05, gt=0, le=1)
    policy_delay: Int = Field(default=2, ge=1)
    target_noise: Float = Field(default=0.2, ge=0)
    target_noise_clip: Float = Field(default=0.5, ge=0)
    pad: Int = Field(default=1, ge=0)
    """Random shift of up to this many pixels (0: no augmentation)."""
    checkpoint_every: Int = Field(default=5000, gt=0)
    keep_replay: Bool = True
    eval: PixelEvalConfig = Field(default_factory=PixelEvalConfig)
    torch_threads: Int = Field(default=1, ge=1)

    @pydantic.model_validator(mode="after")
    def _check(self) -> PixelTrainConfig:
        if self.env_kwargs.get("obs_mode", "pixels+state") != "pixels+state":
            raise ConfigError("env_kwargs.obs_mode: the pixel recipe takes 'pixels+state'")
        return self


class PixelReplay:
    """Transitions of Dict observations (``pixels``, ``state``) in rows, each frame stored once.

    Row ``i`` holds an observation and, once the env stepped from it, the action, reward and whether that step
    terminated (``has_action``); its next observation is row ``i + 1``. An episode's last observation is a row
    without an action, and so is the newest row until the env steps from it. Full, the buffer overwrites its oldest
    rows: the row before the one overwritten is always the newest, so no kept transition loses its successor.
    """

    def __init__(self, capacity: int, image_shape: tuple[int, ...], state_dim: int, action_dim: int) -> None:
        self.capacity = capacity
        self.pixels = np.zeros((capacity, *image_shape), np.uint8)
        self.state = np.zeros((capacity, state_dim), np.float32)
        self.action = np.zeros((capacity, action_dim), np.float32)
        self.reward = np.zeros(capacity, np.float32)
        self.terminal = np.zeros(capacity, bool)
        self.has_action = np.zeros(capacity, bool)
        self.ptr = 0
        self.size = 0

    def start(self, obs: dict[str, np.ndarray]) -> None:
        """Write an episode's first observation."""
        self._write(obs)

    def add(self, action: np.ndarray, reward: float, terminated: bool, next_obs: dict[str, np.ndarray]) -> None:
        """The step from the newest row: its action, reward and termination, and the next observation."""
        last = (self.ptr - 1) % self.capacity
        self.action[last] = action
        self.reward[last] = reward
        self.terminal[last] = terminated
        self.has_action[last] = True
        self._write(next_obs)

    def _write(self, obs: dict[str, np.ndarray]) -> None:
        i = self.ptr
        self.pixels[i] = obs["pixels"]
        self.state[i] = obs["state"]
        self.has_action[i] = False
        self.terminal[i] = False
        self.ptr = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def transitions(self) -> int:
        """How many transitions can be sampled."""
        return int(self.has_action[: self.size].sum())

    def sample(self, rng: np.random.Generator, batch: int, n_step: int, gamma: float) -> dict[str, torch.Tensor]:
        """``batch`` n-step transitions: rewards summed over up to ``n_step`` steps of one episode, ``discount``
        gamma^k, or 0 where the episode terminated within them."""
        valid = np.flatnonzero(self.has_action[: self.size])
        idx = valid[rng.integers(0, len(valid), batch)]
        ret = np.zeros(batch, np.float32)
        disc = np.ones(batch, np.float32)
        alive = np.ones(batch, bool)
        nxt = (idx + 1) % self.capacity
        for k in range(n_step):
            r = (idx + k) % self.capacity
            ret += np.where(alive, disc * self.reward[r], 0.0).astype(np.float32)
            nxt = np.where(alive, (r + 1) % self.capacity, nxt)
            disc = np.where(alive, disc * gamma, disc).astype(np.float32)
            ended = alive & self.terminal[r]
            disc = np.where(ended, 0.0, disc).astype(np.float32)
            alive = alive & ~self.terminal[r] & self.has_action[(r + 1) % self.capacity]
        return {
            "pixels": torch.from_numpy(self.pixels[idx]),
            "state": torch.from_numpy(self.state[idx]),
            "action": torch.from_numpy(self.action[idx]),
            "reward": torch.from_numpy(ret[:, None]),
            "discount": torch.from_numpy(disc[:, None]),
            "next_pixels": torch.from_numpy(self.pixels[nxt]),
            "next_state": torch.from_numpy(self.state[nxt]),
        }

    def save(self, path: Path) -> None:
        """Write the buffer to ``path`` (.npz, uncompressed)."""
        np.savez(
            path,
            **{k: getattr(self, k)[: self.size] for k in ("pixels", "state", "action", "reward", "terminal")},
            has_action=self.has_action[: self.size],
            ptr=np.int64(self.ptr),
        )

    def load(self, path: Path) -> None:
        """Read what ``save`` wrote (into a buffer of at least that capacity)."""
        with np.load(path) as z:
            n = len(z["pixels"])
            if n > self.capacity:
                raise ConfigError(f"{path}: {n} rows do not fit buffer_size={self.capacity}")
            for k in ("pixels", "state", "action", "reward", "terminal", "has_action"):
                getattr(self, k)[:n] = z[k]
            self.size = n
            self.ptr = int(z["ptr"]) % self.capacity


def make_env(cfg: PixelTrainConfig) -> gym.Env[Any, Any]:
    """The config's env, made by its id."""
    return gym.make(cfg.env_id, **{"obs_mode": "pixels+state", **cfg.env_kwargs})


def agent_config(cfg: PixelTrainConfig, env: gym.Env[Any, Any]) -> DrQConfig:
    """The agent's sizes from ``env``'s spaces and its hyperparameters from ``cfg``."""
    space = env.observation_space
    assert isinstance(space, gym.spaces.Dict) and space["pixels"].shape is not None
    h, w = space["pixels"].shape[:2]
    return DrQConfig(
        image_size=(int(h), int(w)),
        state_dim=int(np.prod(space["state"].shape or (1,))),
        action_dim=int(np.prod(env.action_space.shape or (1,))),
        channels=cfg.channels,
        hidden=cfg.hidden,
        lr=cfg.learning_rate,
        gamma=cfg.gamma,
        tau=cfg.tau,
        encoder_tau=cfg.encoder_tau,
        policy_delay=cfg.policy_delay,
        target_noise=cfg.target_noise,
        target_noise_clip=cfg.target_noise_clip,
        pad=cfg.pad,
    )


def export_policy(run_dir: Path, out_dir: Path) -> Path:
    """Write the newest checkpoint's encoder and actor (what acting needs) to ``out_dir/policy.pt``.

    Raises:
        ConfigError: ``run_dir`` has no complete checkpoint.
    """
    ckpt = _newest_checkpoint(run_dir)
    if ckpt is None:
        raise ConfigError(f"{run_dir}: no complete checkpoint (checkpoints/step_N/done)")
    state = torch.load(ckpt / "agent.pt", weights_only=False)
    keep = ("encoder.", "actor.")
    weights = {k: v for k, v in state["model"].items() if k.startswith(keep)}
    cfg = json.loads((run_dir / "config.json").read_text())
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.save({"weights": weights, "config": cfg, "step": int(state["step"])}, out_dir / POLICY_FILE)
    return out_dir / POLICY_FILE


def load_policy(path: Path) -> tuple[PixelTD3, PixelTrainConfig, int]:
    """The agent of a ``policy.pt`` written by ``export_policy`` (encoder and actor loaded), its run's config and
    the step it was taken at; act with ``agent.act(pixels, state)``."""
    saved = torch.load(path, weights_only=False)
    cfg = PixelTrainConfig.from_data(saved["config"])
    env = make_env(cfg)
    try:
        agent = PixelTD3(agent_config(cfg, env))
    finally:
        env.close()
    missing = agent.load_state_dict(saved["weights"], strict=False).missing_keys
    assert not [k for k in missing if k.startswith(("encoder.", "actor."))], missing
    return agent, cfg, int(saved["step"])


def evaluate(agent: PixelTD3, env: gym.Env[Any, Any], episodes: int, seed: int) -> dict[str, float]:
    """The deterministic policy over ``episodes`` fresh episodes: success rate, mean return and length."""
    successes, returns, lengths = [], [], []
    for e in range(episodes):
        obs, _ = env.reset(seed=seed + e)
        done, ret, n = False, 0.0, 0
        info: dict[str, Any] = {}
        while not done:
            a = agent.act(obs["pixels"][None], obs["state"][None])[0]
            obs, r, term, trunc, info = env.step(a)
            ret += float(r)
            n += 1
            done = bool(term or trunc)
        successes.append(bool(info.get("is_success", False)))
        returns.append(ret)
        lengths.append(n)
    return {
        "success_rate": float(np.mean(successes)),
        "mean_return": float(np.mean(returns)),
        "mean_length": float(np.mean(lengths)),
        "episodes": float(episodes),
    }


def _newest_checkpoint(run_dir: Path) -> Path | None:
    ckpts = sorted((run_dir / "checkpoints").glob("step_*/done"), key=lambda p: int(p.parent.name[5:]))
    return ckpts[-1].parent if ckpts else None


def _save_checkpoint(run_dir: Path, step: int, agent: PixelTD3, buf: PixelReplay, state: dict[str, Any]) -> None:
    d = run_dir / "checkpoints" / f"step_{step}"
    d.mkdir(parents=True, exist_ok=True)
    torch.save({**agent.training_state(), **state, "torch_rng": torch.get_rng_state()}, d / "agent.pt")
    buf.save(d / "replay.npz")
    write_atomic(d / "done", str(step).encode())
    for old in (run_dir / "checkpoints").glob("step_*"):
        if old != d:
            shutil.rmtree(old, ignore_errors=True)


def train(
    cfg: PixelTrainConfig, run_dir: Path, *, resume: bool = False, max_minutes: float | None = None
) -> dict[str, Any]:
    """Run (or resume) the recipe; returns the final evaluation (see the module docstring)."""
    torch.set_num_threads(cfg.torch_threads)
    run_dir.mkdir(parents=True, exist_ok=True)
    env, eval_env = make_env(cfg), make_env(cfg)
    try:
        return _train(cfg, run_dir, env, eval_env, resume=resume, max_minutes=max_minutes)
    finally:
        env.close()
        eval_env.close()


def _train(
    cfg: PixelTrainConfig,
    run_dir: Path,
    env: gym.Env[Any, Any],
    eval_env: gym.Env[Any, Any],
    *,
    resume: bool,
    max_minutes: float | None,
) -> dict[str, Any]:
    agent = PixelTD3(agent_config(cfg, env))
    pix_shape = agent.cfg.image_size + (3,)
    state_dim, action_dim = agent.cfg.state_dim, agent.cfg.action_dim
    buf = PixelReplay(cfg.buffer_size, tuple(pix_shape), state_dim, action_dim)
    rng = np.random.default_rng(cfg.seed)
    torch.manual_seed(cfg.seed)
    step, episode, wall_offset = 0, 0, 0.0
    ckpt = _newest_checkpoint(run_dir) if resume else None
    if resume and ckpt is None:
        logger.info("%s: no complete checkpoint; starting afresh", run_dir)
    if ckpt is not None:
        state = torch.load(ckpt / "agent.pt", weights_only=False)
        agent.load_training_state(state)
        buf.load(ckpt / "replay.npz")
        rng.bit_generator.state = state["np_rng"]
        torch.set_rng_state(state["torch_rng"])
        step, episode, wall_offset = int(state["step"]), int(state["episode"]), float(state["wall_s"])
        logger.info("resumed from %s at step %d", ckpt, step)
    keep = step if ckpt is not None else 0
    ep_log = CsvLog(run_dir / "episodes.csv", EPISODE_FIELDS, keep_until_step=keep)
    ev_log = CsvLog(run_dir / "eval.csv", EVAL_FIELDS, keep_until_step=keep)
    (run_dir / "config.json").write_text(json.dumps(cfg.model_dump(mode="json"), indent=1))
    t0 = time.monotonic()
    deadline = None if max_minutes is None else t0 + 60 * max_minutes
    label = cfg.env_id.split("/")[-1].rsplit("-v", 1)[0]

    def wall() -> float:
        return wall_offset + time.monotonic() - t0

    def checkpoint() -> None:
        state = {"np_rng": rng.bit_generator.state, "step": step, "episode": episode, "wall_s": wall()}
        _save_checkpoint(run_dir, step, agent, buf, state)

    obs, _ = env.reset(seed=cfg.seed * 1_000_003 + episode)
    buf.start(obs)
    ep_ret, ep_len, update_s, updates = 0.0, 0, 0.0, 0
    final: dict[str, Any] | None = None
    while step < cfg.total_steps:
        if step < cfg.learning_starts:
            action = rng.uniform(-1.0, 1.0, action_dim).astype(np.float32)
        else:
            action = agent.act(obs["pixels"][None], obs["state"][None])[0]
            action = np.clip(action + rng.normal(0.0, cfg.action_noise_std, action_dim), -1, 1).astype(np.float32)
        obs, reward, term, trunc, info = env.step(action)
        step += 1
        buf.add(action, float(reward), bool(term), obs)
        ep_ret, ep_len = ep_ret + float(reward), ep_len + 1
        if term or trunc:
            episode += 1
            success = int(bool(info.get("is_success", False)))
            ep_log.write(step=step, task=label, **{"return": round(ep_ret, 4)}, length=ep_len, success=success,
                         wall_s=round(wall(), 1))  # fmt: skip
            obs, _ = env.reset(seed=cfg.seed * 1_000_003 + episode)
            buf.start(obs)
            ep_ret, ep_len = 0.0, 0
        if step >= cfg.learning_starts and step % cfg.update_every == 0 and buf.transitions() >= cfg.batch_size:
            t = time.perf_counter()
            agent.update(buf.sample(rng, cfg.batch_size, cfg.n_step, cfg.gamma))
            update_s += time.perf_counter() - t
            updates += 1
        if step % cfg.eval.every_steps == 0 or step == cfg.total_steps:
            res = evaluate(agent, eval_env, cfg.eval.episodes, 10_000_000 + step)
            ev_log.write(step=step, task=label, **res, wall_s=round(wall(), 1))
            logger.info(
                "step %d: eval %.0f %% over %d, %.1f ms per update, %.0f s",
                step, 100 * res["success_rate"], cfg.eval.episodes, 1e3 * update_s / max(updates, 1), wall(),
            )  # fmt: skip
            stop = cfg.eval.stop_success
            if stop is not None and res["success_rate"] >= stop and cfg.eval.final_episodes > cfg.eval.episodes:
                res = evaluate(agent, eval_env, cfg.eval.final_episodes, 20_000_000 + step)
                ev_log.write(step=step, task=label, **res, wall_s=round(wall(), 1))
                logger.info("step %d: eval %.0f %% over %d", step, 100 * res["success_rate"], cfg.eval.final_episodes)
            if stop is not None and res["success_rate"] >= stop:
                final = {"step": step, **res}
        if step % cfg.checkpoint_every == 0 or final is not None:
            checkpoint()
        if final is not None:
            break
        if deadline is not None and time.monotonic() > deadline:
            checkpoint()
            logger.info("stopped at --max-minutes after step %d; --resume goes on from here", step)
            ep_log.close()
            ev_log.close()
            return {"step": step, "stopped": "max_minutes"}
    if final is None:
        res = evaluate(agent, eval_env, cfg.eval.final_episodes, 30_000_000 + step)
        ev_log.write(step=step, task=label, **res, wall_s=round(wall(), 1))
        final = {"step": step, **res}
        checkpoint()
    final["ms_per_update"] = 1e3 * update_s / max(updates, 1)
    final["wall_s"] = wall()
    write_atomic(run_dir / "final_eval.json", json.dumps(final, indent=1).encode())
    ep_log.close()
    ev_log.close()
    return final


def main(argv: list[str] | None = None) -> int:
    """``python -m uniros_async.training.pixel_train CONFIG [--resume] [--max-minutes M] [--runs DIR] [--export DIR]
    [--evaluate POLICY --episodes N --seed S]``."""
    p = argparse.ArgumentParser(prog="python -m uniros_async.training.pixel_train", description=__doc__)
    p.add_argument("config")
    p.add_argument("--resume", action="store_true", help="go on from the newest complete checkpoint")
    p.add_argument("--max-minutes", type=float, default=None, help="checkpoint and stop after this long")
    p.add_argument("--runs", default="runs", help="parent directory of the run's directory")
    p.add_argument("--total-steps", type=int, default=None, help="override total_steps")
    p.add_argument("--export", metavar="DIR", help="write the newest checkpoint's policy to DIR/policy.pt and stop")
    p.add_argument("--evaluate", metavar="POLICY", help="evaluate a policy.pt (--episodes of them) and stop")
    p.add_argument("--episodes", type=int, default=100, help="episodes of --evaluate")
    p.add_argument("--seed", type=int, default=40_000_000, help="reset seed of --evaluate's first episode")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    try:
        cfg = load_config(args.config, PixelTrainConfig)
        if args.total_steps is not None:
            cfg = cfg.model_copy(update={"total_steps": args.total_steps})
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    torch.set_num_threads(cfg.torch_threads)
    if args.export:
        print(export_policy(Path(args.runs) / cfg.name, Path(args.export)))
        return 0
    if args.evaluate:
        agent, pcfg, step = load_policy(Path(args.evaluate))
        env = make_env(pcfg)
        try:
            res = evaluate(agent, env, args.episodes, args.seed)
        finally:
            env.close()
        print(json.dumps({"policy_step": step, **res}))
        return 0
    final = train(cfg, Path(args.runs) / cfg.name, resume=args.resume, max_minutes=args.max_minutes)
    print(json.dumps(final))
    return 0


if __name__ == "__main__":
    sys.exit(main())
