"""Checks of env ids and keyword arguments, made in the caller before any worker starts.

``check_env_args`` tells an unknown id or keyword argument (and a malformed ``worker`` placement) at once, with
what was expected, instead of as a worker's failure; ``split_placement`` takes the ``worker`` keyword (where the
worker runs: a launcher, runtime/remote.py, or a node Ray picks, runtime/ray_backend.py) out of a spec's kwargs.
"""

from __future__ import annotations

import difflib
import importlib
from typing import Any

from gymnasium.envs.registration import registry

from uniros_async.errors import ConfigError
from uniros_async.runtime.ray_backend import RayPlacement, parse_ray_placement
from uniros_async.runtime.remote import RemoteWorker, check_plain, parse_placement

__all__ = ["PLACEMENT_KWARG", "check_env_args", "registration", "split_placement"]

# gymnasium.make's own keyword arguments (not passed to the env constructor)
_MAKE_KWARGS = {"max_episode_steps", "disable_env_checker", "autoreset", "apply_api_compatibility"}
# where the worker runs (runtime/remote.py); taken out of the kwargs before they reach the env
PLACEMENT_KWARG = "worker"


def split_placement(kwargs: dict[str, Any]) -> tuple[RemoteWorker | RayPlacement | None, dict[str, Any]]:
    """The placement of a spec (None: a local worker) and the kwargs without it.

    Raises:
        ConfigError: a malformed ``worker`` value.
    """
    if PLACEMENT_KWARG not in kwargs:
        return None, kwargs
    rest = {k: v for k, v in kwargs.items() if k != PLACEMENT_KWARG}
    value = kwargs[PLACEMENT_KWARG]
    return parse_ray_placement(value) or parse_placement(value), rest


def check_env_args(env_id: str, kwargs: dict[str, Any]) -> None:
    """Check, in the caller, that ``env_id`` is registered and (for uniros envs) that ``kwargs`` are known.

    ``worker`` (where the worker runs, see runtime/remote.py) is accepted and checked, never passed to the env. For
    a spec placed on a launcher, an id unknown here is left to the launcher's registry to judge; for a spec placed by
    Ray, a ``"module:Id"`` whose module does not import here is left to the worker's node.

    Raises:
        ConfigError: an unknown id (the registered uniros ids are listed) or unknown keyword arguments (the
            valid ones are listed), or an invalid run-time setting (EnvConfig's own checks), or a malformed
            ``worker``, or (remote) kwargs that are not plain data.
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
            if placement is None:  # a launcher may have the module where this machine has not
                raise ConfigError(
                    f"env id {env_id!r}: cannot import {module!r}, which should register {reg_id!r}: {exc}"
                ) from exc
    # a launcher judges an id unknown here; a node Ray picks has the same uniros registry, and judges "module:Id"
    judged_there = isinstance(placement, RemoteWorker) or (isinstance(placement, RayPlacement) and ":" in env_id)
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
