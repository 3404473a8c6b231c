"""The "acme-sim" placement: uniros_async's in-process servo sim, wrapped, counting the arms it opened."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import AsyncIterator

from uniros_async.placements import ArmLink, PlacementRequest, open_placement

__all__ = ["OPENED", "open_acme_sim"]

logger = logging.getLogger(__name__)

OPENED: list[str] = []
"""The robot of every arm this placement opened in this process, in order."""


@contextlib.asynccontextmanager
async def open_acme_sim(request: PlacementRequest) -> AsyncIterator[ArmLink]:
    """Open the built-in "sim" placement for the request and yield its link; record the arm first."""
    OPENED.append(request.robot.name)
    logger.info("acme-sim: %s on %s", request.robot.name, request.uri)
    async with open_placement("sim", request) as link:
        yield link
