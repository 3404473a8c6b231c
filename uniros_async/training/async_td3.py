"""Asynchronous TD3: gradient updates on a learner thread beside data collection (the paper's Figure 9 learner).

SB3's TD3 alternates: collect ``train_freq`` steps, then run ``gradient_steps`` updates, so every update (a
sizeable share of an action cycle for 400-300 networks on one core) lands between an env step's return and the
next step call and stretches the action cycle. ``AsyncTD3`` keeps TD3's update, hyperparameters and replay, and
moves the updates to a learner thread that ``learn`` owns:

- **Actor** (the thread that calls ``learn``): SB3's step loop (callbacks, episode statistics, logging, storing
  transitions); its actions come from a policy *snapshot*, a separate copy of the actor network run under
  ``torch.no_grad``. It never waits on a gradient step: the locks it takes are held by the learner only for a
  replay-buffer sample, a snapshot reference swap, or a wake-up.
- **Learner**: ``train(1, batch_size)`` in a loop after ``learning_starts``, paced so that the updates of a ``learn``
  call never exceed ``updates_per_step`` x the transitions collected after ``learning_starts`` (it may fall behind
  when updates are slower than the env, never run ahead). Every ``sync_every`` updates it copies the actor's
  weights into a free snapshot (one the actor is not using) and swaps the reference under a lock.
- **Replay**: one lock, held by the actor while it adds a transition and by the learner while it samples a batch
  (the copy out of the buffer), never during the gradient step. HerReplayBuffer works; its goal relabelling asks
  the env for rewards on every sample, which for envs in worker processes would be a round trip racing the
  actor's step on the same connection, so ``learn`` answers it locally (``her.LocalGoalReward``).
- **GIL**: torch releases the GIL inside its kernels, but the Python between them competes with the actor and
  with any env loop or supervisor thread in this process. With ``yield_to_actor`` (the default) the learner starts
  an update only while the actor is inside ``env.step`` (waiting on the env's deadline), and only ``step_grace_s``
  after it entered, once the action has been handed to the env: an update started at once competes for the GIL
  with that hand-over (step call to the action reaching the env loop, part of the action cycle) and spreads it;
  started ``step_grace_s`` later it finds the hand-over done.
  (A lower OS priority for the learner thread made the actor's compute worse: the thread gets descheduled while
  it holds the GIL.)

The learner thread is joined in ``learn``'s ``finally``; an exception raised in it stops collection and is
raised again in the caller (with a note naming the learner); Ctrl-C stops both. ``learner_stats`` reports what the
last ``learn`` did. ``save``/``load`` are TD3's (AsyncTD3 is a TD3 subclass); ``save`` during ``learn`` (from a
callback) pauses the learner for at most one update so the file holds a consistent state.
"""

from __future__ import annotations

import collections
import contextlib
import io
import math
import os
import pathlib
import threading
import time
from collections.abc import Iterator
from typing import Any, TypeVar

import numpy as np
import torch as th
from stable_baselines3 import TD3
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule, TrainFreq, TrainFrequencyUnit
from stable_baselines3.common.utils import polyak_update, should_collect_more_steps
from stable_baselines3.her.her_replay_buffer import HerReplayBuffer
from stable_baselines3.td3.policies import Actor, TD3Policy
from torch.nn import functional as F

from uniros_async.errors import ConfigError
from uniros_async.priority import gil_switch_interval, real_time_thread

__all__ = ["AsyncTD3"]

SelfAsyncTD3 = TypeVar("SelfAsyncTD3", bound="AsyncTD3")

# how many actor-side lock waits the statistics keep (the median is over these; the maximum over all)
_WAIT_HISTORY = 100_000
# snapshots: the current one, one the actor may still be reading, and one free for the learner to fill
_N_SNAPSHOTS = 3


class _Runtime:
    """What one ``learn`` call shares between the actor and the learner thread (never saved)."""

    def __init__(self) -> None:
        self.buffer_lock = threading.Lock()  # replay add (actor) / sample (learner): held for the copy only
        self.log_lock = threading.Lock()  # logger records (learner) / dumps (actor)
        self.snap_lock = threading.Lock()  # the snapshot reference and reference counts
        self.cond = threading.Condition()  # learner wake-ups, pauses, stop
        self.update_lock = threading.Lock()  # held by the learner through one update (only ``save`` waits on it)
        self.active = False
        self.learner_ident: int | None = None
        self.reset_stats()
        self.snapshots: list[Actor] = []
        self._snapshot_of: Actor | None = None
        self._pairs: list[list[tuple[th.Tensor, th.Tensor]]] = []

    def reset_stats(self) -> None:
        self.stop = False
        self.paused = 0
        self.error: BaseException | None = None
        self.actor_in_step = False
        self.step_t0 = 0.0  # perf_counter when the actor entered the current env.step
        self.step_s_ema: float | None = None  # how long env.step takes (exponential average)
        self.stored = 0  # num_timesteps after the last stored transition
        self.start_steps = 0  # updates are owed for transitions beyond this count
        self.episodes_done = 0
        self.buffer_ready = False
        self.updates = 0
        self.update_s = 0.0
        self.swaps = 0
        self.steps_at_start = 0
        self.t_start = time.perf_counter()
        self.t_end: float | None = None
        self.waits_ns: collections.deque[int] = collections.deque(maxlen=_WAIT_HISTORY)
        self.max_wait_ns = 0
        self.current = 0
        self.refs = [0] * _N_SNAPSHOTS

    # ---- actor side

    @contextlib.contextmanager
    def timed(self, lock: threading.Lock | threading.Condition) -> Iterator[None]:
        """Hold ``lock``; record how long the actor waited for it."""
        t0 = time.perf_counter_ns()
        lock.acquire()
        dt = time.perf_counter_ns() - t0
        self.waits_ns.append(dt)
        if dt > self.max_wait_ns:
            self.max_wait_ns = dt
        try:
            yield
        finally:
            lock.release()

    @contextlib.contextmanager
    def snapshot(self) -> Iterator[Actor]:
        """The current snapshot, marked in use (the learner never overwrites it) until the block ends."""
        with self.timed(self.snap_lock):
            i = self.current
            self.refs[i] += 1
        try:
            yield self.snapshots[i]
        finally:
            with self.snap_lock:
                self.refs[i] -= 1

    # ---- learner side

    def make_snapshots(self, policy: TD3Policy) -> None:
        """Build the snapshot actors (same architecture as ``policy.actor``, eval mode, no gradients), once per
        policy object, and pair their tensors with the live actor's for copying."""
        if self._snapshot_of is not policy.actor:
            self.snapshots = []
            for _ in range(_N_SNAPSHOTS):
                snap = policy.make_actor(features_extractor=None)
                snap.set_training_mode(False)
                snap.requires_grad_(False)
                self.snapshots.append(snap)
            self._snapshot_of = policy.actor
        live = list(policy.actor.state_dict().values())
        self._pairs = [list(zip(s.state_dict().values(), live, strict=True)) for s in self.snapshots]

    def fill(self, index: int) -> None:
        with th.no_grad():
            for dst, src in self._pairs[index]:
                dst.copy_(src)

    def publish(self) -> bool:
        """Copy the live actor into a snapshot nobody reads and make it current; False if none was free."""
        with self.snap_lock:
            free = next((i for i in range(_N_SNAPSHOTS) if i != self.current and self.refs[i] == 0), None)
        if free is None:
            return False
        self.fill(free)  # outside the lock: the actor only ever takes ``current``
        with self.snap_lock:
            self.current = free
            self.swaps += 1
        return True


class AsyncTD3(TD3):
    """TD3 whose gradient updates run on a learner thread beside collection; see the module docstring.

    Takes TD3's arguments (same defaults, same meaning) plus the keyword-only ones below. ``train_freq`` sets how
    often callbacks see a rollout start and end; ``gradient_steps`` is unused (the pace is ``updates_per_step``).

    Args:
        updates_per_step: gradient updates per collected transition (per env step of each sub-env, as SB3's
            ``gradient_steps=-1``); the learner never runs ahead of ``updates_per_step`` x transitions.
        sync_every: updates between two snapshot swaps (the actor acts with weights at most this many updates
            old, plus the update in progress).
        yield_to_actor: start updates only while the actor waits inside ``env.step`` (see the module docstring);
            False lets the learner run whenever an update is owed.
        step_grace_s: with ``yield_to_actor``, how long after the actor enters ``env.step`` the learner waits before
            starting an update (at most a quarter of the recent step duration), so that handing the action to the
            env (its loop thread, or the supervisor's, in this process) does not compete with it for the GIL.
        torch_threads: ``torch.set_num_threads`` for the caller and the learner during ``learn`` (process-wide;
            one thread beside env loops: on 2 cores more stall them); None leaves torch's setting alone.
        real_time_actor: for envs on the wall clock: during ``learn`` the acting thread runs under SCHED_RR when
            permitted (``priority.real_time_thread``; the learner thread puts itself back to ordinary scheduling)
            and the process's GIL switch interval drops to ``priority.ACTOR_GIL_SWITCH_S``, so a learner
            update in progress delays the next action by at most that much. Keep False for accelerated (sim clock)
            training: there the actor computes flat out and must not starve other processes.
        action_l2: weight of the mean squared (normalised) action in the actor's loss, as in the HER paper
            (Andrychowicz et al. 2017 use 1.0): under a sparse reward the critic's gradient otherwise drives the
            actor's tanh into saturation, pinning every joint at a limit. 0 (the default) is TD3's update exactly.

    Raises:
        ConfigError: (a ValueError) an async setting out of range; the message names the value and the range.
    """

    def __init__(
        self,
        policy: str | type[TD3Policy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 1e-3,
        buffer_size: int = 1_000_000,
        learning_starts: int = 100,
        batch_size: int = 256,
        tau: float = 0.005,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        action_noise: ActionNoise | None = None,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        policy_delay: int = 2,
        target_policy_noise: float = 0.2,
        target_noise_clip: float = 0.5,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
        *,
        updates_per_step: float = 1.0,
        sync_every: int = 2,
        yield_to_actor: bool = True,
        step_grace_s: float = 0.01,
        torch_threads: int | None = 1,
        real_time_actor: bool = False,
        action_l2: float = 0.0,
    ) -> None:
        if not (isinstance(updates_per_step, int | float) and math.isfinite(updates_per_step) and updates_per_step > 0):
            raise ConfigError(f"updates_per_step must be a finite number > 0, got {updates_per_step!r}")
        if isinstance(sync_every, bool) or not isinstance(sync_every, int) or sync_every < 1:
            raise ConfigError(
                f"sync_every must be an integer >= 1 (updates between snapshot swaps), got {sync_every!r}"
            )
        if not (isinstance(step_grace_s, int | float) and 0 <= step_grace_s < math.inf):
            raise ConfigError(f"step_grace_s must be a finite number of seconds >= 0, got {step_grace_s!r}")
        if torch_threads is not None and (
            isinstance(torch_threads, bool) or not isinstance(torch_threads, int) or torch_threads < 1
        ):
            raise ConfigError(f"torch_threads must be None or an integer >= 1, got {torch_threads!r}")
        self.updates_per_step = float(updates_per_step)
        self.sync_every = sync_every
        self.yield_to_actor = bool(yield_to_actor)
        self.step_grace_s = float(step_grace_s)
        self.torch_threads = torch_threads
        if not (isinstance(action_l2, int | float) and math.isfinite(action_l2) and action_l2 >= 0):
            raise ConfigError(f"action_l2 must be a finite number >= 0, got {action_l2!r}")
        self.real_time_actor = bool(real_time_actor)
        self.action_l2 = float(action_l2)
        self._rt = _Runtime()
        super().__init__(
            policy,
            env,
            learning_rate=learning_rate,
            buffer_size=buffer_size,
            learning_starts=learning_starts,
            batch_size=batch_size,
            tau=tau,
            gamma=gamma,
            train_freq=train_freq,
            gradient_steps=gradient_steps,
            action_noise=action_noise,
            replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=replay_buffer_kwargs,
            optimize_memory_usage=optimize_memory_usage,
            n_steps=n_steps,
            policy_delay=policy_delay,
            target_policy_noise=target_policy_noise,
            target_noise_clip=target_noise_clip,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            policy_kwargs=policy_kwargs,
            verbose=verbose,
            seed=seed,
            device=device,
            _init_setup_model=_init_setup_model,
        )

    # ---- statistics

    @property
    def learner_stats(self) -> dict[str, float]:
        """What the current (or last) ``learn`` did.

        Keys: ``updates`` (gradient updates), ``env_steps`` (transitions collected), ``updates_per_env_step``
        (their ratio over the transitions after ``learning_starts``), ``updates_per_s`` (over the learn call's wall
        time), ``update_ms_mean``, ``snapshot_swaps``, ``actor_lock_waits`` (how many times the actor took a lock),
        ``actor_lock_wait_max_us`` and ``actor_lock_wait_median_us`` (how long it waited for one).
        """
        rt = self._rt
        end = rt.t_end if rt.t_end is not None else time.perf_counter()
        wall = max(end - rt.t_start, 1e-9)
        steps = rt.stored - rt.steps_at_start
        owed_steps = max(0, rt.stored - rt.start_steps)
        waits = np.fromiter(rt.waits_ns, dtype=np.int64) if rt.waits_ns else np.zeros(1, np.int64)
        return {
            "updates": float(rt.updates),
            "env_steps": float(max(0, steps)),
            "updates_per_env_step": rt.updates / owed_steps if owed_steps else 0.0,
            "updates_per_s": rt.updates / wall if rt.updates else 0.0,
            "update_ms_mean": 1e3 * rt.update_s / rt.updates if rt.updates else 0.0,
            "snapshot_swaps": float(rt.swaps),
            "actor_lock_waits": float(len(rt.waits_ns)),
            "actor_lock_wait_max_us": rt.max_wait_ns / 1e3,
            "actor_lock_wait_median_us": float(np.median(waits)) / 1e3,
        }

    # ---- learning

    def learn(
        self: SelfAsyncTD3,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "AsyncTD3",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfAsyncTD3:
        """Collect ``total_timesteps`` steps in the calling thread while the learner thread updates (as TD3.learn).

        Raises:
            RuntimeError: ``learn`` is already running on this model.
            ConfigError: HER over an env whose rewards cannot be computed in this process (see ``her.LocalGoalReward``).
            Whatever the learner raised (the same exception, with a note), after both threads have stopped.
        """
        rt = self._rt
        if rt.active:
            raise RuntimeError("AsyncTD3.learn is already running on this model (one learn at a time)")
        total_timesteps, callback = self._setup_learn(
            total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar
        )
        assert self.env is not None and self.replay_buffer is not None and isinstance(self.train_freq, TrainFreq)
        self._local_goal_rewards()
        if self.torch_threads is not None:
            th.set_num_threads(self.torch_threads)
        callback.on_training_start(locals(), globals())

        rt.reset_stats()
        rt.make_snapshots(self.policy)
        rt.fill(rt.current)
        rt.steps_at_start = rt.stored = self.num_timesteps
        rt.start_steps = max(self.learning_starts, self.num_timesteps)
        rt.buffer_ready = not isinstance(self.replay_buffer, HerReplayBuffer) or bool(
            np.any(self.replay_buffer.ep_length > 0)
        )
        self.policy.set_training_mode(True)  # the live networks belong to the learner now; the snapshots act
        rt.active = True
        learner = threading.Thread(target=self._learner_main, name="uniros-async-td3-learner", daemon=True)
        learner.start()
        try:
            with contextlib.ExitStack() as stack:
                if self.real_time_actor:
                    stack.enter_context(real_time_thread())
                    stack.enter_context(gil_switch_interval())
                self._actor_loop(total_timesteps, callback, log_interval)
        finally:
            self._stop_learner(learner)
        if rt.error is not None:
            rt.error.add_note("(raised in the AsyncTD3 learner thread)")
            raise rt.error
        callback.on_training_end()
        return self

    def _stop_learner(self, learner: threading.Thread) -> None:
        rt = self._rt
        with rt.cond:
            rt.stop = True
            rt.cond.notify_all()
        try:
            while learner.is_alive():  # in short joins, so that Ctrl-C still reaches this thread
                learner.join(0.1)
        finally:
            rt.active = False
            rt.t_end = time.perf_counter()
            self.policy.set_training_mode(False)

    def _actor_loop(self, total_timesteps: int, callback: BaseCallback, log_interval: int | None) -> None:
        """SB3's collect_rollouts, step for step, with snapshot actions, a locked buffer and learner wake-ups."""
        rt = self._rt
        env = self.env
        buffer = self.replay_buffer
        assert env is not None and buffer is not None and isinstance(self.train_freq, TrainFreq)
        n_envs = env.num_envs
        if n_envs > 1 and self.train_freq.unit != TrainFrequencyUnit.STEP:
            raise ConfigError("train_freq must be counted in steps with more than one env (as in SB3)")
        while self.num_timesteps < total_timesteps and rt.error is None:
            callback.on_rollout_start()
            num_collected_steps, num_collected_episodes = 0, 0
            while (
                should_collect_more_steps(self.train_freq, num_collected_steps, num_collected_episodes)
                and self.num_timesteps < total_timesteps
            ):
                actions, buffer_actions = self._sample_action(self.learning_starts, self.action_noise, n_envs)
                with rt.timed(rt.cond):
                    rt.step_t0 = time.perf_counter()
                    rt.actor_in_step = True
                try:
                    # SB3's VecEnv.step, in its two halves: the learner is woken only once the actions are out, so
                    # that its wake-up does not take the GIL from the actor in the middle of sending them
                    env.step_async(actions)
                    with rt.timed(rt.cond):
                        rt.cond.notify()
                    new_obs, rewards, dones, infos = env.step_wait()
                finally:
                    rt.actor_in_step = False
                step_s = time.perf_counter() - rt.step_t0
                rt.step_s_ema = step_s if rt.step_s_ema is None else 0.9 * rt.step_s_ema + 0.1 * step_s
                self.num_timesteps += n_envs
                num_collected_steps += 1
                callback.update_locals(locals())
                if not callback.on_step():
                    callback.on_rollout_end()
                    return
                self._update_info_buffer(infos, dones)
                with rt.timed(rt.buffer_lock):
                    self._store_transition(buffer, buffer_actions, new_obs, rewards, dones, infos)
                rt.episodes_done += int(np.sum(dones))
                rt.stored = self.num_timesteps
                if not self.yield_to_actor:
                    with rt.timed(rt.cond):
                        rt.cond.notify()
                self._update_current_progress_remaining(self.num_timesteps, self._total_timesteps)
                self._on_step()
                for idx, done in enumerate(dones):
                    if done:
                        num_collected_episodes += 1
                        self._episode_num += 1
                        if self.action_noise is not None:
                            kwargs = dict(indices=[idx]) if n_envs > 1 else {}
                            self.action_noise.reset(**kwargs)
                        if log_interval is not None and self._episode_num % log_interval == 0:
                            self.dump_logs()
                if rt.error is not None:
                    break
            callback.on_rollout_end()

    def _learner_wait_s(self) -> float:
        """0 if the learner may start an update now, else how long to wait before asking again (under ``cond``)."""
        rt = self._rt
        if rt.paused or (self.yield_to_actor and not rt.actor_in_step):
            return 0.05
        if rt.updates >= math.floor(self.updates_per_step * (rt.stored - rt.start_steps) + 1e-9):
            return 0.05
        if not rt.buffer_ready:  # HER samples only from complete episodes
            rt.buffer_ready = rt.episodes_done > 0
            if not rt.buffer_ready:
                return 0.05
        if self.yield_to_actor and self.step_grace_s > 0:
            grace = self.step_grace_s if rt.step_s_ema is None else min(self.step_grace_s, 0.25 * rt.step_s_ema)
            left = rt.step_t0 + grace - time.perf_counter()
            if left > 0:
                return left
        return 0.0

    def _learner_main(self) -> None:
        rt = self._rt
        rt.learner_ident = threading.get_ident()
        _ordinary_scheduling()  # an actor thread may run real-time (SCHED_RR); its learner, computing flat out, not
        try:
            if self.torch_threads is not None:
                th.set_num_threads(self.torch_threads)
            while True:
                with rt.cond:
                    while not rt.stop and (wait_s := self._learner_wait_s()) > 0:
                        rt.cond.wait(wait_s)
                    if rt.stop:
                        return
                with rt.update_lock:
                    t0 = time.perf_counter()
                    self.train(gradient_steps=1, batch_size=self.batch_size)
                    rt.update_s += time.perf_counter() - t0
                    rt.updates += 1
                    if rt.updates % self.sync_every == 0:
                        rt.publish()
        except BaseException as exc:  # noqa: BLE001 - handed to the caller, raised there
            rt.error = exc

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        """TD3's update, line for line, except that the batch is sampled under the replay lock and logger records
        are taken under the log lock (so the actor may add transitions and dump logs meanwhile), and the optional
        ``action_l2`` term of the actor's loss."""
        rt = self._rt
        self.policy.set_training_mode(True)
        with rt.log_lock:
            self._update_learning_rate([self.actor.optimizer, self.critic.optimizer])

        actor_losses, critic_losses = [], []
        for _ in range(gradient_steps):
            self._n_updates += 1
            with rt.buffer_lock:
                replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
            discounts = replay_data.discounts if replay_data.discounts is not None else self.gamma

            with th.no_grad():
                noise = replay_data.actions.clone().data.normal_(0, self.target_policy_noise)
                noise = noise.clamp(-self.target_noise_clip, self.target_noise_clip)
                next_actions = (self.actor_target(replay_data.next_observations) + noise).clamp(-1, 1)
                next_q_values = th.cat(self.critic_target(replay_data.next_observations, next_actions), dim=1)
                next_q_values, _ = th.min(next_q_values, dim=1, keepdim=True)
                target_q_values = replay_data.rewards + (1 - replay_data.dones) * discounts * next_q_values

            current_q_values = self.critic(replay_data.observations, replay_data.actions)
            critic_loss = sum(F.mse_loss(current_q, target_q_values) for current_q in current_q_values)
            assert isinstance(critic_loss, th.Tensor)
            critic_losses.append(critic_loss.item())
            self.critic.optimizer.zero_grad()
            critic_loss.backward()  # type: ignore[no-untyped-call]
            self.critic.optimizer.step()

            if self._n_updates % self.policy_delay == 0:
                obs = replay_data.observations
                actions = self.actor(obs)
                actor_loss = -self.critic.q1_forward(obs, actions).mean()
                if self.action_l2:  # HER's action penalty (Andrychowicz et al. 2017): keeps tanh out of saturation
                    actor_loss = actor_loss + self.action_l2 * actions.pow(2).mean()
                actor_losses.append(actor_loss.item())
                self.actor.optimizer.zero_grad()
                actor_loss.backward()  # type: ignore[no-untyped-call]
                self.actor.optimizer.step()
                polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
                polyak_update(self.actor.parameters(), self.actor_target.parameters(), self.tau)
                polyak_update(self.critic_batch_norm_stats, self.critic_batch_norm_stats_target, 1.0)
                polyak_update(self.actor_batch_norm_stats, self.actor_batch_norm_stats_target, 1.0)

        with rt.log_lock:
            self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
            if len(actor_losses) > 0:
                self.logger.record("train/actor_loss", np.mean(actor_losses))
            self.logger.record("train/critic_loss", np.mean(critic_losses))

    def dump_logs(self) -> None:
        """SB3's dump_logs under the log lock (the learner records meanwhile)."""
        with self._rt.log_lock:
            super().dump_logs()

    # ---- acting

    def _snapshot_actions(self, observation: np.ndarray | dict[str, np.ndarray]) -> tuple[np.ndarray, bool]:
        """The snapshot actor's output in [-1, 1] (batch first) and whether the observation was vectorised."""
        obs_tensor, vectorized = self.policy.obs_to_tensor(observation)
        with self._rt.snapshot() as snap, th.no_grad():
            actions = snap(obs_tensor)
        return actions.cpu().numpy().reshape((-1, *self.action_space.shape)), vectorized  # type: ignore[misc]

    def _sample_action(
        self, learning_starts: int, action_noise: ActionNoise | None = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """SB3's exploration (random before ``learning_starts``, then policy + noise), the policy being the
        snapshot while ``learn`` runs."""
        if not self._rt.active or self.num_timesteps < learning_starts:
            return super()._sample_action(learning_starts, action_noise, n_envs)
        assert self._last_obs is not None, "self._last_obs was not set"
        scaled_action, _ = self._snapshot_actions(self._last_obs)
        if action_noise is not None:
            scaled_action = np.clip(scaled_action + action_noise(), -1, 1)
        return self.policy.unscale_action(scaled_action), scaled_action

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """TD3's predict; while ``learn`` runs (e.g. an evaluation callback) it reads the snapshot, not the
        networks the learner is updating."""
        if not self._rt.active:
            return super().predict(observation, state, episode_start, deterministic)
        scaled, vectorized = self._snapshot_actions(observation)
        actions = self.policy.unscale_action(scaled)
        if not vectorized:
            actions = actions.squeeze(axis=0)
        return actions, state

    # ---- HER, saving

    def _local_goal_rewards(self) -> None:
        """With HER over an env whose ``compute_reward`` would cross to a worker (``her.computes_reward_locally``),
        relabel with ``her.LocalGoalReward`` (the reach reward; it raises ConfigError for an env without the reach
        settings: wrap such an env yourself with its own ``reward_fn``)."""
        buffer = self.replay_buffer
        if isinstance(buffer, HerReplayBuffer) and buffer.env is not None:
            from uniros_async.training.her import LocalGoalReward, computes_reward_locally

            if not computes_reward_locally(buffer.env):
                buffer.env = LocalGoalReward(buffer.env)

    @contextlib.contextmanager
    def learner_paused(self) -> Iterator[None]:
        """Hold the learner between updates for the block (waits for the update in progress, at most one); a no-op
        when ``learn`` is not running or when called from the learner itself."""
        rt = self._rt
        if not rt.active or threading.get_ident() == rt.learner_ident:
            yield
            return
        with rt.cond:
            rt.paused += 1
        try:
            with rt.update_lock:
                yield
        finally:
            with rt.cond:
                rt.paused -= 1
                rt.cond.notify_all()

    def save(
        self,
        path: str | pathlib.Path | io.BufferedIOBase,
        exclude: Any = None,
        include: Any = None,
    ) -> None:
        """TD3's save; during ``learn`` the learner is paused for the write (``learner_paused``)."""
        with self.learner_paused():
            super().save(path, exclude=exclude, include=include)

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "_rt"]


def _ordinary_scheduling() -> None:
    """Put the calling thread in the ordinary scheduling class (threads inherit their creator's: an actor thread
    that asked for SCHED_RR, as real-time agents do, must not hand it to a learner that never sleeps)."""
    if hasattr(os, "sched_getscheduler") and os.sched_getscheduler(0) != os.SCHED_OTHER:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
