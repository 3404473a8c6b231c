"""How a vector env's workers share the CPU with their agent and with each other.

A worker polls for its next request for a while before it sleeps (``turn_spin_ns``), except where that poll would
hold a core the agent or another worker needs. When the workers of a vector env outnumber a machine's cores
(``cores_shared``), neither side polls, each worker runs its steps through and, by default, stays on a core of its
own slot (``shared_cores_mode``; ``worker._Server._share_cores`` applies it, the supervisor hands out the slots).
A worker that finds its agent on its own core moves off it (``move_off_core``), where the workers are fewer than the
cores: as many or more have no core each apart from the agent's.
"""

from __future__ import annotations

import ipaddress
import logging
import os
from typing import Any

__all__ = [
    "SHARED_CORES_MODES",
    "TURN_SPIN_NS",
    "cores_shared",
    "move_off_core",
    "on_loopback",
    "shared_cores_mode",
    "turn_spin_ns",
    "usable_cpus",
]

logger = logging.getLogger(__name__)


TURN_SPIN_NS = 200_000
"""How long a worker without a real-time env loop polls for the next request before it sleeps: the agent's turn
between two steps (collect the returns, pick the next actions, pack them) is longer than ``ShmTransport.spin_ns``,
so with the default every step would wake the worker from sleep (docs/performance.md has the costs).
The spin credit still stops the polling when requests come slower than this (a learner's update between steps).
Not for a tcp connection on loopback: see ``turn_spin_ns``."""


def turn_spin_ns(transport: Any) -> int:
    """How long this worker polls for its next request: ``TURN_SPIN_NS``, but a tcp connection on loopback keeps
    the transport's own ``spin_ns``. A socket wakes its reader with a sync wake-up (the kernel is told that the
    waker is about to sleep), which places a woken worker on its agent's core. There a long poll holds the agent off
    its own core for the whole window: two tcp vector envs stepped in turn take far longer a step with
    ``TURN_SPIN_NS`` than with the transport's short poll, while one env's steps cost the same with either. A poll
    that finds
    the agent on its core moves the worker off it (``TcpTransport._peer_here``, as shm's ``_peer_here``). A worker
    on another host never shares its agent's core and keeps the longer poll."""
    if on_loopback(transport):
        return int(transport.spin_ns)
    return TURN_SPIN_NS


def on_loopback(transport: Any) -> bool:
    """Whether ``transport`` is a tcp connection on loopback (its peer on this host)."""
    if getattr(transport, "scheme", None) == "tcp":
        try:
            return bool(ipaddress.ip_address(transport.sockname[0]).is_loopback)
        except (AssertionError, ValueError):  # closed (no socket), or not an IP address
            pass
    return False


SHARED_CORES_MODES = ("pin", "through", "off")


def shared_cores_mode() -> str:
    """``UNIROS_SHARED_CORES`` (default ``pin``): what the workers of a vector env do when they outnumber a
    machine's cores (``cores_shared``). ``pin``: each runs its steps through (``priority.run_steps_through``) on a
    core of its own slot (``_Server._share_cores``), and neither they nor the agent poll for the other's message;
    ``through``: the same without the pinning; ``off``: neither (they poll and the scheduler places them).

    Raises:
        ConfigError: not one of ``pin``, ``through``, ``off``.
    """
    from uniros_async.priority import environ_choice

    return environ_choice("UNIROS_SHARED_CORES", SHARED_CORES_MODES, "pin")


def usable_cpus() -> list[int]:
    """The CPUs this process may run on, in order."""
    try:
        return sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return list(range(os.cpu_count() or 1))


def cores_shared(n_workers: int) -> bool:
    """Whether ``n_workers`` workers of a vector env on one machine outnumber the cores this process may run on:
    then a step's replies come one core's share of the physics apart, so neither a worker's poll for its next
    request nor the agent's for a reply catches anything, and either poll takes the core from a worker still
    stepping (see ``shared_cores_mode`` for what the workers do instead)."""
    return n_workers > len(usable_cpus())


def move_off_core(cpu: int) -> None:
    """Move this worker off ``cpu``, its agent's core (``ShmTransport.on_shared_core``): the scheduler often wakes a
    worker on the core of the agent that woke it (in a VM, whose halted vCPU looks busy, nearly always), and the two
    then take turns on one core while the other idles. Pinned away for a moment, then allowed everywhere again: the
    worker stays on its new core until a later wake-up places it anew."""
    try:
        allowed = os.sched_getaffinity(0)
        others = allowed - {cpu}
        if others:
            os.sched_setaffinity(0, others)  # migrates at once
            os.sched_setaffinity(0, allowed)
    except OSError as exc:  # not permitted here: the turns on one core go on, correct if slower
        logger.debug("could not move off cpu %d: %s", cpu, exc)
