"""The ``dxl://`` placement: an env's arm on its Dynamixel bus, driven from the env's own process.

    robot="dxl:///dev/ttyUSB0"                                  # the robot's servo map, at the map's baud rate
    robot="dxl:///dev/ttyUSB0?baud=1000000&map=rx200&rate=20&shutdown=rest&margin_ms=35&profile_ms=0"

The path is the serial device (a pty of ``uniros robot vbus`` too). The query may set ``baud`` (default: the
map's), ``map`` (a registered servo map; default: the one named as the env's robot), ``rate`` (the bus loop in Hz;
default the env's loop rate, ``env_loop_rate_hz``, else the robot's hardware rate, raised to at least two ticks
per Bus Watchdog window), ``shutdown`` (``hold``, the default, or ``rest``) and ``margin_ms`` (the host-side slack
of every transaction's timeout; default 10 ms, for a USB adapter whose latency timer is 1 ms: an FTDI adapter left
at its 16 ms default needs about 35) and ``profile_ms`` (the arm servos' profile, ``ServoMap.with_arm_profile``:
with the rx200's time profile the move time of each goal in ms; default the map's, Interbotix's 2000 ms; 0 runs
each goal at the servos' full speed, as the sim a policy trained on moves its servos to an env's commands).

The placement opens a memory domain in the env's process and runs ``DxlArmNode`` on it: a node in the robot's
namespace that publishes ``joint_states`` and takes ``command`` as every other placement's arm does, and serves
``hold`` and ``stats`` (the bus's counters and cycle time, the present current and, read once a second, the
temperature of each servo; the servos' Bus Watchdogs are read once a second too, ``DxlArm.check_watchdogs``). Its
loop is one task: each tick one sync read (published as the joint state) and one sync write of the newest command's
goals. The bus's fd sits in the event loop, so no transaction blocks the env's loop.
The env gets the servos' newest readings in the ``info`` of every step and reset (``DxlArmNode.info``, handed over
as ``ArmLink.info``): ``servo_current_ma`` (the servos that sense current), ``servo_load_pct`` (those that
report load instead, the XL430) and ``servo_temperature_c`` (every arm and gripper servo, read once a second), each
a dict by joint name.
A ``RobotError`` of the arm (hardware error, a silent servo: the bus's timeouts are milliseconds, well within the
env's ``robot_timeout_s``) ends the node's task and, with it, the env's loop: the env's next call raises that
RobotError, which names the joint, the servo's ID and what happened.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import dataclasses
import logging
import time
import urllib.parse
from collections.abc import AsyncIterator, Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from uniros_async.bus import open_domain, open_node
from uniros_async.bus.messages import Data, Empty, JointCommand, JointState, Trigger
from uniros_async.bus.qos import latest
from uniros_async.errors import ConfigError, DxlCrcError, RobotError
from uniros_async.hardware.dxl.control_table import MODELS
from uniros_async.placements import ArmLink, PlacementRequest
from uniros_async.transports.base import TransportOptions, options_from_environ

if TYPE_CHECKING:
    from uniros_async.bus.node import Node
    from uniros_async.clock import Clock
    from uniros_async.envs.config import EnvConfig
    from uniros_async.hardware.dxl.arm import DxlArm
    from uniros_async.hardware.dxl.servo_map import ServoMap
    from uniros_async.robots.spec import RobotSpec

__all__ = [
    "DxlArmNode",
    "DxlUri",
    "check_dxl_placement",
    "open_dxl_arm",
    "open_dxl_placement",
    "parse_dxl_uri",
    "serve_dxl_arm",
]

logger = logging.getLogger(__name__)

_KEYS = ("baud", "map", "rate", "shutdown", "margin_ms", "profile_ms")
TEMPERATURE_PERIOD_S = 1.0
"""How often the bus loop reads the servos' temperatures (one sync read of its own)."""


@dataclasses.dataclass(frozen=True)
class DxlUri:
    """A parsed ``dxl://`` URI (see the module docstring)."""

    path: str
    baud: int | None
    map_name: str | None
    rate_hz: float | None
    shutdown: str
    margin_s: float | None = None
    profile_ms: int | None = None


def parse_dxl_uri(uri: str) -> DxlUri:
    """Parse ``dxl:///dev/ttyX?baud=...&map=...&rate=...&shutdown=...``.

    Raises:
        ConfigError: no device path, an unknown key, or a value of the wrong kind.
    """
    form = "dxl:///dev/ttyUSB0?baud=1000000&map=rx200&rate=20&shutdown=hold&profile_ms=0"
    parts = urllib.parse.urlsplit(uri)
    if parts.scheme != "dxl" or parts.netloc or not parts.path.startswith("/"):
        raise ConfigError(f"robot={uri!r}: expected a serial device path after dxl://, e.g. {form}")
    query = urllib.parse.parse_qs(parts.query, keep_blank_values=True, strict_parsing=False)
    unknown = sorted(set(query) - set(_KEYS))
    if unknown:
        raise ConfigError(f"robot={uri!r}: unknown query key(s) {unknown}; expected some of {list(_KEYS)}, e.g. {form}")
    one = {k: v[-1] for k, v in query.items()}
    try:
        baud = int(one["baud"]) if "baud" in one else None
        rate = float(one["rate"]) if "rate" in one else None
        margin = float(one["margin_ms"]) / 1e3 if "margin_ms" in one else None
    except ValueError:
        raise ConfigError(
            f"robot={uri!r}: baud must be an integer, rate a number of Hz and margin_ms of ms, e.g. {form}"
        ) from None
    if any(v is not None and not v > 0 for v in (baud, rate, margin)):
        raise ConfigError(f"robot={uri!r}: baud, rate and margin_ms must be > 0")
    profile_ms = None
    if "profile_ms" in one:
        text = one["profile_ms"]
        if not (text.isdigit() and int(text) <= 32767):
            raise ConfigError(
                f"robot={uri!r}: profile_ms must be an integer in 0..32767 (the arm's move time per goal in ms; "
                f"0: none), got {text!r}"
            )
        profile_ms = int(text)
    shutdown = one.get("shutdown", "hold")
    if shutdown not in ("hold", "rest"):
        raise ConfigError(f"robot={uri!r}: shutdown must be 'hold' or 'rest', got {shutdown!r}")
    return DxlUri(parts.path, baud, one.get("map"), rate, shutdown, margin, profile_ms)


def check_dxl_placement(robot: str, config: EnvConfig) -> None:
    """The placement's check of an env config: a well-formed URI naming a registered servo map.

    Raises:
        ConfigError: a malformed URI or an unknown servo map.
    """
    from uniros_async.hardware.dxl.servo_map import servo_map

    parsed = parse_dxl_uri(robot)
    if parsed.map_name is not None:
        servo_map(parsed.map_name)


class DxlArmNode:
    """A DxlArm on the bus: publishes ``joint_states``, takes ``command``, serves ``hold`` and ``stats``.

    Args:
        node: the node (namespace ``/<robot>``).
        arm: the started arm.
        rate_hz: ticks per second.
    """

    def __init__(self, node: Node, arm: DxlArm, rate_hz: float) -> None:
        self.node, self.arm, self.rate_hz = node, arm, rate_hz
        self.ticks = 0
        self.late_ticks = 0
        self.cycle_s: collections.deque[float] = collections.deque(maxlen=2000)
        """The last ticks' bus time (sync read, then sync write), in s."""
        self.error: str = ""
        self.current_a: dict[str, float] = {}
        self.load_pct: dict[str, float] = {}
        self.temperature_c: dict[str, float] = {}
        self._reports_load = any(MODELS[s.model].current_unit_a is None for s in arm.read_servos)
        self._seen = 0
        self._cmd_echo: tuple[int, int] | None = None
        self._goal: np.ndarray | None = None
        self._gripper: float | None = None

    async def serve(self) -> None:
        """Create the topics and services, then tick until cancelled or until the arm fails (RobotError)."""
        node = self.node
        self.joint_states = await node.create_publisher(JointState, "joint_states", qos=latest())
        self.commands = await node.create_subscription(JointCommand, "command", qos=latest())
        await node.create_service(Empty, Trigger, "hold", self._srv_hold)
        await node.create_service(Empty, Data, "stats", self._srv_stats)
        loop = asyncio.get_running_loop()
        period = 1.0 / self.rate_hz
        next_t = loop.time()
        try:
            while True:
                t0 = time.perf_counter()
                await self._tick()
                self.cycle_s.append(time.perf_counter() - t0)
                next_t += period
                delay = next_t - loop.time()
                if delay < 0:
                    self.late_ticks += 1
                    next_t = loop.time()
                await asyncio.sleep(max(0.0, delay))
        except RobotError as exc:
            self.error = str(exc)
            logger.error("%s", exc)
            raise

    async def _tick(self) -> None:
        try:
            state = await self.arm.read_state(self.node.now_ns())
        except DxlCrcError:
            return  # retried within the call, counted; RobotError after max_crc_errors ticks in a row
        self.current_a, self.load_pct = state.current_a, state.load_pct
        js = state.joint_state
        echo = self._cmd_echo
        if echo is not None:
            js = JointState(
                header=js.header,
                name=js.name,
                position=js.position,
                velocity=js.velocity,
                effort=js.effort,
                command_stamp_ns=echo[0],
                command_age_ns=time.monotonic_ns() - echo[1],
            )
        self.joint_states.publish(js)
        self.ticks += 1
        if self.ticks % max(1, round(self.rate_hz * TEMPERATURE_PERIOD_S)) == 1:
            self.temperature_c = await self.arm.read_temperatures()
            await self.arm.check_watchdogs()
        sub = self.commands
        if sub.received != self._seen:
            self._seen = sub.received
            cmd = sub.latest()
            if cmd is not None:
                self._cmd_echo = (cmd.header.stamp_ns, sub.latest_recv_ns)
                pos = np.asarray(cmd.position, dtype=np.float64)
                n = len(self.arm.arm_servos)
                self._goal = pos[:n]
                self._gripper = float(pos[n]) if pos.shape[0] > n else None
        if self._goal is not None:
            # one sync write a tick (the newest goals again when no new command came): the bus watchdog stays fed
            await self.arm.write_goals(self._goal, self._gripper)

    def _srv_hold(self, req: Empty) -> Trigger:
        q = self.arm.last_q
        if q is None:
            return Trigger(success=False, message="no state read yet")
        self._seen = self.commands.received  # commands sent before the hold are dropped
        self._goal, self._gripper = q.copy(), None
        return Trigger(success=True, message=f"holding at {np.round(q, 4).tolist()}")

    def _srv_stats(self, req: Empty) -> Data:
        bus = self.arm.bus.stats
        cycles = sorted(self.cycle_s)
        value: dict[str, Any] = {
            "rate_hz": self.rate_hz,
            "ticks": self.ticks,
            "cycle_p50_us": round(cycles[len(cycles) // 2] * 1e6) if cycles else None,
            "cycle_p99_us": round(cycles[min(len(cycles) - 1, len(cycles) * 99 // 100)] * 1e6) if cycles else None,
            "late_ticks": self.late_ticks,
            "clamped": self.arm.clamped,
            "refused": self.arm.refused,
            "transactions": bus.transactions,
            "crc_errors": bus.crc_errors,
            "timeouts": bus.timeouts,
            "retries": bus.retries,
            "current_a": self.current_a,
            "load_pct": self.load_pct,
            "temperature_c": self.temperature_c,
            "error": self.error,
        }
        return Data(value=value)

    def info(self) -> dict[str, dict[str, float]]:
        """The servos' newest readings, for an env's ``info``, each a dict by joint name (copies):
        ``servo_current_ma`` (present current in mA, of the servos that sense current), ``servo_load_pct`` (present
        load in % of the stall torque, of those that report load instead; only when the arm has such servos) and
        ``servo_temperature_c`` (present temperature in degC, read every ``TEMPERATURE_PERIOD_S``). Current and
        load are the newest tick's."""
        readings = {
            "servo_current_ma": {j: round(a * 1e3, 3) for j, a in self.current_a.items()},
            "servo_temperature_c": dict(self.temperature_c),
        }
        if self._reports_load:
            readings["servo_load_pct"] = dict(self.load_pct)
        return readings


def _rate(rate_hz: float | None, watchdog_ms: int, default_hz: float) -> float:
    """The bus loop's rate: ``rate_hz`` if given (at least two ticks per watchdog window), else ``default_hz``
    raised to that."""
    floor = 2000.0 / watchdog_ms
    if rate_hz is not None:
        if rate_hz < floor:
            raise ConfigError(
                f"dxl rate={rate_hz:g} Hz: the servos' bus watchdog is {watchdog_ms} ms, so the bus loop needs at "
                f"least {floor:g} Hz (two ticks per watchdog window)"
            )
        return rate_hz
    return max(default_hz, floor)


@contextlib.asynccontextmanager
async def open_dxl_arm(
    path: str,
    robot: RobotSpec,
    servos: ServoMap,
    *,
    domain: Any,
    baud: int | None = None,
    rate_hz: float | None = None,
    default_rate_hz: float | None = None,
    margin_s: float | None = None,
    shutdown: str = "hold",
    clock: Clock | None = None,
    namespace: str | None = None,
    transport: str = "auto",
    options: TransportOptions | None = None,
) -> AsyncIterator[DxlArmNode]:
    """Start the arm of ``servos`` on the bus at ``path`` and serve it as a node of ``domain`` for the block.

    The bus loop runs at ``rate_hz`` if given, else at ``default_rate_hz`` (None: the robot's hardware rate) raised
    to two ticks per Bus Watchdog window. ``margin_s`` is the bus client's host-side slack on every transaction
    (None: ``bus.DEFAULT_MARGIN_S``, for a USB adapter whose latency timer is 1 ms).

    Raises:
        ConfigError: a map of another robot, or a rate too low for the servos' bus watchdog.
        DxlPortError: the port cannot be opened (for EACCES the message names the dialout group).
        RobotError: the start-up failed (a silent servo, a wrong model, ...), or, at the block's end, the arm failed
            while it was served.
    """
    from uniros_async.bus.tasks import unwrap_task_group
    from uniros_async.hardware.dxl.arm import DxlArm
    from uniros_async.hardware.dxl.bus import DEFAULT_MARGIN_S, open_dxl_bus

    if servos.robot != robot.name:
        raise ConfigError(f"servo map {servos.name!r} drives {servos.robot!r}, not {robot.name!r}")
    rate = _rate(rate_hz, servos.bus_watchdog_ms, default_rate_hz or robot.hardware_rate_hz)
    return_delay_s = max(s.return_delay_time for s in servos.servos) * 2e-6
    bus = await open_dxl_bus(
        path, baud or servos.baud, return_delay_s=return_delay_s, margin_s=margin_s or DEFAULT_MARGIN_S
    )
    async with bus:
        arm = DxlArm(bus, servos, robot, shutdown=shutdown)  # type: ignore[arg-type]
        await arm.start()
        try:
            async with (
                open_node(
                    "dxl_arm",
                    domain=domain,
                    namespace=namespace or f"/{robot.name}",
                    clock=clock,
                    transport=transport,
                    options=options,
                ) as node,
                unwrap_task_group() as tg,
            ):
                arm_node = DxlArmNode(node, arm, rate)
                task = tg.create_task(arm_node.serve(), name=f"{robot.name} dxl bus")
                try:
                    yield arm_node
                finally:
                    task.cancel()
        except BaseExceptionGroup as group:
            # the arm's own failure (a RobotError naming the joint and the servo) comes out as itself
            only = group.exceptions[0] if len(group.exceptions) == 1 else None
            if isinstance(only, RobotError):
                raise only from None
            raise
        finally:
            await arm.close()


@contextlib.asynccontextmanager
async def open_dxl_placement(request: PlacementRequest[EnvConfig]) -> AsyncIterator[ArmLink]:
    """``robot="dxl://..."``: the arm on its bus in the env's process (see the module docstring)."""
    from uniros_async.hardware.dxl.servo_map import arm_servo_map

    uri = parse_dxl_uri(request.uri)
    servos = arm_servo_map(uri.map_name, request.robot.name, uri.profile_ms)
    async with (
        open_domain("memory://") as domain,
        open_dxl_arm(
            uri.path,
            request.robot,
            servos,
            domain=domain,
            baud=uri.baud,
            rate_hz=uri.rate_hz,
            default_rate_hz=request.config.env_loop_rate_hz,
            margin_s=uri.margin_s,
            shutdown=uri.shutdown,
            clock=request.clock,
        ) as arm_node,
    ):
        yield ArmLink(domain=domain, info=arm_node.info)


async def serve_dxl_arm(
    path: str,
    robot: str,
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    tls: bool = False,
    servo_map_name: str | None = None,
    baud: int | None = None,
    rate_hz: float | None = None,
    margin_s: float | None = None,
    shutdown: str = "hold",
    profile_ms: int | None = None,
    namespace: str | None = None,
    options: TransportOptions | None = None,
    on_ready: Callable[[str], Any] | None = None,
) -> None:
    """``uniros robot serve ROBOT --dxl PATH``: the arm on its bus, served in an own tcp (or tls) domain on
    ``host:port`` until cancelled, for envs elsewhere (``robot="tcp://HOST:PORT"``).

    Raises:
        ConfigError, DxlPortError, RobotError: as ``open_dxl_arm``.
    """
    from uniros_async.hardware.dxl.servo_map import arm_servo_map
    from uniros_async.robots import get_robot_spec

    spec = get_robot_spec(robot)
    servos = arm_servo_map(servo_map_name, spec.name, profile_ms)
    node_options = dataclasses.replace(options or options_from_environ(), bind_host=host)
    scheme = "tls" if tls else "tcp"
    async with (
        open_domain(f"{scheme}://{host}:{port}", options=node_options) as domain,
        open_dxl_arm(
            path,
            spec,
            servos,
            domain=domain,
            baud=baud,
            rate_hz=rate_hz,
            margin_s=margin_s,
            shutdown=shutdown,
            namespace=namespace,
            transport=scheme,
            options=node_options,
        ),
    ):
        logger.info("serving %s on %s in %s", spec.name, path, domain.uri)
        if on_ready is not None:
            on_ready(domain.uri)
        await asyncio.Event().wait()  # until cancelled
