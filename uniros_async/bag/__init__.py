"""Bags: what the bus carried, kept in MCAP files that ROS 2 tools and Foxglove read, and read back here.

    from uniros_async.bag import BagReader

    for m in BagReader("run.mcap").messages(["/rx200/joint_states"]):
        print(m.log_time_ns, m.message.position)

``BagWriter`` writes (a thread of its own, bounded memory, counted drops), ``record`` records topics of a domain,
``play`` publishes a bag into a domain, ``RecordEpisodes`` records an env's steps, and ``uniros bag
record|info|play`` does the same from a shell. The formats are in ``schemas.py``.
"""

from __future__ import annotations

from typing import Any

from uniros_async.bag.errors import BagDamagedError, BagError
from uniros_async.bag.reader import BagInfo, BagMessage, BagReader, EpisodeStep, TopicInfo
from uniros_async.bag.writer import BagWriter, WriterStats

__all__ = [
    "BagDamagedError",
    "BagError",
    "BagInfo",
    "BagMessage",
    "BagReader",
    "BagWriter",
    "EpisodeStep",
    "PlayConfig",
    "RecordConfig",
    "RecordEpisodes",
    "TopicInfo",
    "WriterStats",
    "play",
    "record",
]


def __getattr__(name: str) -> Any:
    # record and play import the bus's nodes, RecordEpisodes gymnasium: only when asked for
    if name in ("record", "RecordConfig"):
        from uniros_async.bag import recorder

        return getattr(recorder, name)
    if name in ("play", "PlayConfig"):
        from uniros_async.bag import player

        return getattr(player, name)
    if name == "RecordEpisodes":
        from uniros_async.bag.episodes import RecordEpisodes

        return RecordEpisodes
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
