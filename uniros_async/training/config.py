"""TrainConfig: one training run (envs, TD3 / TD3+HER hyperparameters, learner, evaluation, checkpoints) from YAML.

The defaults are the UniROS paper's (TD3 with 400-300 networks, lr 3e-4, buffer 1e6, batch 256, tau 0.005,
gamma 0.99, policy delay 2, target noise 0.2 clipped at 0.5; HER with the ``future`` strategy and 4 sampled
goals). Every key is checked before anything starts (pydantic models, uniros_async/config.py): an unknown key
(with the closest valid one), a wrong type or an impossible value raises ConfigError with one line per problem,
each naming the key's path (``td3.batch_size: expected an integer, got 128.5``); ``check_envs`` checks the env
ids and keyword arguments the same way (``envs[1].kwargs.reward_type: ...``). Every key, its type and default:
docs/configuration.md. ::

    name: rx200_reach_dense
    seed: 0
    total_steps: 10000
    envs:
      - {id: uniros/Rx200Reach-v0, kwargs: {reward_type: dense}}
    td3: {learning_starts: 1000, action_noise_std: 0.1}
    eval: {every_steps: 1000, episodes: 20}
    normalize_obs: false   # true: running mean/std of observations (SB3 VecNormalize), rewards untouched
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

import pydantic
from pydantic import BeforeValidator, Field

from uniros_async.config import (
    Bool,
    ConfigModel,
    Float,
    Int,
    Str,
    key_error,
    load_yaml,
    problems_error,
)
from uniros_async.errors import ConfigError

__all__ = [
    "AsyncLearnerConfig",
    "CheckpointConfig",
    "EnvEntry",
    "EvalConfig",
    "HerConfig",
    "RecordConfig",
    "TD3Config",
    "TrainConfig",
    "config_to_dict",
    "load_train_config",
    "train_config_from_dict",
]

LEARNERS = ("sync", "async")
PLACEMENTS = ("inprocess", "workers", "ray")
REPLAY_BUFFERS = ("auto", "standard", "her")
GOAL_STRATEGIES = ("future", "final", "episode")
_NAME_PATTERN = r"^[A-Za-z0-9_.+-]+$"

Name = Annotated[Str, Field(pattern=_NAME_PATTERN)]
"""A run or env name: letters, digits and ``_ . + -`` (it becomes part of file names)."""


class EnvEntry(ConfigModel):
    """One env of a run (in YAML: a mapping, or just the id)."""

    id: Annotated[Str, Field(min_length=1)]
    """A registered id, e.g. ``uniros/Rx200Reach-v0``."""
    kwargs: dict[str, Any] = Field(default_factory=dict)
    """Keyword arguments of the env (``reward_type``, ``robot``, ``action_cycle_s``, ...; docs/configuration.md);
    the run's ``env_defaults`` fill in what is missing."""
    name: Name | None = None
    """Label in logs and reports (default: derived from the id and the robot)."""

    def label(self, defaults: dict[str, Any] | None = None) -> str:
        """The name, or ``Rx200Reach`` / ``Rx200Reach-emulated-real`` from the id and robot."""
        if self.name:
            return self.name
        kw = {**(defaults or {}), **self.kwargs}
        base = self.id.split("/")[-1].rsplit("-v", 1)[0]
        robot = kw.get("robot", "sim")
        return base if robot == "sim" else f"{base}-{str(robot).replace('://', '-').replace(':', '-')}"


def _env_list(v: Any) -> Any:
    """``envs`` as YAML gives it: None, or a list of ids and mappings."""
    if v is None:
        return ()
    if not isinstance(v, list | tuple):
        raise ConfigError(f"expected a list of envs (ids or {{id, kwargs, name}} mappings), got {v!r}")
    return [{"id": item} if isinstance(item, str) else item for item in v]


EnvList = Annotated[tuple[EnvEntry, ...], BeforeValidator(_env_list)]
PositiveInt = Annotated[Int, Field(gt=0)]
Index = Annotated[Int, Field(ge=0)]


class TD3Config(ConfigModel):
    """TD3 hyperparameters (SB3 names; defaults from the paper)."""

    learning_rate: Float = Field(default=3e-4, gt=0)
    """Adam's learning rate of actor and critics."""
    buffer_size: Int = Field(default=1_000_000, gt=0)
    """Replay buffer capacity (transitions)."""
    batch_size: Int = Field(default=256, gt=0)
    """Transitions per gradient step."""
    tau: Float = Field(default=0.005, gt=0, le=1)
    """Polyak coefficient of the target networks."""
    gamma: Float = Field(default=0.99, gt=0, le=1)
    """Discount factor."""
    net_arch: Annotated[tuple[PositiveInt, ...], Field(min_length=1)] = (400, 300)
    """Hidden layers of actor and critics."""
    policy_delay: Int = Field(default=2, gt=0)
    """Critic updates per actor update."""
    target_policy_noise: Float = Field(default=0.2, ge=0)
    """Standard deviation of the target policy smoothing noise."""
    target_noise_clip: Float = Field(default=0.5, ge=0)
    """The smoothing noise is clipped to +- this."""
    learning_starts: Int = Field(default=1000, ge=0)
    """Random-action steps before the first update."""
    action_noise_std: Float = Field(default=0.1, ge=0)
    """Standard deviation of the Gaussian exploration noise, in action units ([-1, 1])."""
    train_freq: Int = Field(default=1, gt=0)
    """Env steps between updates."""
    gradient_steps: Int = Field(default=1, ge=1)
    """Updates each time."""

    @pydantic.model_validator(mode="after")
    def _check(self) -> TD3Config:
        if self.batch_size > self.buffer_size:
            raise key_error("batch_size", f"must be <= buffer_size ({self.buffer_size}), got {self.batch_size}")
        return self


class HerConfig(ConfigModel):
    """Hindsight experience replay (SB3 HerReplayBuffer)."""

    n_sampled_goal: Int = Field(default=4, ge=1)
    """Relabelled goals per real transition."""
    goal_selection_strategy: Literal["future", "final", "episode"] = "future"
    """Where relabelled goals come from."""


class AsyncLearnerConfig(ConfigModel):
    """Settings of the asynchronous learner (``learner: async``, training/async_td3.py)."""

    updates_per_step: Float = Field(default=1.0, gt=0)
    """Gradient updates per collected transition; the learner never runs ahead of this x transitions."""
    sync_every: Int = Field(default=2, ge=1)
    """Updates between two swaps of the actor's weights the acting side uses."""
    real_time_actor: Bool | None = None
    """AsyncTD3's ``real_time_actor``; unset: on when any training env runs on the wall clock."""
    action_l2: Float = Field(default=0.0, ge=0)
    """AsyncTD3's ``action_l2``: the HER paper's action penalty in the actor's loss (1.0 there)."""


class EvalConfig(ConfigModel):
    """Periodic evaluation (deterministic policy) on every training env, or on ``envs`` if given; the evaluation at
    the end of the run takes ``final_episodes`` episodes per env."""

    every_steps: Int = Field(default=1000, ge=0)
    """Env steps between evaluations (0: never)."""
    episodes: Int = Field(default=20, ge=1)
    """Episodes per env and evaluation."""
    final_episodes: Int | None = Field(default=None, ge=1)
    """Episodes per env of the evaluation at the end of the run; unset: ``episodes``."""
    stop_success: Float | None = Field(default=None, gt=0, le=1)
    """Stop training once a periodic evaluation finds every env at this success rate or above (then evaluate and
    save as at ``total_steps``): train until each env reaches its target; unset: train to ``total_steps`` or
    ``max_wall_s``."""
    envs: EnvList = ()
    """Evaluation envs (as ``envs``); empty: the training envs."""
    alongside: Bool = False
    """(``concurrent`` runs) Evaluate on a second set of the training envs (an emulated real arm gets its own arm)
    in an evaluation process of its own, their workers its children, so that training never pauses for an
    evaluation and no learner update delays an evaluation arm's action (docs/performance.md, "The agent process in
    real time"). Each periodic evaluation acts with the policy's weights and observation statistics as they were at
    its step, sent to the process, in the real-time class when the training envs run on the wall clock; its rows are
    written when it ends (one falling due while another runs starts when that one ends). The final evaluation runs
    there too. The process closes with the run, also on Ctrl-C or SIGTERM."""
    alongside_rank: Literal["training", "evaluation"] = "training"
    """(``alongside``) Which set of arms' env loops ranks higher in the real-time class: ``training``, the arms
    whose steps the policy learns from, or ``evaluation``, the arms of the evaluation process. The set ranked higher
    holds its action cycle closer to its period when the loops of both sets fall due on the same instants
    (docs/performance.md, "The agent process in real time", has both orders measured)."""
    alongside_phase: Float = Field(default=0.5, ge=0, lt=1)
    """(``alongside``, wall clock) The evaluation arms' ``action_cycle_phase``: how far, as a fraction of the action
    cycle, their steps fall after the training arms' (whole env-loop periods), so that the two sets' steps, and the
    policy's actions for them, do not fall due on the same instants. 0: the same instants."""


class CheckpointConfig(ConfigModel):
    """Checkpoints: model and replay buffer every ``every_steps`` (and at the end), the last ``keep`` kept."""

    every_steps: Int = Field(default=2000, ge=0)
    """Env steps between checkpoints (0: only at the end)."""
    keep: Int = Field(default=2, ge=1)
    """Checkpoints kept."""
    replay_buffer: Bool = True
    """Save the replay buffer too (needed to resume exactly)."""


class DelayAwareConfig(ConfigModel):
    """The last actions and the observation's age in every env's observation (``envs.delay_aware``)."""

    action_history: Int = Field(default=1, ge=0)
    """How many past actions the observation carries, newest first (zeros after a reset)."""
    observation_age: Bool = True
    """Append how old the observation is, in seconds (the env loop's own measure)."""


class RecordConfig(ConfigModel):
    """Every step of the training envs written to MCAP bags while training (``bag.episodes.RecordEpisodes``:
    observation, action, reward, goal, success, the env loop's joint states, commands and timings, camera
    frames)."""

    path: Str | None = None
    """The bag; unset: ``<run_dir>/episodes.mcap``. With ``episodes_per_file``, the stem of the numbered files."""
    episodes_per_file: Int | None = Field(default=None, ge=1)
    """A new file every this many episodes; unset: one file per run."""
    compression: Literal["zstd", "lz4"] = "zstd"
    """The chunks' compression."""


class TrainConfig(ConfigModel):
    """One training run (see the module docstring)."""

    name: Name = "run"
    """Run name; the run directory defaults to ``runs/<name>``."""
    seed: Int = Field(default=0, ge=0)
    """Seed of the envs, the networks and the exploration noise."""
    total_steps: Int = Field(default=10_000, ge=1)
    """Env steps of the run."""
    envs: EnvList = ()
    """One env (single task) or several (multi-task: one policy, one replay buffer, an env sampled per episode;
    observations and actions padded to the largest sizes). Each is an id or ``{id, kwargs, name}``."""
    env_defaults: dict[str, Any] = Field(default_factory=lambda: {"clock": "sim"})
    """Keyword arguments given to every env unless it sets them."""
    randomize: dict[str, tuple[float, float]] | None = None
    """Domain randomization: a range [low, high] of strengths per imperfection knob
    (``uniros_async.sim.imperfections``), drawn afresh at every reset of each training env's sim (the sim
    placements, either clock, in the agent's process or in workers) from the env's reset seed and its
    ``emulation_seed``, the draw in the reset's ``info["imperfections"]``; given to every training env that does not
    set ``randomize`` itself."""
    placement: Literal["inprocess", "workers", "ray"] = "inprocess"
    """``inprocess`` (envs in the agent's process: fastest with accelerated sim), ``workers`` (each env in a
    worker process through ``uniros_async.make``) or ``ray`` (each env's worker placed by Ray on a node of the
    connected cluster, ``make(..., backend="ray")``; an env's ``kwargs: {worker: {ray: {resources: {rx200_arm:
    1}}}}`` pins it, docs/howto/cluster.md)."""
    learner: Literal["sync", "async"] = "sync"
    """``sync`` (SB3 TD3: collect, then update) or ``async`` (AsyncTD3: updates beside collection)."""
    concurrent: Bool = False
    """Every env acts in every step (training/concurrent.py): the envs run as one vector env over worker processes
    (needs ``placement: workers``), each step gives every env an action, all their transitions go to the one
    replay buffer, and the evaluation steps them all at once; for real-time (``clock: wall``) envs, where sampling
    one env per episode leaves the other arms idle. Off: one env sampled per episode (the paper's Algorithm 1)."""
    replay_buffer: Literal["auto", "standard", "her"] = "auto"
    """``auto`` (HER for goal envs, plain replay otherwise), ``standard`` or ``her``."""
    task_id_in_obs: Bool = False
    """Append a one-hot env index to observations (multi-task only, concurrent runs included; off as in the paper)."""
    drop_observation: tuple[Index, ...] = ()
    """Indices of the vector observation (the ``observation`` key of a goal env) to remove before the policy sees
    it (the reach goal envs' ``observation`` is already goal-free; this is for envs whose is not: HER's relabelled
    goals would contradict goal-dependent entries)."""
    normalize_obs: Bool = False
    """Normalise observations with running mean/std statistics (SB3 ``VecNormalize``, as the HER paper and
    rl-baselines3-zoo's ``normalize: true``; for goal envs the ``observation``, ``achieved_goal`` and
    ``desired_goal`` keys), clipped to +-10 std; rewards are not normalised. The replay buffer keeps raw
    observations (normalised when sampled); the statistics are saved with every checkpoint, restored on resume and
    used, frozen, by every evaluation."""
    td3: TD3Config = TD3Config()
    """TD3 hyperparameters."""
    her: HerConfig = HerConfig()
    """HER settings (goal envs)."""
    async_learner: AsyncLearnerConfig = AsyncLearnerConfig()
    """Settings of ``learner: async``."""
    eval: EvalConfig = EvalConfig()
    """Periodic evaluation."""
    checkpoint: CheckpointConfig = CheckpointConfig()
    """Checkpoints."""
    max_wall_s: Float | None = Field(default=None, gt=0)
    """Stop training after this many seconds of wall time (then evaluate and save as at ``total_steps``): the
    budget of a real-time run, whose steps per hour depend on the learner; unset: no limit."""
    torch_threads: Int = Field(default=1, ge=1)
    """Torch intra-op threads (1: envs share the machine, and more threads stall updates beside real-time loops)."""
    run_dir: Str | None = None
    """Where logs and checkpoints go; unset: ``runs/<name>``."""
    progress_bar: Bool = True
    """Show a progress bar of the run's steps (``uniros train --no-progress`` turns it off)."""
    record: RecordConfig | None = None
    """Record the training envs' steps to MCAP (not with ``concurrent``); unset: nothing is recorded."""
    delay_aware: DelayAwareConfig | None = None
    """Delay-aware observations (``envs.delay_aware.DelayAwareObservation``, an action buffer as rtgym's for
    delayed MDPs) on every training and evaluation env, e.g. ``{action_history: 2}``; not with ``concurrent``, and
    ``observation_age`` only with ``placement: inprocess`` (it reads the env's own timing). Unset: observations as
    the env gives them."""

    @pydantic.model_validator(mode="after")
    def _check(self) -> TrainConfig:
        """The checks that span keys."""
        if not self.envs:
            raise key_error("envs", "at least one env is needed, e.g. envs: [{id: uniros/Rx200Reach-v0}]")
        labels = self.labels()
        if len(set(labels)) != len(labels):
            raise key_error("envs", f"env labels must be unique (give envs a name:), got {labels}")
        drop = self.drop_observation
        if len(set(drop)) != len(drop):
            raise key_error("drop_observation", f"must be distinct indices, got {list(drop)}")
        if self.task_id_in_obs and len(self.envs) < 2:
            raise key_error("task_id_in_obs", "needs two or more envs")
        if self.concurrent:
            if self.placement != "workers":
                raise key_error(
                    "concurrent",
                    "steps the envs as one vector env over worker processes: it needs placement: workers, got "
                    f"placement: {self.placement}",
                )
            if self.drop_observation:
                raise key_error("concurrent", "does not support drop_observation (the envs are padded alike)")
            if self.eval.envs:
                raise key_error("concurrent", "evaluates on the training envs; remove eval.envs")
            if self.record is not None:
                raise key_error("record", "records one env's steps, and a concurrent run steps a vector env")
            if self.delay_aware is not None:
                raise key_error("delay_aware", "wraps each env of a run, and a concurrent run steps a vector env")
        elif self.eval.alongside:
            raise key_error(
                "eval.alongside", "evaluates on a second vector env of the training envs: it needs concurrent: true"
            )
        if self.delay_aware is not None and self.delay_aware.observation_age and self.placement != "inprocess":
            raise key_error(
                "delay_aware.observation_age",
                f"reads the env's own timing, which a worker process keeps: it needs placement: inprocess, got "
                f"placement: {self.placement} (or set observation_age: false)",
            )
        delay = self.delay_aware
        if delay is not None and not delay.action_history and not delay.observation_age:
            raise key_error("delay_aware", "adds nothing: set action_history >= 1 or observation_age: true")
        if self.async_learner.action_l2 and self.learner != "async":
            raise ConfigError(
                f"async_learner.action_l2={self.async_learner.action_l2} needs learner: async (AsyncTD3's update; "
                "SB3's TD3 has no such term)"
            )
        return self

    def delay_aware_args(self) -> tuple[int, bool] | None:
        """``(action_history, observation_age)`` of ``delay_aware``, or None."""
        d = self.delay_aware
        return None if d is None else (d.action_history, d.observation_age)

    def labels(self) -> list[str]:
        """Label of every training env."""
        return [e.label(self.env_defaults) for e in self.envs]

    def env_specs(self) -> list[tuple[str, str, dict[str, Any]]]:
        """(label, id, kwargs with env_defaults filled in) of every training env."""
        extra = {} if self.randomize is None else {"randomize": self.randomize}
        return [(e.label(self.env_defaults), e.id, {**self.env_defaults, **extra, **e.kwargs}) for e in self.envs]

    def eval_specs(self) -> list[tuple[str, str, dict[str, Any]]]:
        """(label, id, kwargs) of every evaluation env (the training envs unless ``eval.envs`` is set)."""
        if not self.eval.envs:
            return self.env_specs()
        return [(e.label(self.env_defaults), e.id, {**self.env_defaults, **e.kwargs}) for e in self.eval.envs]

    def resolved_run_dir(self) -> Path:
        """``run_dir`` or ``runs/<name>``."""
        return Path(self.run_dir) if self.run_dir else Path("runs") / self.name

    def check_envs(self) -> None:
        """Check every env id and keyword argument (imports the task modules, starts nothing).

        Raises:
            ConfigError: one line per problem, each with its path in the config (``envs[1].kwargs.reward_type``,
                or ``env_defaults.clock`` for a value that comes from ``env_defaults``): an unknown id or keyword
                argument, or a bad value.
        """
        from uniros_async.runtime.envargs import check_env_args

        problems: list[tuple[str, str]] = []
        for where, entries in (("envs", self.envs), ("eval.envs", self.eval.envs)):
            for i, e in enumerate(entries):
                try:
                    check_env_args(e.id, {**self.env_defaults, **e.kwargs})
                except ConfigError as exc:
                    problems += _env_problems(exc, f"{where}[{i}]", e, self.env_defaults)
        if problems:  # a bad env_defaults value is wrong for every env: said once
            raise problems_error(list(dict.fromkeys(problems)))


def _env_problems(exc: ConfigError, where: str, entry: EnvEntry, defaults: dict[str, Any]) -> list[tuple[str, str]]:
    """The problems of one env's check, with paths in the config: a key the entry sets is under its ``kwargs``,
    one it takes from ``env_defaults`` under that."""
    found: list[tuple[str, str]] | None = getattr(exc, "problems", None)
    if not found:
        return [(where, str(exc))]
    out = []
    for path, message in found:
        key = path.split(".")[0].split("[")[0]
        if key and key not in entry.kwargs and key in defaults:
            out.append((f"env_defaults.{path}", message))
        else:
            out.append((f"{where}.kwargs.{path}" if path else where, message))
    return out


def train_config_from_dict(data: Any, *, where: str = "") -> TrainConfig:
    """Build a TrainConfig from a mapping (as read from YAML); env entries may be ids or ``{id, kwargs, name}``.

    Raises:
        ConfigError: one line per problem (the key's path, what was expected, what was given), after ``where``.
    """
    return TrainConfig.from_data(data, where=where)


def load_train_config(path: str | Path, overrides: dict[str, Any] | None = None) -> TrainConfig:
    """Load a TrainConfig from YAML, with ``overrides`` (dotted keys, e.g. ``{"td3.batch_size": 128}``) applied.

    Raises:
        ConfigError: an unreadable file, bad YAML, unknown keys or impossible values (naming the file).
    """
    data = load_yaml(path) if path is not None else {}
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{str(path)!r}: expected a mapping at the top level, got {type(data).__name__}")
    return train_config_from_dict(apply_overrides(data, overrides or {}), where=str(path))


def apply_overrides(data: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """A copy of ``data`` with dotted keys set (``"eval.episodes": 50`` sets ``data["eval"]["episodes"]``)."""
    import copy

    out = copy.deepcopy(data)
    for dotted, value in overrides.items():
        parts = dotted.split(".")
        node = out
        for p in parts[:-1]:
            nxt = node.get(p)
            if nxt is None:
                nxt = node[p] = {}
            if not isinstance(nxt, dict):
                raise ConfigError(f"override {dotted!r}: {p!r} is not a mapping")
            node = nxt
        node[parts[-1]] = value
    return out


def config_to_dict(cfg: Any) -> Any:
    """Plain data (dicts, lists, scalars) of a config, for YAML and checkpoint metadata."""
    if isinstance(cfg, ConfigModel):
        return cfg.to_data()
    if isinstance(cfg, tuple | list):
        return [config_to_dict(v) for v in cfg]
    if isinstance(cfg, dict):
        return {k: config_to_dict(v) for k, v in cfg.items()}
    return cfg
