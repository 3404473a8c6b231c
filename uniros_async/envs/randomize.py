"""The env's side of ``randomize``: the sim draws each episode's imperfections, the env reports them.

At every reset an env with ``randomize`` calls its servo sim's ``new_episode`` service (``ServoSimNode``) with a seed
from its own ``np_random`` before the arm moves home, so the draws follow the reset's seed whichever process the
sim runs in, and puts the draw in the reset's ``info``. This module imports no sim: the env reaches the sim over the
bus only.
"""

from __future__ import annotations

from typing import Any

from uniros_async.bus.messages import Data
from uniros_async.errors import DomainError, RobotError

__all__ = ["draw_episode"]


async def draw_episode(client: Any, seed: int, timeout_s: float) -> dict[str, Any]:
    """Have a servo sim draw the next episode's imperfections from ``seed`` (its ``new_episode`` service).

    Args:
        client: a client of the sim node's ``new_episode`` service (Data -> Data).
        seed: the episode's seed (>= 0).
        timeout_s: bound on the call.

    Returns:
        The reset's ``info`` entries: ``{"imperfections": {knob: strength}, "imperfections_seed": seed}``.

    Raises:
        RobotError: no such service or no reply within ``timeout_s`` (no servo sim serves the arm), or the sim
            drew nothing.
    """
    expected = "expected a servo sim placement (robot='sim', 'sim-process' or 'emulated-real') that draws them"
    try:
        reply = await client.call(Data(value={"seed": seed}), timeout_s=timeout_s)
    except TimeoutError:
        raise RobotError(f"randomize: no reply from {client.name} within {timeout_s} s; {expected}") from None
    except DomainError as exc:
        raise RobotError(f"randomize: {exc}; {expected}") from None
    value = reply.value
    if not isinstance(value, dict) or "error" in value or "strengths" not in value:
        raise RobotError(f"randomize: {client.name} drew no imperfections: {value!r:.200}")
    return {"imperfections": dict(value["strengths"]), "imperfections_seed": value["seed"]}
