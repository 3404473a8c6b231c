"""The ``uniros robot vbus`` subcommand (sim/cli.py adds it); importing this module is cheap (no MuJoCo)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

__all__ = ["add_parser", "run"]


def add_parser(actions: Any) -> argparse.ArgumentParser:
    """Add ``vbus`` to the ``uniros robot`` actions; returns its parser."""
    vbus: argparse.ArgumentParser = actions.add_parser(
        "vbus",
        help="a virtual Dynamixel bus on a pty, answered by the arm's servo sim; prints the pty's path, then "
        "serves until SIGINT (fault lines on stdin: uniros_async/hardware/dxl/vbus_pty.py)",
    )
    vbus.add_argument("servo_map", help="a registered servo map (rx200), or MODULE:NAME for one MODULE registers")
    vbus.add_argument("--baud", type=int, default=None, help="baud rate of the timing model (default: the map's)")
    vbus.add_argument("--emulate-real", action="store_true", help="the emulated real arm's dynamics and sensor noise")
    vbus.add_argument("--seed", type=int, default=0, help="seed of the emulated arm (default %(default)s)")
    return vbus


def run(args: argparse.Namespace) -> int:
    """Run ``uniros robot vbus``.

    Raises:
        ConfigError: an unknown servo map, or a bad baud rate (the ``uniros`` entry point reports it).
    """
    from uniros_async.hardware.dxl.servo_map import servo_map
    from uniros_async.hardware.dxl.vbus_pty import serve_vbus
    from uniros_async.sim.emulated import EmulationConfig

    servos = servo_map(args.servo_map)
    emulation = EmulationConfig(seed=args.seed) if args.emulate_real else None
    return serve_vbus(servos, baud=args.baud, emulation=emulation, control_fd=sys.stdin.fileno())
