"""Checks of env ids and keyword arguments, made in the caller before any worker starts.

``check_env_args`` tells an unknown id or keyword argument (and a malformed ``worker`` placement) at once, with
what was expected, instead of as a worker's failure; ``split_placement`` takes the ``worker`` keyword (where the
worker runs: here, or on a node Ray picks, runtime/ray_backend.py) out of a spec's kwargs.
"""

from __future__ import annotations

import difflib
import importlib
from typing import Any

import numpy as np
from gymnasium.envs.registration import registry

from uniros_async.bus.codec import encode_plain
from uniros_async.errors import CodecError, ConfigError
from uniros_async.runtime.ray_placement import RayPlacement, parse_ray_placement

__all__ = ["CLUSTER_HOWTO", "PLACEMENT_KWARG", "check_env_args", "check_plain", "registration", "split_placement"]

# gymnasium.make's own keyword arguments (not passed to the env constructor)
_MAKE_KWARGS = {"max_episode_steps", "disable_env_checker", "autoreset", "apply_api_compatibility"}
# where the worker runs (None: here; a Ray placement: runtime/ray_backend.py); taken out of the kwargs before they
# reach the env
PLACEMENT_KWARG = "worker"
CLUSTER_HOWTO = "docs/howto/cluster.md"
"""The how-to that a misplaced ``worker`` points at: workers on other hosts run on Ray."""


def split_placement(kwargs: dict[str, Any]) -> tuple[RayPlacement | None, dict[str, Any]]:
    """The placement of a spec (None: a local worker) and the kwargs without it.

    Raises:
        ConfigError: a ``worker`` value that is neither None nor a Ray placement (a ``"tcp://HOST:PORT"`` among
            them: workers on other hosts are placed by Ray).
    """
    if PLACEMENT_KWARG not in kwargs:
        return None, kwargs
    rest = {k: v for k, v in kwargs.items() if k != PLACEMENT_KWARG}
    value = kwargs[PLACEMENT_KWARG]
    if value is None:
        return None, rest
    placement = parse_ray_placement(value)
    if placement is not None:
        return placement, rest
    if isinstance(value, str) and value.startswith("tcp://"):
        raise ConfigError(
            f"worker={value!r}: workers on other hosts run on Ray: start a Ray cluster and give the spec "
            f"worker='ray' or {{'ray': {{'resources': ..., 'node_id': ...}}}}, or make_vec(..., backend='ray') "
            f"(see {CLUSTER_HOWTO})"
        )
    raise ConfigError(
        f"worker must be None (a worker on this machine), 'ray', {{'ray': {{...}}}} or a RayPlacement (placed by Ray, "
        f"on any node of a cluster: see {CLUSTER_HOWTO}), got {value!r:.80}"
    )


def _strict_default(value: Any) -> Any:
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    if isinstance(value, tuple):
        return list(value)
    raise TypeError(f"{type(value).__name__} is not plain data")


def check_plain(kwargs: dict[str, Any], env_id: str) -> None:
    """ConfigError unless ``kwargs`` can travel to a worker on another node as plain data (no pickles cross the
    wire)."""
    for k, v in kwargs.items():
        try:
            encode_plain(v, _strict_default)
        except CodecError as exc:
            raise ConfigError(
                f"{env_id}: keyword {k!r} cannot be sent to a worker placed by Ray ({exc}); use plain data"
            ) from None


def check_env_args(env_id: str, kwargs: dict[str, Any]) -> None:
    """Check, in the caller, that ``env_id`` is registered and (for uniros envs) that ``kwargs`` are known.

    ``worker`` (where the worker runs, see ``split_placement``) is accepted and checked, never passed to the env.
    For a spec placed by Ray, a ``"module:Id"`` whose module does not import here is left to the worker's node.

    Raises:
        ConfigError: an unknown id (the registered uniros ids are listed) or unknown keyword arguments (the
            valid ones are listed), or an invalid run-time setting (EnvConfig's own checks), or a malformed
            ``worker``, or (placed by Ray) kwargs that are not plain data.
    """
    from uniros_async.tasks.registry import ENV_IDS, register_envs

    placement, kwargs = split_placement(kwargs)
    if placement is not None:
        check_plain(kwargs, str(env_id))
    register_envs()
    reg_id = env_id  # the id in the registry
    if isinstance(env_id, str) and ":" in env_id:  # gymnasium's "module:Id": importing the module registers Id
        module, _, reg_id = env_id.partition(":")
        try:
            importlib.import_module(module)
        except ImportError as exc:
            if placement is None:  # the worker's node may have the module where this machine has not
                raise ConfigError(
                    f"env id {env_id!r}: cannot import {module!r}, which should register {reg_id!r}: {exc}"
                ) from exc
    # a node Ray picks has the same uniros registry, and judges a "module:Id" whose module does not import here
    judged_there = placement is not None and ":" in env_id
    if judged_there and isinstance(reg_id, str) and reg_id not in registry:
        return
    if not isinstance(reg_id, str) or reg_id not in registry:
        close = difflib.get_close_matches(str(reg_id), list(registry), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ConfigError(
            f"unknown env id {env_id!r}{hint}; registered uniros ids: {sorted(ENV_IDS)}; another gymnasium id must"
            " be registered in this process, or given as 'module:Id' (the module registers Id, in every worker too)"
        )
    entry = registry[reg_id].entry_point
    if placement is None and ":" not in env_id:
        registration(env_id)  # raises for an entry point in __main__
    if not isinstance(entry, str) or not entry.startswith("uniros_async."):
        return
    module, _, name = entry.partition(":")
    cls = getattr(importlib.import_module(module), name)
    if not hasattr(cls, "TASK_KEYS"):
        return
    from uniros_async.envs.task import split_kwargs

    env_kwargs = {k: v for k, v in kwargs.items() if k not in _MAKE_KWARGS and k not in registry[reg_id].kwargs}
    split_kwargs(cls, env_kwargs)


def registration(env_id: str) -> dict[str, Any] | None:
    """What a worker needs to register ``env_id`` as this process has it, when the id is registered here with an
    entry point in an importable module: a worker is a fresh interpreter, where only the ids that gymnasium, uniros
    and the modules it imports register exist (an id registered by the agent's script is not). None for an id that
    is not registered here, or given as ``"module:Id"`` (the worker imports the module).

    Raises:
        ConfigError: the entry point is defined in ``__main__``, which a worker does not import.
    """
    if ":" in env_id or env_id not in registry:
        return None
    spec = registry[env_id]
    entry = spec.entry_point
    if callable(entry):
        module = getattr(entry, "__module__", None)
        name = getattr(entry, "__qualname__", None)
        if module == "__main__":
            raise ConfigError(
                f"env id {env_id!r}: its entry point {name} is defined in __main__, which worker processes do not "
                "import (each is a fresh interpreter); define the env in a module of its own and register it there "
                "(then name it 'module:Id'), or register it with entry_point='module:Class'"
            )
        if not module or not name or "<locals>" in name:
            return None
        entry = f"{module}:{name}"
    if not isinstance(entry, str):
        return None
    return {
        "id": env_id,
        "entry_point": entry,
        "kwargs": dict(spec.kwargs),
        "max_episode_steps": spec.max_episode_steps,
        "reward_threshold": spec.reward_threshold,
        "nondeterministic": spec.nondeterministic,
        "order_enforce": spec.order_enforce,
        "disable_env_checker": spec.disable_env_checker,
    }
