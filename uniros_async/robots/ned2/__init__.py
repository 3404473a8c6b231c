"""Niryo Ned2: MJCF model (ned2.xml) and robot spec."""

from __future__ import annotations

from uniros_async.robots.ned2.config import NED2

__all__ = ["NED2"]
