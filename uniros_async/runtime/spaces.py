"""One space over the spaces of a vector env's sub-envs, as ``make_vec`` batches them.

Observation spaces are joined (the union of their bounds), action spaces met (the intersection: any action in it is
valid for every sub-env); spaces that differ in kind, keys, shape or dtype are refused with a ConfigError that names
each env and its space. ``vector_box`` picks the 1-D Box that padding applies to.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from uniros_async.errors import ConfigError

__all__ = ["merge_spaces", "vector_box"]


def vector_box(space: gym.Space[Any]) -> gym.spaces.Box | None:
    """The 1-D Box that padding applies to (the ``observation`` key of a goal env), or None."""
    if isinstance(space, gym.spaces.Dict):
        space = space.spaces.get("observation")  # type: ignore[assignment]
    if isinstance(space, gym.spaces.Box) and len(space.shape) == 1:
        return space
    return None


def _listing(names: list[str], spaces: list[gym.Space[Any]]) -> str:
    return "; ".join(f"{n}: {s}" for n, s in zip(names, spaces, strict=True))


def merge_spaces(spaces: list[gym.Space[Any]], names: list[str], *, union: bool, what: str) -> gym.Space[Any]:
    """One space covering ``spaces`` (bounds: union or intersection); ConfigError naming the envs if they differ."""
    first = spaces[0]
    if isinstance(first, gym.spaces.Dict):
        if not all(isinstance(s, gym.spaces.Dict) and s.spaces.keys() == first.spaces.keys() for s in spaces):
            raise ConfigError(f"{what} spaces differ in kind or keys: {_listing(names, spaces)}")
        return gym.spaces.Dict(
            {k: merge_spaces([s[k] for s in spaces], names, union=union, what=f"{what}[{k!r}]") for k in first.spaces}  # type: ignore[index]
        )
    if isinstance(first, gym.spaces.Box):
        boxes = [
            s for s in spaces if isinstance(s, gym.spaces.Box) and (s.shape, s.dtype) == (first.shape, first.dtype)
        ]
        if len(boxes) != len(spaces):
            raise ConfigError(f"{what} spaces cannot be combined: {_listing(names, spaces)}")
        lows = np.stack([b.low for b in boxes])
        highs = np.stack([b.high for b in boxes])
        low, high = (lows.min(0), highs.max(0)) if union else (lows.max(0), highs.min(0))
        if np.any(low > high):
            raise ConfigError(f"{what} spaces have no common range: " + ", ".join(names))
        return gym.spaces.Box(low, high, shape=first.shape, dtype=first.dtype)  # a 0-d Box stays 0-d
    if not all(s == first for s in spaces):
        raise ConfigError(f"{what} spaces differ: {_listing(names, spaces)}")
    return first
