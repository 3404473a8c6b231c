"""Interbotix ReactorX-200: MJCF model (rx200.xml) and robot spec."""

from __future__ import annotations

from uniros_async.robots.rx200.config import RX200

__all__ = ["RX200"]
