"""Policy weights: a trained TD3 actor as plain arrays, and the function that turns them back into a policy.

A checkpoint (checkpoint.py) holds everything needed to resume training: the SB3 zip with both networks, their
optimisers and counters, and the replay buffer. To act, only the actor is needed. ``export_weights`` writes it as
a weights directory::

    policy.npz      the actor's state_dict (``mu.0.weight``, ...), the action bounds and the observation keys
    obs_stats.npz   with ``normalize_obs``: the observation statistics (mean, var, clip, epsilon per key)
    meta.json       the checkpoint's meta.json (sizes, padding, the run's config)

``load_policy`` reads one back as a callable ``obs -> action`` in NumPy alone (no torch, no SB3): the observation
normalised as VecNormalize does, flattened and concatenated as SB3's extractors do (a Dict observation in the order
of its keys at training), the MLP with ReLU and a tanh output, scaled to the action space's bounds. Its actions are
SB3's ``model.predict(obs, deterministic=True)`` to float32 rounding. ``uniros eval`` and ``evaluate_checkpoint``
take a weights directory wherever they take a checkpoint.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from uniros_async.training.checkpoint import META_FILE, CheckpointError, load_obs_stats, read_meta

__all__ = ["OBS_STATS_FILE", "WEIGHTS_FILE", "WeightsPolicy", "export_weights", "is_weights_dir", "load_policy"]

WEIGHTS_FILE = "policy.npz"
OBS_STATS_FILE = "obs_stats.npz"

_Obs = npt.NDArray[Any] | Mapping[str, npt.NDArray[Any]]


def _stat(key: str, what: str) -> str:
    """The name of an observation statistic in obs_stats.npz: ``observation.mean`` (a Dict key), ``mean`` (a Box)."""
    return f"{key}.{what}" if key else what


def is_weights_dir(path: str | Path) -> bool:
    """Whether ``path`` is a directory written by ``export_weights`` (policy.npz and meta.json)."""
    p = Path(path)
    return (p / WEIGHTS_FILE).is_file() and (p / META_FILE).is_file()


class WeightsPolicy:
    """A deterministic TD3 actor in NumPy: call it with one observation (or a batch) to get its action(s).

    ``predict`` has SB3's signature, so the evaluation loops that run SB3 models run it too; it normalises the
    observations itself, so ``get_vec_normalize_env`` returns None.
    """

    def __init__(self, arrays: Mapping[str, npt.NDArray[Any]], stats: Mapping[str, npt.NDArray[Any]] | None) -> None:
        """Build the policy from the arrays of policy.npz and, when the policy was trained on normalised
        observations, of obs_stats.npz.

        Raises:
            CheckpointError: a layer, the action bounds or the observation keys are missing.
        """
        try:
            self.action_low = np.asarray(arrays["action_low"], dtype=np.float32)
            self.action_high = np.asarray(arrays["action_high"], dtype=np.float32)
            self.obs_keys: tuple[str, ...] = tuple(str(k) for k in arrays["obs_keys"])
            indices = sorted(int(k.split(".")[1]) for k in arrays if k.startswith("mu.") and k.endswith(".weight"))
            self.layers = [
                (np.asarray(arrays[f"mu.{i}.weight"], np.float32).T, np.asarray(arrays[f"mu.{i}.bias"], np.float32))
                for i in indices
            ]
        except KeyError as exc:
            raise CheckpointError(f"{WEIGHTS_FILE} lacks {exc.args[0]!r}: not written by export_weights") from exc
        if not self.layers:
            raise CheckpointError(f"{WEIGHTS_FILE} holds no layer mu.N.weight: not written by export_weights")
        self.obs_size = int(self.layers[0][0].shape[0])
        self.stats = dict(stats) if stats is not None else None

    def _features(self, obs: _Obs) -> tuple[npt.NDArray[np.float32], bool]:
        """The actor's input rows, and whether ``obs`` was a single observation."""
        if self.obs_keys:
            if not isinstance(obs, Mapping):
                raise CheckpointError(f"the policy takes a dict observation with keys {list(self.obs_keys)}")
            parts = [np.asarray(obs[k], dtype=np.float64) for k in self.obs_keys]
        else:
            if isinstance(obs, Mapping):
                raise CheckpointError("the policy takes an array observation, got a dict")
            parts = [np.asarray(obs, dtype=np.float64)]
        keys = self.obs_keys or ("",)
        if self.stats is not None:
            clip = float(self.stats["clip_obs"])
            eps = float(self.stats["epsilon"])
            for j, key in enumerate(keys):
                if _stat(key, "mean") in self.stats:
                    mean, var = self.stats[_stat(key, "mean")], self.stats[_stat(key, "var")]
                    parts[j] = np.clip((parts[j] - mean) / np.sqrt(var + eps), -clip, clip)
        single = parts[0].ndim <= 1
        rows = np.concatenate([p.reshape(1 if single else p.shape[0], -1) for p in parts], axis=1)
        if rows.shape[1] != self.obs_size:
            raise CheckpointError(f"the policy takes {self.obs_size} observation entries, got {rows.shape[1]}")
        return rows.astype(np.float32), single

    def __call__(self, obs: _Obs) -> npt.NDArray[np.float32]:
        """The action for ``obs`` (shape ``(action_size,)``), or for each row of a batch.

        Raises:
            CheckpointError: the observation does not fit the policy (its size, or dict against array).
        """
        x, single = self._features(obs)
        for i, (w, b) in enumerate(self.layers):
            x = x @ w + b
            x = np.maximum(x, 0.0) if i < len(self.layers) - 1 else np.tanh(x)
        action = self.action_low + 0.5 * (x + 1.0) * (self.action_high - self.action_low)
        return action[0] if single else action

    def predict(self, obs: _Obs, deterministic: bool = True) -> tuple[npt.NDArray[np.float32], None]:
        """SB3's ``predict``: ``(action, None)``; TD3's policy is deterministic either way."""
        return self(obs), None

    def get_vec_normalize_env(self) -> None:
        """None: the policy normalises its observations itself."""
        return None


def load_policy(path: str | Path) -> WeightsPolicy:
    """Load a weights directory (or its policy.npz) as a callable ``obs -> action``.

    Raises:
        CheckpointError: no policy.npz there, or meta.json says the policy takes normalised observations and
            obs_stats.npz is missing.
    """
    p = Path(path)
    d = p.parent if p.name == WEIGHTS_FILE else p
    if not (d / WEIGHTS_FILE).is_file():
        raise CheckpointError(f"no {WEIGHTS_FILE} in {str(d)!r}: expected a directory written by export_weights")
    with np.load(d / WEIGHTS_FILE, allow_pickle=False) as f:
        arrays = {k: f[k] for k in f.files}
    stats = None
    if (d / META_FILE).is_file() and read_meta(d).normalize_obs:
        if not (d / OBS_STATS_FILE).is_file():
            raise CheckpointError(
                f"{d}'s policy was trained on normalised observations but {OBS_STATS_FILE} is missing: without its "
                "statistics the policy would see raw observations"
            )
        with np.load(d / OBS_STATS_FILE, allow_pickle=False) as f:
            stats = {k: f[k] for k in f.files}
    return WeightsPolicy(arrays, stats)


def export_weights(checkpoint: str | Path, out_dir: str | Path) -> Path:
    """Write the policy weights of a checkpoint (a run, a checkpoint directory or a model.zip) to ``out_dir``.

    Returns:
        ``out_dir``, holding policy.npz, meta.json and, for a policy on normalised observations, obs_stats.npz.

    Raises:
        CheckpointError: no checkpoint there, or one whose policy is not an MLP actor (``actor.mu``).
    """
    from uniros_async.training.evaluate import load_policy as load_model  # lazy: it imports torch and SB3

    model, _, ckpt = load_model(checkpoint)
    actor = getattr(getattr(model, "policy", None), "actor", None)
    if actor is None or not hasattr(actor, "mu"):
        raise CheckpointError(f"{ckpt}: the model has no MLP actor (policy.actor.mu) to export")
    arrays: dict[str, npt.NDArray[Any]] = {
        k: v.detach().cpu().numpy() for k, v in actor.state_dict().items() if k.startswith("mu.")
    }
    space = model.policy.observation_space
    keys = list(space.spaces) if hasattr(space, "spaces") else []
    arrays["obs_keys"] = np.asarray(keys, dtype=np.str_)
    arrays["action_low"] = np.asarray(model.action_space.low, dtype=np.float32)
    arrays["action_high"] = np.asarray(model.action_space.high, dtype=np.float32)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out / WEIGHTS_FILE, **arrays)  # type: ignore[arg-type]
    vec_normalize = load_obs_stats(ckpt)
    if vec_normalize is not None:
        stats: dict[str, npt.NDArray[Any]] = {
            "clip_obs": np.asarray(vec_normalize.clip_obs, dtype=np.float64),
            "epsilon": np.asarray(vec_normalize.epsilon, dtype=np.float64),
        }
        rms = vec_normalize.obs_rms
        for key, r in rms.items() if isinstance(rms, dict) else [("", rms)]:
            stats[_stat(key, "mean")] = np.asarray(r.mean, dtype=np.float64)
            stats[_stat(key, "var")] = np.asarray(r.var, dtype=np.float64)
        np.savez_compressed(out / OBS_STATS_FILE, **stats)  # type: ignore[arg-type]
    if (out / META_FILE).resolve() != (ckpt / META_FILE).resolve():
        shutil.copyfile(ckpt / META_FILE, out / META_FILE)
    return out


def _main(argv: list[str] | None = None) -> int:
    """``python -m uniros_async.training.weights CHECKPOINT OUT_DIR``: export a checkpoint's policy weights."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m uniros_async.training.weights", description=_main.__doc__)
    parser.add_argument("checkpoint", help="a run directory, a checkpoint directory or a model.zip")
    parser.add_argument("out_dir", help="the weights directory to write")
    args = parser.parse_args(argv)
    out = export_weights(args.checkpoint, args.out_dir)
    print(json.dumps({"weights": str(out), "files": sorted(p.name for p in out.iterdir())}))
    return 0


if __name__ == "__main__":
    raise SystemExit(_main())
