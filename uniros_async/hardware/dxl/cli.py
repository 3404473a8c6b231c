"""The Dynamixel parts of ``uniros robot`` (sim/cli.py adds them); importing this module is cheap (no MuJoCo).

uniros robot vbus rx200                        # a virtual servo bus on a pty; prints its path first
uniros robot serve rx200 --dxl /dev/ttyUSB0    # the arm on its bus, served in a tcp (--tls: tls) domain
uniros robot serve rx200 --dxl /dev/ttyUSB0 --ros2 0   # or as a ROS 2 driver in domain 0 (adapters/ros2_driver.py)
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Coroutine
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from uniros_async.adapters.ros2_bridge import Ros2BridgeConfig

__all__ = ["add_parser", "add_serve_arguments", "run", "serve", "serve_ros2"]


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


def add_serve_arguments(serve: argparse.ArgumentParser) -> None:
    """Add ``--dxl PATH`` and its options to ``uniros robot serve``."""
    serve.add_argument(
        "--dxl",
        default=None,
        metavar="PATH",
        help="serve the real arm on its Dynamixel bus at PATH (/dev/ttyUSB0; a vbus pty) instead of a sim, in a tcp "
        "(--tls: tls) domain, or with --ros2 as a ROS 2 driver (no uniros domain then)",
    )
    serve.add_argument("--dxl-map", default=None, help="with --dxl: the servo map (default: the robot's)")
    serve.add_argument("--dxl-baud", type=int, default=None, help="with --dxl: the baud rate (default: the map's)")
    serve.add_argument(
        "--dxl-margin-ms",
        type=float,
        default=None,
        help="with --dxl: host-side slack of each bus transaction's timeout (default 10; ~35 for an FTDI adapter "
        "whose latency timer is left at 16 ms)",
    )
    serve.add_argument(
        "--dxl-profile-ms",
        type=int,
        default=None,
        help="with --dxl: the arm servos' profile, the move time of each goal in ms for a time profile (default: "
        "the map's, 2000 for the rx200; 0: none, the servos' full speed, as the sim moves to an env's commands)",
    )
    serve.add_argument(
        "--dxl-shutdown",
        choices=("hold", "rest"),
        default="hold",
        help="with --dxl: at the end, hold where the arm is (torque on) or move to rest, then torque off",
    )


def serve(
    args: argparse.Namespace, *, auth_key: bytes | None, on_ready: Callable[[str], Any]
) -> Coroutine[Any, Any, None]:
    """The coroutine that serves ``uniros robot serve ROBOT --dxl PATH`` until cancelled."""
    from uniros_async.hardware.dxl.placement import serve_dxl_arm
    from uniros_async.transports.base import TransportOptions, options_from_environ

    options = TransportOptions(
        bind_host=args.host,
        auth_key=auth_key if auth_key is not None else options_from_environ().auth_key,
        insecure=args.insecure,
        tls_cert_file=args.tls_cert,
        tls_key_file=args.tls_key,
        tls_ca_file=args.tls_ca,
    )
    return serve_dxl_arm(
        args.dxl,
        args.robot,
        host=args.host,
        port=args.port,
        tls=args.tls,
        servo_map_name=args.dxl_map,
        baud=args.dxl_baud,
        margin_s=args.dxl_margin_ms / 1e3 if args.dxl_margin_ms else None,
        shutdown=args.dxl_shutdown,
        profile_ms=args.dxl_profile_ms,
        namespace=args.namespace,
        options=options,
        on_ready=on_ready,
    )


def serve_ros2(
    args: argparse.Namespace, config: Ros2BridgeConfig, *, on_ready: Callable[[str], Any]
) -> Coroutine[Any, Any, None]:
    """The coroutine that serves ``uniros robot serve ROBOT --dxl PATH --ros2 [URI]`` until cancelled: the arm as a
    ROS 2 driver on the topics of ``config``, and no uniros domain.

    Raises:
        ConfigError: an unknown servo map.
    """
    from uniros_async.adapters.ros2_driver import serve_ros2_dxl_driver
    from uniros_async.hardware.dxl.servo_map import arm_servo_map

    servos = arm_servo_map(args.dxl_map, config.spec.name, args.dxl_profile_ms)
    return serve_ros2_dxl_driver(
        config,
        args.dxl,
        servos,
        baud=args.dxl_baud,
        margin_s=args.dxl_margin_ms / 1e3 if args.dxl_margin_ms else None,
        shutdown=args.dxl_shutdown,
        on_ready=on_ready,
    )
