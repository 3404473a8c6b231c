"""What ``make_vec`` is given, and how its envs are spread over worker processes.

A spec is an env id (``"uniros/Rx200Reach-v0"``, ``"module:Id"``), an ``(env id, kwargs)`` pair, or an env
factory: a callable without arguments that returns a ``gymnasium.Env``, as gymnasium's ``AsyncVectorEnv`` and
SB3's ``SubprocVecEnv`` take them. A factory is pickled with cloudpickle (as ``AsyncVectorEnv`` does), so a lambda
or a closure defined in the agent's script works; the worker process unpickles it and calls it once to build its
env. Ids and factories mix in one list. ``normalize_specs`` turns every spec into ``(name, kwargs)``: a factory's
name is its qualified name followed by ``()`` and its kwargs carry only the pickled factory (``FACTORY_KWARG``).

``envs_per_worker="auto"`` (``make_vec``'s default) decides how many envs share a worker process from what is
known before any env is built (``plan_envs_per_worker``):

- a real-time env (a uniros env whose ``clock`` is ``"wall"``: given in its kwargs, registered with its id, or
  EnvConfig's default, ``"wall"`` unless ``turn_based``) always gets a process of its own: its env loop's ticks
  must not wait for other envs' steps;
- where the accelerated envs placed here (every other env: a uniros env on the sim clock, any other gymnasium env,
  any factory) outnumber this process's cores, they share ``ceil(n / cores)`` to a process, one process per core:
  the envs of a process share its caches, where a core switching between processes pays more per step;
- otherwise every env gets a process of its own, as ``AsyncVectorEnv`` does;
- a spec placed by Ray gets a process of its own (its node's cores are not known here).

A factory is counted as accelerated: a factory that builds a wall-clock uniros env needs ``envs_per_worker=1``
(with ``"auto"`` it may share a process, and its worker then fails to start with a WorkerError that says so).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any, Literal, cast

from uniros_async.errors import ConfigError
from uniros_async.runtime.cores import usable_cpus

__all__ = [
    "AUTO",
    "FACTORY_KWARG",
    "EnvSpec",
    "factory_of",
    "is_realtime",
    "normalize_specs",
    "plan_envs_per_worker",
]

EnvSpec = str | tuple[str, dict[str, Any]] | Callable[[], Any]
"""An env id, an ``(env id, kwargs)`` pair, or an env factory (a callable without arguments)."""
FACTORY_KWARG = "__env_factory__"
"""The key under which a factory spec's kwargs carry the cloudpickled factory (never passed to an env)."""
AUTO: Literal["auto"] = "auto"


def normalize_specs(
    specs: Sequence[EnvSpec] | EnvSpec, common_kwargs: dict[str, Any], num_envs: int | None = None
) -> list[tuple[str, dict[str, Any]]]:
    """``specs`` as ``(name, kwargs)`` pairs: an id's kwargs are ``common_kwargs`` updated with its own; a factory's
    hold the pickled factory alone (``FACTORY_KWARG``). One spec given alone (an id, a pair or a factory), with
    ``num_envs`` (default 1), is that many copies of it, as ``gymnasium.make_vec(id, num_envs=n)`` has it.

    Raises:
        ConfigError: a spec that is none of the three forms, a factory that cannot be pickled, ``common_kwargs``
            given with a factory (a factory builds its env itself; keyword arguments go to ids), ``specs`` that is
            neither a list nor one spec, or ``num_envs`` that is not an int >= 1 or is given with a list (a list has
            one env per spec).
    """
    import cloudpickle

    if num_envs is not None and (isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1):
        raise ConfigError(f"num_envs must be an int >= 1, got {num_envs!r}")
    if isinstance(specs, str) or callable(specs) or (isinstance(specs, tuple) and _is_pair(specs)):  # one spec alone
        specs = [specs] * (num_envs or 1)
    elif not isinstance(specs, Iterable):
        raise ConfigError(
            "specs: expected a list of env ids, (env id, kwargs) pairs or env factories, or one of them with "
            f"num_envs; got {type(specs).__name__}"
        )
    else:
        specs = list(cast(Iterable[EnvSpec], specs))  # (a generator of factories too)
        if num_envs is not None:
            raise ConfigError(
                f"num_envs={num_envs} goes with one spec (make_vec('CartPole-v1', num_envs=4)); a list of specs has "
                f"one env per spec (here {len(specs)}): repeat the list instead"
            )
    out: list[tuple[str, dict[str, Any]]] = []
    for i, s in enumerate(specs):
        if isinstance(s, str):
            out.append((s, dict(common_kwargs)))
        elif isinstance(s, tuple | list) and _is_pair(s):
            out.append((s[0], {**common_kwargs, **s[1]}))
        elif callable(s):
            name = f"{getattr(s, '__qualname__', type(s).__qualname__)}()"
            if common_kwargs:
                raise ConfigError(
                    f"spec {i}: keyword arguments {sorted(common_kwargs)} go to env ids, not to the env factory {name}"
                    " (a factory builds its env itself)"
                )
            try:
                payload = cloudpickle.dumps(s)
            except Exception as exc:  # noqa: BLE001 - whatever the pickler raised, named
                raise ConfigError(
                    f"spec {i}: the env factory {name} cannot be pickled for its worker process "
                    f"({type(exc).__name__}: {exc})"
                ) from exc
            out.append((name, {FACTORY_KWARG: payload}))
        else:
            raise ConfigError(
                f"spec {i}: expected an env id, an (env id, kwargs) pair or an env factory (a callable without "
                f"arguments that returns a gymnasium.Env), got {s!r:.80}"
            )
    return out


def _is_pair(s: Sequence[Any]) -> bool:
    """Whether ``s`` is an ``(env id, kwargs)`` pair."""
    return len(s) == 2 and isinstance(s[0], str) and isinstance(s[1], dict)


def factory_of(kwargs: dict[str, Any]) -> bytes | None:
    """The pickled factory of a spec's kwargs, or None for an env id's."""
    payload = kwargs.get(FACTORY_KWARG)
    return payload if isinstance(payload, bytes) else None


def is_realtime(env_id: str, kwargs: dict[str, Any]) -> bool:
    """Whether the spec's env runs a real-time env loop, judged before it is built: a uniros env (its entry point in
    ``uniros_async``) whose ``clock`` (its kwargs, else the kwargs registered with its id, else EnvConfig's default:
    ``"sim"`` when ``turn_based``, else ``"wall"``) is not ``"sim"``. A factory, an id not registered here and any
    other gymnasium env: False."""
    if factory_of(kwargs) is not None:
        return False
    from gymnasium.envs.registration import registry

    reg_id = env_id.partition(":")[2] if ":" in env_id else env_id
    spec = registry.get(reg_id)
    if spec is None or not isinstance(spec.entry_point, str) or not spec.entry_point.startswith("uniros_async."):
        return False
    merged = {**spec.kwargs, **kwargs}
    clock = merged.get("clock")
    if clock is None:
        clock = "sim" if merged.get("turn_based") is True else "wall"
    return clock != "sim"


def plan_envs_per_worker(
    specs: Sequence[tuple[str, dict[str, Any]]], placed: Sequence[bool], envs_per_worker: int | str
) -> tuple[int, list[bool]]:
    """``envs_per_worker`` as ``worker_groups`` takes it: the most envs a process hosts, and which specs get a process
    of their own. ``placed``: which specs Ray places. A count is taken as it is (no spec alone); ``"auto"`` follows the
    rule of the module docstring.

    Raises:
        ConfigError: neither a count >= 1 nor ``"auto"``.
    """
    if envs_per_worker == AUTO:
        alone = [p or is_realtime(env_id, kwargs) for (env_id, kwargs), p in zip(specs, placed, strict=True)]
        accelerated = alone.count(False)
        cores = len(usable_cpus())
        return (-(-accelerated // cores) if accelerated > cores else 1), alone
    if isinstance(envs_per_worker, bool) or not isinstance(envs_per_worker, int) or envs_per_worker < 1:
        raise ConfigError(f"envs_per_worker must be an int >= 1 or 'auto', got {envs_per_worker!r}")
    return envs_per_worker, [False] * len(specs)
