"""The sim placements' factories: ``robot="sim"``, ``"sim-process"`` and ``"emulated-real"``.

``uniros_async.placements`` registers them by entry point (``"uniros_async.sim.placement:open_sim"``), so the
placement registry never imports sim code; this module is imported when an env first opens one of them. Each
factory takes the env's ``PlacementRequest`` and returns an async context manager that yields the ``ArmLink`` of a
servo sim it starts, and stops that sim on exit.
"""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator
from contextlib import AbstractAsyncContextManager
from typing import TYPE_CHECKING

from uniros_async.placements import ArmLink, PlacementRequest

if TYPE_CHECKING:
    from uniros_async.envs.config import EnvConfig
    from uniros_async.sim.emulated import EmulationConfig
    from uniros_async.sim.imperfections import Imperfections, Randomization

__all__ = ["open_emulated_real", "open_sim", "open_sim_process"]


def _sim_settings(
    request: PlacementRequest[EnvConfig], emulated: bool
) -> tuple[EmulationConfig | None, Imperfections | None, Randomization | None]:
    """The (emulation, imperfections, randomize) of the env's config: ``imperfections`` or ``randomize`` replace an
    emulated arm's default emulation."""
    from uniros_async.sim.emulated import EmulationConfig
    from uniros_async.sim.imperfections import Imperfections, Randomization

    cfg = request.config
    imperfections = None if cfg.imperfections is None else Imperfections.of(cfg.imperfections, cfg.emulation_seed)
    randomize = None if cfg.randomize is None else Randomization(ranges=cfg.randomize, seed=cfg.emulation_seed)
    custom = imperfections is not None or randomize is not None
    emulation = EmulationConfig(seed=cfg.emulation_seed) if emulated and not custom else None
    return emulation, imperfections, randomize


@contextlib.asynccontextmanager
async def _open_in_process_sim(request: PlacementRequest[EnvConfig], *, emulated: bool) -> AsyncIterator[ArmLink]:
    """The servo sim (``emulated``: the emulated real arm's model) in the env's process, on its clock, over memory."""
    from uniros_async.bus import open_domain
    from uniros_async.sim.node import open_servo_sim

    emulation, imperfections, randomize = _sim_settings(request, emulated)
    async with (
        open_domain("memory://") as domain,
        open_servo_sim(
            request.robot,
            domain=domain,
            clock=request.clock,
            emulation=emulation,
            imperfections=imperfections,
            randomize=randomize,
        ),
    ):
        yield ArmLink(domain=domain)


@contextlib.asynccontextmanager
async def _open_sim_process(request: PlacementRequest[EnvConfig], *, emulated: bool) -> AsyncIterator[ArmLink]:
    """The servo sim in a child process of a tcp domain this env opens; the emulated arm is reached over tcp only,
    as a physical arm on the network would be, the nominal sim over shm."""
    from uniros_async.bus import open_domain
    from uniros_async.sim.serve import open_servo_sim_process

    transport = "tcp" if emulated else "auto"
    emulation, imperfections, randomize = _sim_settings(request, emulated)
    async with (
        open_domain("tcp://127.0.0.1:0") as domain,
        # the spec itself, not its name: the child then finds a robot registered by user code too
        open_servo_sim_process(
            request.robot,
            domain=domain,
            emulation=emulation,
            imperfections=imperfections,
            randomize=randomize,
            transport=transport,
        ) as process,
    ):
        yield ArmLink(domain=domain, transport=transport, process=process)


def open_sim(request: PlacementRequest[EnvConfig]) -> AbstractAsyncContextManager[ArmLink]:
    """``robot="sim"``: the nominal servo sim in the env's process (memory transport, the env's clock)."""
    return _open_in_process_sim(request, emulated=False)


def open_sim_process(request: PlacementRequest[EnvConfig]) -> AbstractAsyncContextManager[ArmLink]:
    """``robot="sim-process"``: the nominal servo sim in its own process (shm)."""
    return _open_sim_process(request, emulated=False)


def open_emulated_real(request: PlacementRequest[EnvConfig]) -> AbstractAsyncContextManager[ArmLink]:
    """``robot="emulated-real"``: the emulated real arm as a tcp service in its own process; with ``clock="sim"``
    the same emulation model (perturbed dynamics, sensor noise, latencies) in sim time in the env's process."""
    if request.config.clock == "sim":
        return _open_in_process_sim(request, emulated=True)
    return _open_sim_process(request, emulated=True)
