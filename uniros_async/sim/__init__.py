"""Simulated arms: the MuJoCo servo core, its bus node, the emulated real arm, serving and rendering.

    servo.py     ServoSim: synchronous MuJoCo servo core at the hardware rate (no asyncio)
    node.py      ServoSimNode / open_servo_sim: the sim on the bus, in the caller's process
    serve.py     open_servo_sim_process (own process, same domain), serve_servo_sim (remote, own tcp domain)
    emulated.py  EmulationConfig: perturbed dynamics, sensor noise, network delay (the emulated real arm)
    imperfections.py  Imperfections: servo-level imperfections of a real arm as knobs with a strength
    placement.py the "sim", "sim-process" and "emulated-real" placements' factories (uniros_async.placements)
    render.py    render_png (offscreen), view (interactive)
    cli.py       ``uniros robot serve|render|view``

Names are imported lazily, so ``import uniros_async.sim`` (and the ``uniros`` CLI) does not load MuJoCo.
"""

from __future__ import annotations

from uniros_async._lazy import lazy_exports

__all__ = [
    "EmulationConfig",
    "Imperfections",
    "LatencyModel",
    "ServeConfig",
    "ServoSim",
    "ServoSimConfig",
    "ServoSimNode",
    "ServoSimProcess",
    "ServoStats",
    "open_servo_sim",
    "open_servo_sim_process",
    "render_png",
    "serve_servo_sim",
]

_WHERE = {
    "EmulationConfig": "emulated",
    "Imperfections": "imperfections",
    "LatencyModel": "emulated",
    "ServeConfig": "serve",
    "ServoSim": "servo",
    "ServoSimConfig": "servo",
    "ServoSimNode": "node",
    "ServoSimProcess": "serve",
    "ServoStats": "servo",
    "open_servo_sim": "node",
    "open_servo_sim_process": "serve",
    "render_png": "render",
    "serve_servo_sim": "serve",
}


__getattr__, __dir__ = lazy_exports(__name__, _WHERE)
