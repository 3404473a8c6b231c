"""EpisodeStep: one env step as ``RecordEpisodes`` writes it (a message type of its own, registered whenever a bag
is read, so that an episode bag reads in a process that never imported gymnasium)."""

from __future__ import annotations

import numpy as np

from uniros_async.bus.messages import Header, array_field, message

__all__ = ["EpisodeStep"]


@message
class EpisodeStep:
    """One env step (``bag.episodes`` lists its fields)."""

    header: Header
    episode: int = 0
    step: int = 0
    observation: np.ndarray | None = array_field(np.float64, 1, optional=True, default=None)
    action: np.ndarray | None = array_field(np.float64, 1, optional=True, default=None)
    reward: float = 0.0
    terminated: bool = False
    truncated: bool = False
    success: bool | None = None
    desired_goal: np.ndarray | None = array_field(np.float64, 1, optional=True, default=None)
    achieved_goal: np.ndarray | None = array_field(np.float64, 1, optional=True, default=None)
    step_wall_ns: int = 0
    """How long ``step`` took, on the wall clock."""
    tick_ns: np.ndarray | None = array_field(np.int64, 1, optional=True, default=None)
    """The env loop's ticks since the previous step (the env's clock)."""
    command_ns: np.ndarray | None = array_field(np.int64, 1, optional=True, default=None)
    """The ticks of those that sent a command."""
    observation_age_ns: int | None = None
    action_latency_ns: int | None = None
