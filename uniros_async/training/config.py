"""TrainConfig: one training run (envs, TD3 / TD3+HER hyperparameters, learner, evaluation, checkpoints) from YAML.

The defaults are the UniROS paper's (TD3 with 400-300 networks, lr 3e-4, buffer 1e6, batch 256, tau 0.005,
gamma 0.99, policy delay 2, target noise 0.2 clipped at 0.5; HER with the ``future`` strategy and 4 sampled
goals). Every key is checked before anything starts: unknown keys (with the valid ones listed), impossible
values, unknown env ids and env keyword arguments all raise ConfigError::

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

import dataclasses
import re
from pathlib import Path
from typing import Any

from uniros_async.config import config_from_dict, load_yaml
from uniros_async.errors import ConfigError

__all__ = [
    "AsyncLearnerConfig",
    "CheckpointConfig",
    "EnvEntry",
    "EvalConfig",
    "HerConfig",
    "TD3Config",
    "TrainConfig",
    "config_to_dict",
    "load_train_config",
    "train_config_from_dict",
]

LEARNERS = ("sync", "async")
PLACEMENTS = ("inprocess", "workers")
REPLAY_BUFFERS = ("auto", "standard", "her")
GOAL_STRATEGIES = ("future", "final", "episode")
_NAME_RE = re.compile(r"^[A-Za-z0-9_.+-]+$")


@dataclasses.dataclass(frozen=True, kw_only=True)
class EnvEntry:
    """One env of a run.

    Attributes:
        id: a registered id, e.g. ``uniros/Rx200Reach-v0``.
        kwargs: keyword arguments of the env (``reward_type``, ``robot``, ``action_cycle_s``, ...); the run's
            ``env_defaults`` fill in what is missing.
        name: label in logs and reports (default: derived from the id and the robot).
    """

    id: str
    kwargs: dict[str, Any] = dataclasses.field(default_factory=dict)
    name: str | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.id, str) or not self.id:
            raise ConfigError(f"env id must be a non-empty string, got {self.id!r}")
        if not isinstance(self.kwargs, dict):
            raise ConfigError(f"env kwargs must be a mapping, got {type(self.kwargs).__name__}")
        if self.name is not None and not _NAME_RE.match(self.name):
            raise ConfigError(f"env name must match {_NAME_RE.pattern}, got {self.name!r}")

    def label(self, defaults: dict[str, Any] | None = None) -> str:
        """The name, or ``Rx200Reach`` / ``Rx200Reach-emulated-real`` from the id and robot."""
        if self.name:
            return self.name
        kw = {**(defaults or {}), **self.kwargs}
        base = self.id.split("/")[-1].rsplit("-v", 1)[0]
        robot = kw.get("robot", "sim")
        return base if robot == "sim" else f"{base}-{str(robot).replace('://', '-').replace(':', '-')}"


@dataclasses.dataclass(frozen=True, kw_only=True)
class TD3Config:
    """TD3 hyperparameters (SB3 names; defaults from the paper).

    Attributes:
        action_noise_std: standard deviation of the Gaussian exploration noise, in action units ([-1, 1]).
        net_arch: hidden layers of actor and critics.
        learning_starts: random-action steps before the first update.
        train_freq: env steps between updates; gradient_steps: updates each time.
    """

    learning_rate: float = 3e-4
    buffer_size: int = 1_000_000
    batch_size: int = 256
    tau: float = 0.005
    gamma: float = 0.99
    net_arch: tuple[int, ...] = (400, 300)
    policy_delay: int = 2
    target_policy_noise: float = 0.2
    target_noise_clip: float = 0.5
    learning_starts: int = 1000
    action_noise_std: float = 0.1
    train_freq: int = 1
    gradient_steps: int = 1

    def __post_init__(self) -> None:
        _positive(self, "learning_rate", "buffer_size", "batch_size", "train_freq", "policy_delay")
        if not 0 < self.tau <= 1:
            raise ConfigError(f"td3.tau must be in (0, 1], got {self.tau}")
        if not 0 < self.gamma <= 1:
            raise ConfigError(f"td3.gamma must be in (0, 1], got {self.gamma}")
        if self.batch_size > self.buffer_size:
            raise ConfigError(f"td3.batch_size={self.batch_size} > td3.buffer_size={self.buffer_size}")
        if not self.net_arch or not all(isinstance(n, int) and n > 0 for n in self.net_arch):
            raise ConfigError(f"td3.net_arch must be a non-empty list of positive ints, got {list(self.net_arch)}")
        for name in ("target_policy_noise", "target_noise_clip", "action_noise_std"):
            if getattr(self, name) < 0:
                raise ConfigError(f"td3.{name} must be >= 0, got {getattr(self, name)}")
        if self.learning_starts < 0:
            raise ConfigError(f"td3.learning_starts must be >= 0, got {self.learning_starts}")
        if self.gradient_steps < 1:
            raise ConfigError(f"td3.gradient_steps must be >= 1, got {self.gradient_steps}")


@dataclasses.dataclass(frozen=True, kw_only=True)
class HerConfig:
    """Hindsight experience replay (SB3 HerReplayBuffer)."""

    n_sampled_goal: int = 4
    goal_selection_strategy: str = "future"

    def __post_init__(self) -> None:
        if self.n_sampled_goal < 1:
            raise ConfigError(f"her.n_sampled_goal must be >= 1, got {self.n_sampled_goal}")
        if self.goal_selection_strategy not in GOAL_STRATEGIES:
            raise ConfigError(
                f"her.goal_selection_strategy must be one of {GOAL_STRATEGIES}, got {self.goal_selection_strategy!r}"
            )


@dataclasses.dataclass(frozen=True, kw_only=True)
class AsyncLearnerConfig:
    """Settings of the asynchronous learner (``learner: async``, training/async_td3.py)."""

    updates_per_step: float = 1.0
    sync_every: int = 2
    real_time_actor: bool | None = None
    """AsyncTD3's ``real_time_actor``; None: on when any training env runs on the wall clock."""
    action_l2: float = 0.0
    """AsyncTD3's ``action_l2``: the HER paper's action penalty in the actor's loss (1.0 there)."""

    def __post_init__(self) -> None:
        if not self.action_l2 >= 0:
            raise ConfigError(f"async_learner.action_l2 must be >= 0, got {self.action_l2}")
        if self.updates_per_step <= 0:
            raise ConfigError(f"async_learner.updates_per_step must be > 0, got {self.updates_per_step}")
        if self.sync_every < 1:
            raise ConfigError(f"async_learner.sync_every must be >= 1, got {self.sync_every}")


@dataclasses.dataclass(frozen=True, kw_only=True)
class EvalConfig:
    """Periodic evaluation (deterministic policy) on every training env, or on ``envs`` if given."""

    every_steps: int = 1000
    episodes: int = 20
    envs: tuple[EnvEntry, ...] = ()

    def __post_init__(self) -> None:
        if self.every_steps < 0:
            raise ConfigError(f"eval.every_steps must be >= 0 (0: never), got {self.every_steps}")
        if self.episodes < 1:
            raise ConfigError(f"eval.episodes must be >= 1, got {self.episodes}")


@dataclasses.dataclass(frozen=True, kw_only=True)
class CheckpointConfig:
    """Checkpoints: model and replay buffer every ``every_steps`` (and at the end), the last ``keep`` kept."""

    every_steps: int = 2000
    keep: int = 2
    replay_buffer: bool = True

    def __post_init__(self) -> None:
        if self.every_steps < 0:
            raise ConfigError(f"checkpoint.every_steps must be >= 0 (0: only at the end), got {self.every_steps}")
        if self.keep < 1:
            raise ConfigError(f"checkpoint.keep must be >= 1, got {self.keep}")


@dataclasses.dataclass(frozen=True, kw_only=True)
class TrainConfig:
    """One training run (see the module docstring).

    Attributes:
        name: run name; the run directory defaults to ``runs/<name>``.
        envs: one env (single task) or several (multi-task: one policy, one replay buffer, an env sampled per
            episode; observations and actions padded to the largest sizes).
        env_defaults: keyword arguments given to every env unless it sets them (default ``clock: sim``).
        placement: ``inprocess`` (envs in the agent's process: fastest with accelerated sim) or ``workers``
            (each env in a worker process through ``uniros_async.make``).
        learner: ``sync`` (SB3 TD3: collect, then update) or ``async`` (AsyncTD3: updates beside collection).
        replay_buffer: ``auto`` (HER for goal envs, plain replay otherwise), ``standard`` or ``her``.
        task_id_in_obs: append a one-hot env index to observations (multi-task only; off as in the paper).
        drop_observation: indices of the vector observation (the ``observation`` key of a goal env) to remove
            before the policy sees it (the reach goal envs' ``observation`` is already goal-free; this is for
            envs whose is not: HER's relabelled goals would contradict goal-dependent entries).
        normalize_obs: normalise observations with running mean/std statistics (SB3 ``VecNormalize``, as the HER
            paper and rl-baselines3-zoo's ``normalize: true``; for goal envs the ``observation``,
            ``achieved_goal`` and ``desired_goal`` keys), clipped to +-10 std; rewards are not normalised. The
            replay buffer keeps raw observations (normalised when sampled); the statistics are saved with every
            checkpoint, restored on resume and used, frozen, by every evaluation. Off by default.
        torch_threads: torch intra-op threads (1: envs share the machine; more stall env loops).
        run_dir: where logs and checkpoints go (default ``runs/<name>``).
    """

    name: str = "run"
    seed: int = 0
    total_steps: int = 10_000
    envs: tuple[EnvEntry, ...] = ()
    env_defaults: dict[str, Any] = dataclasses.field(default_factory=lambda: {"clock": "sim"})
    placement: str = "inprocess"
    learner: str = "sync"
    replay_buffer: str = "auto"
    task_id_in_obs: bool = False
    drop_observation: tuple[int, ...] = ()
    normalize_obs: bool = False
    td3: TD3Config = dataclasses.field(default_factory=TD3Config)
    her: HerConfig = dataclasses.field(default_factory=HerConfig)
    async_learner: AsyncLearnerConfig = dataclasses.field(default_factory=AsyncLearnerConfig)
    eval: EvalConfig = dataclasses.field(default_factory=EvalConfig)
    checkpoint: CheckpointConfig = dataclasses.field(default_factory=CheckpointConfig)
    torch_threads: int = 1
    run_dir: str | None = None
    progress_bar: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not _NAME_RE.match(self.name):
            raise ConfigError(f"name must match {_NAME_RE.pattern}, got {self.name!r}")
        if not self.envs:
            raise ConfigError("envs: at least one env is needed, e.g. envs: [{id: uniros/Rx200Reach-v0}]")
        if self.total_steps < 1:
            raise ConfigError(f"total_steps must be >= 1, got {self.total_steps}")
        if not isinstance(self.seed, int) or self.seed < 0:
            raise ConfigError(f"seed must be an int >= 0, got {self.seed!r}")
        for key, choices in (("placement", PLACEMENTS), ("learner", LEARNERS), ("replay_buffer", REPLAY_BUFFERS)):
            if getattr(self, key) not in choices:
                raise ConfigError(f"{key} must be one of {choices}, got {getattr(self, key)!r}")
        if not isinstance(self.env_defaults, dict):
            raise ConfigError(f"env_defaults must be a mapping, got {type(self.env_defaults).__name__}")
        if self.torch_threads < 1:
            raise ConfigError(f"torch_threads must be >= 1, got {self.torch_threads}")
        labels = self.labels()
        if len(set(labels)) != len(labels):
            raise ConfigError(f"env labels must be unique (give envs a name:), got {labels}")
        drop = self.drop_observation
        valid = all(isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in drop)
        if not valid or len(set(drop)) != len(drop):
            raise ConfigError(f"drop_observation must be distinct indices >= 0, got {list(drop)}")
        if not isinstance(self.normalize_obs, bool):
            raise ConfigError(f"normalize_obs must be true or false, got {self.normalize_obs!r}")
        if self.task_id_in_obs and len(self.envs) < 2:
            raise ConfigError("task_id_in_obs needs two or more envs")
        if self.async_learner.action_l2 and self.learner != "async":
            raise ConfigError(
                f"async_learner.action_l2={self.async_learner.action_l2} needs learner: async (AsyncTD3's update; "
                "SB3's TD3 has no such term)"
            )

    def labels(self) -> list[str]:
        """Label of every training env."""
        return [e.label(self.env_defaults) for e in self.envs]

    def env_specs(self) -> list[tuple[str, str, dict[str, Any]]]:
        """(label, id, kwargs with env_defaults filled in) of every training env."""
        return [(e.label(self.env_defaults), e.id, {**self.env_defaults, **e.kwargs}) for e in self.envs]

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
            ConfigError: an unknown id or keyword argument, or an invalid run-time setting, naming the env.
        """
        from uniros_async.runtime.envargs import check_env_args

        for where, specs in (("envs", self.env_specs()), ("eval.envs", self.eval_specs())):
            for i, (label, env_id, kwargs) in enumerate(specs):
                try:
                    check_env_args(env_id, kwargs)
                except ConfigError as exc:
                    raise ConfigError(f"{where}[{i}] ({label}): {exc}") from exc


def _positive(cfg: Any, *names: str) -> None:
    for name in names:
        value = getattr(cfg, name)
        if not value > 0:
            raise ConfigError(f"td3.{name} must be > 0, got {value}")


def _env_entries(data: Any, where: str) -> tuple[EnvEntry, ...]:
    if data is None:
        return ()
    if not isinstance(data, list):
        raise ConfigError(f"{where}: expected a list of envs, got {type(data).__name__}")
    out = []
    for i, item in enumerate(data):
        if isinstance(item, str):
            item = {"id": item}
        out.append(config_from_dict(EnvEntry, item, where=f"{where}[{i}]"))
    return tuple(out)


def train_config_from_dict(data: Any, *, where: str = "TrainConfig") -> TrainConfig:
    """Build a TrainConfig from a mapping (as read from YAML); env entries may be ids or ``{id, kwargs, name}``.

    Raises:
        ConfigError: unknown keys (valid ones listed), impossible values, or a malformed env list.
    """
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping, got {type(data).__name__}")
    data = dict(data)
    if "envs" in data:
        data["envs"] = _env_entries(data["envs"], f"{where}.envs")
    if isinstance(data.get("eval"), dict) and "envs" in data["eval"]:
        data["eval"] = {**data["eval"], "envs": _env_entries(data["eval"]["envs"], f"{where}.eval.envs")}
    if isinstance(data.get("td3"), dict):
        td3 = dict(data["td3"])
        for key in ("learning_rate", "tau", "gamma", "target_policy_noise", "target_noise_clip", "action_noise_std"):
            if key in td3:
                td3[key] = _number(td3[key], f"{where}.td3.{key}")
        data["td3"] = td3
    return config_from_dict(TrainConfig, data, where=where)


def _number(v: Any, where: str) -> float:
    # YAML 1.1 reads "3e-4" (no dot) as a string; accept it as the number it plainly is
    if isinstance(v, str):
        try:
            return float(v)
        except ValueError:
            raise ConfigError(f"{where}: expected a number, got {v!r}") from None
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ConfigError(f"{where}: expected a number, got {v!r}")
    return float(v)


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
    if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
        return {f.name: config_to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}
    if isinstance(cfg, tuple | list):
        return [config_to_dict(v) for v in cfg]
    if isinstance(cfg, dict):
        return {k: config_to_dict(v) for k, v in cfg.items()}
    return cfg
