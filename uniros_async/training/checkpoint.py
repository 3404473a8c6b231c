"""Checkpoints of a run: the model, its replay buffer and what is needed to check and resume them, written atomically.

Layout (under ``<run_dir>/checkpoints``)::

    step_000010000/model.zip           SB3 zip (policy, optimisers, counters, action noise)
    step_000010000/replay_buffer.pkl   the filled part of the replay buffer only (not 1e6 empty rows)
    step_000010000/meta.json           step, sizes, padding, learner, replay kind, the run's config
    step_000010000/vec_normalize.pkl   with ``normalize_obs``: the observation statistics (SB3 ``VecNormalize.save``)
    latest                             the name of the newest complete checkpoint

A checkpoint is written into a hidden temporary directory in the same directory (``.tmp-step_...``), every file
flushed and fsynced, the directory fsynced, then renamed into place (``os.replace``: atomic within one file system)
and the parent directory fsynced; ``latest`` is then replaced the same way (``write_atomic``: a temporary file
beside it, flush + fsync, ``os.replace``, fsync of the directory). An interruption at any point, SIGKILL and power
loss included, leaves the previous checkpoint and ``latest`` intact: a reader finds either the old or the new one,
never a part. Old checkpoints beyond ``keep`` are removed only after ``latest`` names the new one. What an
interrupted write leaves behind (``.tmp-*``, ``.old-*``) is removed or, for an ``.old-`` checkpoint whose
replacement never landed, put back by ``clean_partial`` when the run resumes.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import pickle
import shutil
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from uniros_async.errors import CheckpointError, ConfigError

__all__ = [
    "CheckpointError",
    "CheckpointMeta",
    "check_obs_stats",
    "check_sizes",
    "find_checkpoint",
    "latest_checkpoint",
    "load_obs_stats",
    "load_replay_buffer",
    "read_meta",
    "save_checkpoint",
    "write_atomic",
]

logger = logging.getLogger(__name__)

MODEL_FILE = "model.zip"
BUFFER_FILE = "replay_buffer.pkl"
META_FILE = "meta.json"
OBS_STATS_FILE = "vec_normalize.pkl"
LATEST_FILE = "latest"


@dataclasses.dataclass(frozen=True, kw_only=True)
class CheckpointMeta:
    """What a checkpoint holds besides the SB3 files.

    Attributes:
        step: env steps taken when it was written.
        obs_size, action_size: the policy's observation (the ``observation`` key's, for goal envs) and action sizes.
        goal_env: dict observations (HER).
        pad_to: sizes every env was padded to (multi-task), or None.
        task_id_size: length of the one-hot task index appended to observations (0: none).
        algo: ``TD3`` or ``AsyncTD3`` (the class to load with).
        labels: the training envs' labels.
        drop_observation: observation entries removed before the policy (``DropObservation``).
        normalize_obs: the policy takes observations normalised with the statistics in ``vec_normalize.pkl``
            (set by ``save_checkpoint`` from the model's VecNormalize).
        config: the run's TrainConfig as plain data.
    """

    step: int
    obs_size: int
    action_size: int
    goal_env: bool
    pad_to: tuple[int, int] | None
    task_id_size: int = 0
    algo: str = "TD3"
    labels: tuple[str, ...] = ()
    drop_observation: tuple[int, ...] = ()
    normalize_obs: bool = False
    config: dict[str, Any] = dataclasses.field(default_factory=dict)
    wall_time: float = 0.0

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), indent=2, default=_json_default)

    @classmethod
    def from_json(cls, text: str, where: str) -> CheckpointMeta:
        try:
            data = json.loads(text)
            if data.get("pad_to") is not None:
                data["pad_to"] = tuple(data["pad_to"])
            data["labels"] = tuple(data.get("labels", ()))
            data["drop_observation"] = tuple(data.get("drop_observation", ()))
            return cls(**data)
        except (ValueError, TypeError) as exc:
            raise CheckpointError(f"{where}: not a valid checkpoint meta.json: {exc}") from exc


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, tuple):
        return list(o)
    raise TypeError(f"cannot store {type(o).__name__} in meta.json")


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _fsync_file(path: Path) -> None:
    with open(path, "rb+") as f:
        os.fsync(f.fileno())


def write_atomic(path: Path, data: bytes) -> None:
    """Replace ``path`` with ``data`` atomically: a reader (or a process started after a crash) sees the old
    contents or the new, never a part.

    Raises:
        OSError: the disk refused; ``path`` is untouched (a ``.NAME.tmp`` may be left beside it).
    """
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def _buffer_state(buffer: Any) -> dict[str, Any]:
    """The replay buffer's filled rows and scalar state (SB3 ReplayBuffer, DictReplayBuffer, HerReplayBuffer)."""
    size = int(buffer.buffer_size)
    n = size if buffer.full else int(buffer.pos)
    arrays: dict[str, Any] = {}
    scalars: dict[str, Any] = {}
    for key, value in vars(buffer).items():
        if key in ("env", "device", "observation_space", "action_space"):
            continue
        if isinstance(value, np.ndarray) and value.ndim >= 1 and value.shape[0] == size:
            arrays[key] = value[:n].copy()
        elif (
            isinstance(value, dict)
            and value
            and all(isinstance(v, np.ndarray) and v.ndim >= 1 and v.shape[0] == size for v in value.values())
        ):
            arrays[key] = {k: v[:n].copy() for k, v in value.items()}
        elif isinstance(value, int | float | bool | np.ndarray | np.generic | str) or value is None:
            scalars[key] = value
    return {"class": type(buffer).__name__, "buffer_size": size, "rows": n, "arrays": arrays, "scalars": scalars}


def save_checkpoint(
    model: Any,
    run_dir: str | Path,
    meta: CheckpointMeta,
    *,
    keep: int = 2,
    replay_buffer: bool = True,
) -> Path:
    """Write the model (and its replay buffer, and the observation statistics of its VecNormalize if it trains on
    one) as ``checkpoints/step_<step>`` atomically; returns its directory.

    Raises:
        OSError: the disk refused; the previous checkpoint and ``latest`` are untouched.
    """
    root = Path(run_dir) / "checkpoints"
    root.mkdir(parents=True, exist_ok=True)
    name = f"step_{meta.step:09d}"
    final = root / name
    tmp = root / f".tmp-{name}-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    get_vec_normalize = getattr(model, "get_vec_normalize_env", None)
    vec_normalize = get_vec_normalize() if get_vec_normalize is not None else None
    try:
        model.save(tmp / MODEL_FILE)
        if replay_buffer and getattr(model, "replay_buffer", None) is not None:
            with open(tmp / BUFFER_FILE, "wb") as f:
                pickle.dump(_buffer_state(model.replay_buffer), f, protocol=pickle.HIGHEST_PROTOCOL)
        if vec_normalize is not None:
            vec_normalize.save(tmp / OBS_STATS_FILE)  # pickles the statistics and settings, not the envs
        meta = dataclasses.replace(meta, wall_time=time.time(), normalize_obs=vec_normalize is not None)
        (tmp / META_FILE).write_text(meta.to_json())
        for p in tmp.iterdir():
            _fsync_file(p)
        _fsync_dir(tmp)
        if final.exists():  # the same step written again (e.g. the end of a run that just checkpointed)
            old = root / f".old-{name}-{os.getpid()}"
            os.replace(final, old)
            os.replace(tmp, final)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, final)
        _fsync_dir(root)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    write_atomic(root / LATEST_FILE, (name + "\n").encode())
    complete = sorted(p for p in root.iterdir() if p.is_dir() and p.name.startswith("step_"))
    for old in complete[:-keep]:
        if old != final:
            shutil.rmtree(old, ignore_errors=True)
    return final


def _complete(path: Path) -> bool:
    return (path / MODEL_FILE).is_file() and (path / META_FILE).is_file()


def latest_checkpoint(run_dir: str | Path) -> Path | None:
    """The newest complete checkpoint of a run (what ``latest`` names, else the highest step), or None."""
    root = Path(run_dir) / "checkpoints"
    if not root.is_dir():
        return None
    latest = root / LATEST_FILE
    if latest.is_file():
        cand = root / latest.read_text().strip()
        if _complete(cand):
            return cand
    steps = sorted(p for p in root.iterdir() if p.is_dir() and p.name.startswith("step_") and _complete(p))
    return steps[-1] if steps else None


def clean_partial(run_dir: str | Path) -> None:
    """Tidy what an interrupted checkpoint left behind: unfinished ``.tmp-*`` directories and files are removed; an
    ``.old-step_N-PID`` (a complete checkpoint moved aside to be replaced by a rewrite of the same step) goes back
    to ``step_N`` when the rewrite never landed, else it is removed."""
    root = Path(run_dir) / "checkpoints"
    if not root.is_dir():
        return
    for p in sorted(root.iterdir()):
        if p.name.startswith(".old-"):
            name = p.name.removeprefix(".old-").rsplit("-", 1)[0]
            if name.startswith("step_") and not (root / name).exists() and _complete(p):
                os.replace(p, root / name)
                _fsync_dir(root)
            else:
                shutil.rmtree(p, ignore_errors=True)
        elif p.name.startswith(".tmp-"):
            shutil.rmtree(p, ignore_errors=True)
        elif p.name.startswith(".") and p.name.endswith(".tmp") and p.is_file():
            p.unlink(missing_ok=True)


def find_checkpoint(path: str | Path) -> Path:
    """Resolve a run directory, a checkpoint directory, a weights directory or a ``model.zip`` to its directory.

    Raises:
        CheckpointError: nothing usable there (what was looked for is named).
    """
    p = Path(path)
    if p.is_file() and p.name == MODEL_FILE:
        p = p.parent
    if p.is_dir() and (_complete(p) or ((p / "policy.npz").is_file() and (p / META_FILE).is_file())):
        return p  # a checkpoint, or the policy weights of one (weights.py)
    if p.is_dir():
        found = latest_checkpoint(p)
        if found is not None:
            return found
    raise CheckpointError(
        f"no checkpoint at {str(path)!r}: expected a run directory with checkpoints/, a checkpoint directory "
        f"with {MODEL_FILE} and {META_FILE}, or a {MODEL_FILE}"
    )


def read_meta(ckpt: Path) -> CheckpointMeta:
    """The checkpoint's meta.json."""
    f = ckpt / META_FILE
    try:
        text = f.read_text()
    except OSError as exc:
        raise CheckpointError(f"cannot read {f}: {exc.strerror}") from exc
    return CheckpointMeta.from_json(text, str(f))


def check_sizes(meta: CheckpointMeta, obs_size: int, action_size: int, goal_env: bool, where: str) -> None:
    """Check that an env fits the checkpoint's policy.

    Raises:
        CheckpointError: the observation or action size (or kind) differs; both sizes are named.
    """
    if goal_env != meta.goal_env:
        kind = {True: "a goal env (dict observation)", False: "a standard env (vector observation)"}
        raise CheckpointError(
            f"{where} is {kind[goal_env]}, but the checkpoint's policy was trained on {kind[meta.goal_env]}"
        )
    if (obs_size, action_size) != (meta.obs_size, meta.action_size):
        raise CheckpointError(
            f"{where} has observation size {obs_size} and action size {action_size}, but the checkpoint's policy "
            f"takes observation size {meta.obs_size} and action size {meta.action_size}"
        )


def load_replay_buffer(model: Any, ckpt: Path) -> int:
    """Fill ``model.replay_buffer`` (freshly built by SB3 ``load``) from the checkpoint; returns the rows restored.

    An unfinished HER episode at the end is closed (SB3's ``truncate_last_trajectory``), as after
    ``load_replay_buffer(truncate_last_traj=True)``.

    Raises:
        CheckpointError: no buffer file, a different buffer class, or rows that do not fit.
    """
    f = ckpt / BUFFER_FILE
    if not f.is_file():
        raise CheckpointError(f"{ckpt} has no {BUFFER_FILE} (written with checkpoint.replay_buffer: false?)")
    with open(f, "rb") as fh:
        state = pickle.load(fh)
    buf = model.replay_buffer
    if state["class"] != type(buf).__name__:
        raise CheckpointError(f"{f} holds a {state['class']}, the model uses a {type(buf).__name__}")
    n = int(state["rows"])
    if n > buf.buffer_size:
        raise ConfigError(f"{f} holds {n} rows, more than td3.buffer_size={buf.buffer_size}")
    for key, value in state["arrays"].items():
        target = getattr(buf, key)
        if isinstance(value, dict):
            for k, v in value.items():
                target[k][:n] = v
        else:
            target[:n] = value
    for key, value in state["scalars"].items():
        if key in ("buffer_size", "n_envs", "obs_shape", "action_dim"):
            continue
        setattr(buf, key, value)
    if state["buffer_size"] != buf.buffer_size and state["scalars"].get("full"):
        raise CheckpointError(f"{f}: a full buffer of {state['buffer_size']} rows cannot go into {buf.buffer_size}")
    if hasattr(buf, "truncate_last_trajectory") and n > 0:
        with warnings.catch_warnings():  # expected: the run stopped mid-episode, and the env is reset on resume
            warnings.simplefilter("ignore", UserWarning)
            buf.truncate_last_trajectory()
    return n


def load_obs_stats(ckpt: Path, venv: Any = None) -> Any:
    """The checkpoint's observation statistics (an SB3 ``VecNormalize``), or None if it was trained without.

    With ``venv`` (resuming): ``VecNormalize.load`` over it, collecting statistics (``training=True``). Without
    (evaluation): the statistics alone, frozen (``training=False``) and with no env: use ``normalize_obs`` only.
    Rewards are never normalised (``norm_reward=False``).

    Raises:
        CheckpointError: meta.json says the policy takes normalised observations and the file is missing or
            unreadable, or the file does not hold a VecNormalize.
    """
    from stable_baselines3.common.vec_env import VecNormalize

    f = ckpt / OBS_STATS_FILE
    if not read_meta(ckpt).normalize_obs:
        return None
    if not f.is_file():
        raise CheckpointError(
            f"{ckpt}'s policy was trained on normalised observations (normalize_obs) but {OBS_STATS_FILE} is "
            "missing: without its statistics the policy would see raw observations"
        )
    try:
        if venv is not None:
            stats = VecNormalize.load(str(f), venv)
        else:
            with open(f, "rb") as fh:
                stats = pickle.load(fh)
    except (OSError, pickle.UnpicklingError, EOFError, AttributeError, ValueError) as exc:
        raise CheckpointError(f"cannot load the observation statistics {f}: {exc}") from exc
    if not isinstance(stats, VecNormalize):
        raise CheckpointError(f"{f} holds a {type(stats).__name__}, not a VecNormalize")
    stats.training = venv is not None
    stats.norm_reward = False
    return stats


def check_obs_stats(stats: Any, observation_space: Any, where: str) -> None:
    """Check that observation statistics (a VecNormalize) fit an env's observation space.

    Raises:
        CheckpointError: a normalised key is missing or an entry's shape differs (both shapes named).
    """
    import gymnasium as gym

    rms = stats.obs_rms
    if isinstance(rms, dict):
        if not isinstance(observation_space, gym.spaces.Dict):
            raise CheckpointError(f"{where}: the observation statistics are per key of a dict observation")
        pairs = [(k, v, observation_space.spaces.get(k)) for k, v in rms.items()]
    else:
        pairs = [("observation", rms, observation_space)]
    for key, r, space in pairs:
        shape = getattr(space, "shape", None)
        if shape is None or tuple(shape) != tuple(r.mean.shape):
            raise CheckpointError(
                f"{where}: the checkpoint's observation statistics of {key!r} have shape {tuple(r.mean.shape)}, "
                f"the env's {key!r} has shape {shape}"
            )
