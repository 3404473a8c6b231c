"""``uniros robot ...``: serve, render and view simulated arms (wired into uniros_async/cli.py).

    uniros robot serve rx200 --port 0 --emulate-real   # prints the domain URI, serves until SIGINT/SIGTERM
    uniros robot serve rx200 --host 192.168.1.20 --port 7000 --tls   # the same on tls:// ($UNIROS_TLS_*)
    uniros robot bridge rx200 --ros-master http://robot-pc:11311/   # a ROS 1 arm on the bus; prints the URI
    uniros robot bridge rx200 --ros2 0                 # a ROS 2 arm (domain 0) on the bus; prints the URI
    uniros robot bridge rx200 --host 192.168.1.20 --port 7000 --tls   # either, its domain on tls://
    uniros robot render rx200 --out pic.png --goal 0.3 0.1 0.25
    uniros robot view rx200                            # needs a display

Importing this module is cheap (no MuJoCo): the ``uniros`` parser imports it for every command.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import signal
import sys
from collections.abc import Sequence
from typing import Any

from uniros_async._signals import cancel_on_signals

__all__ = ["add_parser", "main", "run"]

logger = logging.getLogger(__name__)

ROBOT_HELP = "a registered robot (rx200, ned2), or MODULE:NAME for one that MODULE registers when imported"

AUTH_KEY_ENV = "UNIROS_AUTH_KEY"
"""Where ``uniros robot serve`` and ``bridge`` read the domain's shared key by default (as domains and nodes do:
``transports.base.options_from_environ``)."""


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``robot`` command to the ``uniros`` subparsers; returns its parser."""
    robot: argparse.ArgumentParser = subparsers.add_parser(
        "robot", help="simulated, emulated, ROS 1 and ROS 2 arms: serve, bridge, render, view"
    )
    actions = robot.add_subparsers(dest="robot_action", required=True)

    serve = actions.add_parser(
        "serve", help="serve a servo sim in an own tcp (or, with --tls, tls) domain; prints the domain URI"
    )
    serve.add_argument("robot", help=ROBOT_HELP)
    serve.add_argument("--host", default="127.0.0.1", help="bind host of the domain and the node (default %(default)s)")
    serve.add_argument("--port", type=int, default=0, help="domain port; 0 picks a free one (default %(default)s)")
    serve.add_argument("--namespace", default=None, help="topic namespace (default /ROBOT)")
    serve.add_argument(
        "--emulate-real",
        action="store_true",
        help="perturbed dynamics, sensor noise and network delay (sim/emulated.py)",
    )
    serve.add_argument("--seed", type=int, default=0, help="seed of the emulated arm (default %(default)s)")
    serve.add_argument("--sim-time", action="store_true", help="drive a SimClock and publish /clock")
    serve.add_argument(
        "--time-scale",
        type=float,
        default=1.0,
        help="with --sim-time: sim seconds per wall second; 0 = unbounded (default %(default)s)",
    )
    serve.add_argument(
        "--command-timeout",
        type=float,
        default=1.0,
        help="watchdog: hold after this many seconds without a command; 0 disables",
    )
    serve.add_argument(
        "--max-command-age",
        type=float,
        default=0.0,
        metavar="S",
        help="drop commands stamped more than S seconds ago (the sender must share this machine's clock); 0: keep all",
    )
    serve.add_argument(
        "--trace",
        action="store_true",
        help="print every command's age and every watchdog hold as JSON lines on stdout, after the URI",
    )
    serve.add_argument("--markers", action="store_true", help="publish EE and goal markers on ROBOT/markers")
    serve.add_argument(
        "--ros1-master",
        default=None,
        metavar="URI",
        help="serve the arm as a ROS 1 driver on this master (the real driver's topics and messages, "
        "adapters/ros1_driver.py) instead of in a uniros domain; prints the master's URI",
    )
    serve.add_argument("--ros-host", default=None, help="with --ros1-master: address ROS peers reach this process at")
    serve.add_argument(
        "--ros2",
        nargs="?",
        const="ros2://",
        default=None,
        metavar="URI",
        help="serve the arm as a ROS 2 driver (the real driver's topics, messages and QoS, adapters/ros2_driver.py) "
        "instead of in a uniros domain: ros2://[DOMAIN_ID][/NAMESPACE][?driver=NAME&discovery=localhost|subnet] or a "
        "domain id (default $ROS_DOMAIN_ID, else 0); prints the ros2:// URI to drive it by",
    )
    _add_exposure_flags(serve)
    _add_tls_flags(serve)

    bridge = actions.add_parser(
        "bridge",
        help="put an arm whose driver is a ROS 1 (or, with --ros2, ROS 2) node on the bus, in an own tcp (or, with "
        "--tls, tls) domain; prints the domain URI",
    )
    bridge.add_argument("robot", help=ROBOT_HELP)
    bridge.add_argument(
        "--ros-master", default=None, help="the ROS master, http://HOST:PORT/ (default $ROS_MASTER_URI, else :11311)"
    )
    bridge.add_argument(
        "--driver",
        default=None,
        help="which of the robot's registered ROS 1 (with --ros2: ROS 2) drivers gives the defaults below "
        "(default: the robot's default)",
    )
    bridge.add_argument("--joint-states", default=None, help="the driver's sensor_msgs/JointState topic")
    # dest: "command" is the uniros subcommand's own
    bridge.add_argument("--command", dest="command_topic", default=None, help="the driver's command topic")
    bridge.add_argument(
        "--command-type",
        default=None,
        help="interbotix_xs_msgs/JointGroupCommand, trajectory_msgs/JointTrajectory or std_msgs/Float64MultiArray",
    )
    bridge.add_argument(
        "--ros2",
        nargs="?",
        const="ros2://",
        default=None,
        metavar="URI",
        help="the driver is a ROS 2 node (adapters/ros2_bridge.py): ros2://[DOMAIN_ID][/NAMESPACE][?driver=NAME&"
        "discovery=localhost|subnet] or a domain id (default $ROS_DOMAIN_ID, else 0); --ros-master and --ros-host "
        "do not apply",
    )
    bridge.add_argument(
        "--group", default=None, help="joint group of a JointGroupCommand (default: the driver's, else arm)"
    )
    bridge.add_argument(
        "--ros-host",
        default=None,
        help="address ROS peers reach this process at (default $ROS_IP, else $ROS_HOSTNAME, else 127.0.0.1)",
    )
    bridge.add_argument(
        "--host", default="127.0.0.1", help="bind host of the domain and the bridge's node (default %(default)s)"
    )
    bridge.add_argument("--port", type=int, default=0, help="domain port; 0 picks a free one (default %(default)s)")
    bridge.add_argument("--namespace", default=None, help="topic namespace (default /ROBOT)")
    _add_exposure_flags(bridge)
    _add_tls_flags(bridge)
    bridge.add_argument(
        "--state-timeout", type=float, default=10.0, help="seconds to wait for the driver's first joint state"
    )
    bridge.add_argument(
        "--max-command-age",
        type=float,
        default=2.0,
        help="ROS 1: no command published longer ago than this reaches the driver, none is sent while the newest "
        "joint state is older; 0: unguarded (default %(default)s s, an env's default robot_timeout_s)",
    )

    render = actions.add_parser("render", help="render the arm to a PNG offscreen")
    render.add_argument("robot", help=ROBOT_HELP)
    render.add_argument("--out", default="pic.png", help="output PNG (default %(default)s)")
    render.add_argument("--q", type=float, nargs="+", default=None, help="arm joint positions (default: home)")
    render.add_argument("--goal", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"), help="goal marker (m)")
    render.add_argument("--width", type=int, default=640, help="pixels (default %(default)s)")
    render.add_argument("--height", type=int, default=480, help="pixels (default %(default)s)")
    render.add_argument("--camera", default="overview", help="MJCF camera name; 'free' for a free camera")

    view = actions.add_parser("view", help="interactive MuJoCo viewer (needs a display)")
    view.add_argument("robot", help=ROBOT_HELP)
    from uniros_async.hardware.dxl import cli as dxl_cli

    dxl_cli.add_parser(actions)
    dxl_cli.add_serve_arguments(serve)
    return robot


def run(args: argparse.Namespace) -> int:
    """Run a parsed ``uniros robot ...`` command; returns the exit code.

    Raises:
        UnirosError: (ConfigError, RenderError, SimulationError) reported by the ``uniros`` entry point.
    """
    action = args.robot_action
    if action == "serve":
        return _serve(args)
    if action == "bridge":
        return _bridge(args)
    if action == "vbus":
        from uniros_async.hardware.dxl import cli as dxl_cli

        return dxl_cli.run(args)
    if action == "render":
        from uniros_async.sim.render import render_png

        path = render_png(
            args.robot,
            q=args.q,
            goal=args.goal,
            out=args.out,
            width=args.width,
            height=args.height,
            camera=None if args.camera == "free" else args.camera,
        )
        sys.stdout.write(f"{path}\n")
        return 0
    if action == "view":
        from uniros_async.sim.render import view

        view(args.robot)
        return 0
    raise AssertionError(f"unknown robot action {action!r}")


def _ros2_uri(value: str) -> str:
    return f"ros2://{value}" if value.isdigit() else value


def _bridge_ros2(args: argparse.Namespace) -> int:
    from uniros_async.adapters.ros2_bridge import Ros2BridgeConfig, serve_ros2_bridge
    from uniros_async.errors import ConfigError

    if args.ros_master is not None or args.ros_host is not None:
        raise ConfigError("--ros2 bridges a ROS 2 driver: --ros-master and --ros-host are ROS 1's")
    settings = {
        "driver": args.driver,
        "joint_states": args.joint_states,
        "command": args.command_topic,
        "command_type": args.command_type,
        "group": args.group,
        "state_timeout_s": args.state_timeout,
        "insecure": args.insecure or None,
    }
    cfg = Ros2BridgeConfig.from_uri(args.robot, _ros2_uri(args.ros2), **settings)
    return _run_until_signal(serve_ros2_bridge(cfg, **_bridge_serving(args)))


def _bridge_serving(args: argparse.Namespace) -> dict[str, Any]:
    """The keywords of ``serve_ros1_bridge`` and ``serve_ros2_bridge`` that ``bridge``'s flags give: where its
    domain listens (``--host``, ``--port``, ``--tls``), its namespace, ``_print_ready``, and the domain's and node's
    options: the shared key, ``--insecure`` and the ``--tls-*`` files (None: ``$UNIROS_TLS_*``, read when the domain
    opens)."""
    from uniros_async.transports.base import TransportOptions

    options = TransportOptions(
        auth_key=_auth_key(args),
        insecure=args.insecure,
        tls_cert_file=args.tls_cert,
        tls_key_file=args.tls_key,
        tls_ca_file=args.tls_ca,
    )
    return {
        "host": args.host,
        "port": args.port,
        "namespace": args.namespace,
        "on_ready": _print_ready,
        "options": options,
        "tls": args.tls,
    }


def _bridge(args: argparse.Namespace) -> int:
    _check_tls_flags(args, None)  # the bridge always serves a uniros domain
    if args.ros2 is not None:
        return _bridge_ros2(args)
    from uniros_async.adapters.ros1_bridge import Ros1BridgeConfig, serve_ros1_bridge

    cfg = Ros1BridgeConfig(
        robot=args.robot,
        master_uri=args.ros_master,
        driver=args.driver,
        joint_states=args.joint_states,
        command=args.command_topic,
        command_type=args.command_type,
        group=args.group,
        ros_host=args.ros_host,
        state_timeout_s=args.state_timeout,
        max_command_age_s=args.max_command_age or None,
        insecure=args.insecure,
    )
    return _run_until_signal(serve_ros1_bridge(cfg, **_bridge_serving(args)))


def _serve_ros1(args: argparse.Namespace) -> int:
    from uniros_async.adapters.ros1_bridge import Ros1BridgeConfig
    from uniros_async.adapters.ros1_driver import serve_ros1_driver
    from uniros_async.sim.emulated import EmulationConfig
    from uniros_async.sim.servo import ServoSimConfig

    if args.sim_time or args.markers or args.namespace is not None:
        from uniros_async.errors import ConfigError

        raise ConfigError(
            "--ros1-master serves on the ROS graph in wall time: --sim-time, --markers and --namespace do not apply"
        )
    if args.max_command_age:
        from uniros_async.errors import ConfigError

        raise ConfigError(
            "--max-command-age needs the sender's stamp, which the ROS 1 driver's command messages do not carry"
        )
    cfg = Ros1BridgeConfig(
        robot=args.robot, master_uri=args.ros1_master, ros_host=args.ros_host, insecure=args.insecure
    )
    emulation = EmulationConfig(seed=args.seed) if args.emulate_real else None
    servo = ServoSimConfig(command_timeout_s=args.command_timeout or None)
    on_event = None
    if args.trace:
        from uniros_async.sim.serve import print_event

        on_event = print_event
    serve = serve_ros1_driver(cfg, emulation=emulation, servo=servo, on_ready=_print_ready, on_event=on_event)
    return _run_until_signal(serve)


def _serve_ros2(args: argparse.Namespace) -> int:
    from uniros_async.adapters.ros2_bridge import Ros2BridgeConfig
    from uniros_async.adapters.ros2_driver import serve_ros2_driver
    from uniros_async.errors import ConfigError
    from uniros_async.sim.emulated import EmulationConfig
    from uniros_async.sim.servo import ServoSimConfig

    if args.sim_time or args.markers or args.namespace is not None or args.ros1_master is not None:
        raise ConfigError(
            "--ros2 serves on a ROS 2 domain in wall time: --sim-time, --markers, --namespace (give it in the URI) "
            "and --ros1-master do not apply"
        )
    cfg = Ros2BridgeConfig.from_uri(args.robot, _ros2_uri(args.ros2), insecure=args.insecure or None)
    emulation = EmulationConfig(seed=args.seed) if args.emulate_real else None
    servo = ServoSimConfig(command_timeout_s=args.command_timeout or None)
    return _run_until_signal(serve_ros2_driver(cfg, emulation=emulation, servo=servo, on_ready=_print_ready))


def _serve_dxl(args: argparse.Namespace) -> int:
    """``serve --dxl PATH``: the bus arm in a tcp/tls domain, or with ``--ros2`` as a ROS 2 driver (and no uniros
    domain: a ROS 2 stack is then the arm's one commander)."""
    from uniros_async.errors import ConfigError
    from uniros_async.hardware.dxl import cli as dxl_cli

    sim_only = {
        "--emulate-real": args.emulate_real,
        "--seed": args.seed != 0,
        "--sim-time": args.sim_time,
        "--time-scale": args.time_scale != 1.0,
        "--command-timeout": args.command_timeout != 1.0,
        "--markers": args.markers,
        "--trace": args.trace,
        "--max-command-age": bool(args.max_command_age),
    }
    given = [flag for flag, on in sim_only.items() if on]
    if given:
        raise ConfigError(f"--dxl serves the arm on its bus: {', '.join(given)} apply to the servo sim only")
    if args.ros1_master is not None:
        raise ConfigError(
            "--ros1-master: --dxl serves the bus arm in a uniros domain, or with --ros2 as a ROS 2 driver, not on ROS 1"
        )
    if args.ros2 is None:
        return _run_until_signal(dxl_cli.serve(args, auth_key=_auth_key(args), on_ready=_print_ready))
    from uniros_async.adapters.ros2_bridge import Ros2BridgeConfig

    domain_flags = {
        "--host": args.host != "127.0.0.1",
        "--port": args.port != 0,
        "--auth-key-env": args.auth_key_env is not None,
        "--namespace (give it in the ros2:// URI)": args.namespace is not None,
    }
    given = [flag for flag, on in domain_flags.items() if on]
    if given:
        raise ConfigError(f"--dxl with --ros2 serves the arm on a ROS 2 domain, not a uniros one: {', '.join(given)}")
    cfg = Ros2BridgeConfig.from_uri(args.robot, _ros2_uri(args.ros2), insecure=args.insecure or None)
    return _run_until_signal(dxl_cli.serve_ros2(args, cfg, on_ready=_print_ready))


_THREADS_BEFORE_SERVING: set[int] = set()


def _print_ready(uri: str) -> None:
    """Once serving: put the serving loop's thread (the caller), and the threads its start-up started, in the
    real-time class, an arm's hardware loop or its bridge on time beside learners and other loops (its start-up
    ran at normal priority: see ``uniros_async.priority``); then say on stdout how to reach it: a shell line to
    paste (or ``eval``) elsewhere, then a hint.

    The first line is ``export UNIROS_DOMAIN=tcp://...`` (or ``tls://...``) for our domain,
    ``export ROS_MASTER_URI=http://...`` when a ROS 1 master carries the arm, or ``export ROS_DOMAIN_ID=N`` for a
    ROS 2 driver (the hint line then gives the ``ros2://`` URI to drive it by); scripts read the value after the
    ``=``.
    """
    from uniros_async.priority import freeze_heap, raise_loop_priority, thread_ids

    freeze_heap()
    raise_loop_priority()
    for tid in thread_ids() - _THREADS_BEFORE_SERVING:  # a ROS 2 driver's cyclonedds receive threads
        raise_loop_priority(thread_id=tid)
    if uri.startswith("ros2://"):
        domain_id = uri.removeprefix("ros2://").split("/", 1)[0]
        sys.stdout.write(
            f"export ROS_DOMAIN_ID={domain_id}\n# the arm serves a ROS 2 driver's topics in this domain: robot={uri}\n"
        )
    elif uri.startswith("http://"):
        sys.stdout.write(f"export ROS_MASTER_URI={uri}\n# the arm serves a ROS 1 driver's topics on this master\n")
    elif uri.startswith("tls://"):
        sys.stdout.write(
            f"export UNIROS_DOMAIN={uri}\n# in another shell, with $UNIROS_TLS_CERT, $UNIROS_TLS_KEY and "
            "$UNIROS_TLS_CA set to that host's certificate, its key and this CA, the line above, then: "
            "uniros topic list\n"
        )
    else:
        sys.stdout.write(f"export UNIROS_DOMAIN={uri}\n# in another shell, the line above, then: uniros topic list\n")
    sys.stdout.flush()


def _run_until_signal(serve: Any) -> int:
    """Run ``serve`` (a coroutine) until SIGINT/SIGTERM; a task group's wrapping of one clear error comes out as
    that error (the ``uniros`` entry point reports it)."""
    from uniros_async.errors import UnirosError

    async def main() -> None:
        cancel_on_signals(signal.SIGINT, signal.SIGTERM)
        await serve

    from uniros_async.priority import thread_ids

    _THREADS_BEFORE_SERVING.update(thread_ids())  # what serving starts gets the loop's class (_print_ready)

    try:
        asyncio.run(main())
    except asyncio.CancelledError:  # SIGINT/SIGTERM: an orderly stop
        logger.info("stopped")
    except BaseExceptionGroup as group:
        mine = group.subgroup(UnirosError)
        if mine is None:
            raise
        first: BaseException = mine
        while isinstance(first, BaseExceptionGroup):
            first = first.exceptions[0]
        raise first from None
    return 0


def _serve(args: argparse.Namespace) -> int:
    from uniros_async.sim.emulated import EmulationConfig
    from uniros_async.sim.serve import ServeConfig, serve_servo_sim
    from uniros_async.sim.servo import ServoSimConfig

    other = "--ros2" if args.ros2 is not None else "--ros1-master" if args.ros1_master is not None else None
    _check_tls_flags(args, other)
    if args.dxl is not None:
        return _serve_dxl(args)
    if args.ros2 is not None:
        return _serve_ros2(args)
    if args.ros1_master is not None:
        return _serve_ros1(args)
    cfg = ServeConfig(
        robot=args.robot,
        host=args.host,
        port=args.port,
        namespace=args.namespace,
        servo=ServoSimConfig(command_timeout_s=args.command_timeout or None),
        emulation=EmulationConfig(seed=args.seed) if args.emulate_real else None,
        clock="sim" if args.sim_time else "wall",
        time_scale=args.time_scale or None,
        publish_markers=args.markers,
        max_command_age_s=args.max_command_age or None,
        trace=args.trace,
        auth_key=_auth_key(args),
        insecure=args.insecure,
        tls=args.tls,
        tls_cert_file=args.tls_cert,
        tls_key_file=args.tls_key,
        tls_ca_file=args.tls_ca,
    )
    return _run_until_signal(serve_servo_sim(cfg, on_ready=_print_ready))


def _add_exposure_flags(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--auth-key-env",
        default=None,
        metavar="VAR",
        help=f"read the domain's shared auth key from this environment variable (default: ${AUTH_KEY_ENV} if set); "
        "nodes joining must use the same key",
    )
    parser.add_argument(
        "--insecure",
        action="store_true",
        help="allow listening beyond loopback without authentication (--host other than 127.0.0.1 without a key; "
        "any ROS 1 listener beyond loopback, since ROS 1 cannot authenticate; ROS 2 discovery=subnet, as DDS without "
        "SROS2 cannot either)",
    )


def _add_tls_flags(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--tls",
        action="store_true",
        help="serve the domain on tls://HOST:PORT (mutual TLS: the registry and the arm's topics are encrypted, and "
        "peers need a certificate signed by the CA; no key needed beyond loopback). The certificate must name "
        "--host. Files: --tls-cert/--tls-key/--tls-ca, else $UNIROS_TLS_CERT/$UNIROS_TLS_KEY/$UNIROS_TLS_CA",
    )
    parser.add_argument("--tls-cert", default=None, metavar="PEM", help="with --tls: this host's certificate")
    parser.add_argument("--tls-key", default=None, metavar="PEM", help="with --tls: its private key")
    parser.add_argument("--tls-ca", default=None, metavar="PEM", help="with --tls: the CA that signed the peers'")


def _check_tls_flags(args: argparse.Namespace, where: str | None) -> None:
    """``--tls-*`` files only with ``--tls``; ``--tls`` only where a uniros domain is served (``where`` None)."""
    from uniros_async.errors import ConfigError

    files = [f for f in ("tls_cert", "tls_key", "tls_ca") if getattr(args, f) is not None]
    if files and not args.tls:
        flags = ", ".join("--" + f.replace("_", "-") for f in files)
        raise ConfigError(f"{flags} only apply with --tls (the domain on tls://)")
    if args.tls and where is not None:
        raise ConfigError(f"--tls serves a uniros domain on tls://; {where} serves no uniros domain")


def _auth_key(args: argparse.Namespace) -> bytes | None:
    var = args.auth_key_env or AUTH_KEY_ENV
    key = os.environ.get(var, "").encode() or None
    if args.auth_key_env and key is None:
        from uniros_async.errors import ConfigError

        raise ConfigError(f"--auth-key-env {var}: the environment variable {var} is not set (or empty)")
    return key


def main(argv: Sequence[str] | None = None) -> int:
    """Stand-alone entry (``python -m uniros_async.sim.cli serve rx200``), same as ``uniros robot ...``."""
    parser = argparse.ArgumentParser(prog="uniros robot")
    parser.add_argument("-v", "--verbose", action="store_true")
    sub = parser.add_subparsers(dest="command", required=True)
    robot = add_parser(sub)
    args = parser.parse_args(["robot", *(argv if argv is not None else sys.argv[1:])])
    del robot
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s"
    )
    from uniros_async.errors import UnirosError

    try:
        return run(args)
    except UnirosError as exc:
        sys.stderr.write(f"uniros robot: error: {exc}\n")
        return 2


if __name__ == "__main__":
    sys.exit(main())
