"""Quality of service of a topic connection: ``latest()`` or ``reliable(depth)``."""

from __future__ import annotations

import dataclasses
from typing import Any

from uniros_async.errors import ConfigError

__all__ = ["QoS", "latest", "reliable"]


@dataclasses.dataclass(frozen=True, slots=True)
class QoS:
    """How messages queue between a publisher and a subscriber.

    ``latest``: keep one; a newer message replaces an older unread one (ros_control commands, sensor caches).
    ``reliable(depth)``: every message, in order, while the reader stays within ``depth`` unread messages. When
    that bounded queue is full the *oldest* unread message is dropped and counted in ``dropped`` (as ROS's
    keep-last queues do), so a stalled reader never blocks a publisher or grows memory without bound. Across
    processes the transport itself loses nothing; the bound applies at the two queues (publisher's outgoing
    queue per subscriber, subscriber's incoming queue).
    """

    kind: str = "latest"
    depth: int = 1

    def __post_init__(self) -> None:
        if self.kind not in ("latest", "reliable"):
            raise ConfigError(f"QoS kind must be 'latest' or 'reliable', got {self.kind!r}")
        if self.depth < 1:
            raise ConfigError(f"QoS depth must be >= 1, got {self.depth}")
        if self.kind == "latest" and self.depth != 1:
            raise ConfigError("QoS 'latest' keeps exactly one message (depth=1)")

    def to_wire(self) -> dict[str, Any]:
        return {"kind": self.kind, "depth": self.depth}

    @classmethod
    def from_wire(cls, d: Any) -> QoS:
        if not isinstance(d, dict):
            raise ConfigError(f"QoS: expected a mapping, got {type(d).__name__}")
        return cls(kind=d.get("kind", "latest"), depth=int(d.get("depth", 1)))


def latest() -> QoS:
    """Keep only the newest message."""
    return QoS("latest", 1)


def reliable(depth: int = 100) -> QoS:
    """Every message in order, up to ``depth`` unread (then the oldest is dropped and counted)."""
    return QoS("reliable", depth)
