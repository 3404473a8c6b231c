"""What the ROS 1 and ROS 2 bridges share: the translation both ways, the checks and the serving.

A bridge (``ros1_bridge``, ``ros2_bridge``) puts an arm whose driver is a ROS node on the uniros bus: it republishes
the driver's joint states as our ``JointState``, in the robot's joint order and stamped by how long they waited on
the way, and turns each of our ``JointCommand`` into one message of the driver's command type, after checking it.
Both do so the same way and differ only in how a message is spelled and in what carries it (TCPROS, DDS).
``Bridge`` holds the shared part: each subclass builds its driver's command messages (``ros_command``), reads its
joint states' stamps (``driver_stamp_ns``) and sets the send of its command publisher (``_send``).
"""

from __future__ import annotations

import abc
import asyncio
import collections
import dataclasses
import logging
import time
from collections.abc import Callable
from contextlib import AbstractAsyncContextManager
from typing import TYPE_CHECKING, Any, Generic, Protocol, TypeVar

import numpy as np

from uniros_async.adapters._driver_mirror import MirrorConfig
from uniros_async.bus import open_domain
from uniros_async.bus.messages import Data, Empty, Header, JointCommand, JointState, Trigger
from uniros_async.bus.qos import latest
from uniros_async.errors import TransportClosedError
from uniros_async.transports.base import options_from_environ

if TYPE_CHECKING:
    from uniros_async.bus.node import Node
    from uniros_async.transports.base import TransportOptions

__all__ = ["LIMIT_CLAMP_RAD", "TRANSIT_WINDOW_S", "Bridge", "BridgeConfig", "BridgeStats", "serve_bridge"]

LIMIT_CLAMP_RAD = 0.05
"""How far beyond a joint limit a command may reach and still be sent, clamped to the limit (counted in
``commands_clamped``), as the servo sim and the servos themselves clip it: holding where the arm measures itself
(the env's hold) can ask for a hair past a limit the arm sits at, through sensor noise or overshoot. Further out,
a command is refused."""
TRANSIT_WINDOW_S = 60.0
"""How far back ``Bridge.queued_ns`` looks for the quickest joint state."""


class BridgeConfig(MirrorConfig, Protocol):
    """The part of a bridge config (``Ros1BridgeConfig``, ``Ros2BridgeConfig``) that ``Bridge`` reads: what a driver
    mirror reads, and how old the newest joint state may be for a command to be sent."""

    @property
    def max_command_age_s(self) -> float | None: ...  # noqa: D102


C = TypeVar("C", bound=BridgeConfig)


@dataclasses.dataclass
class BridgeStats:
    """Counters of one bridge (the ``stats`` service returns them); ``connections_reset`` and
    ``command_node_restarts`` count what the ROS 1 bridge's command guard did (0 on ROS 2, which has none)."""

    states_in: int = 0
    states_dropped: int = 0
    commands_out: int = 0
    commands_clamped: int = 0
    commands_rejected: int = 0
    commands_stale: int = 0
    connections_reset: int = 0
    command_node_restarts: int = 0


class Bridge(abc.ABC, Generic[C]):
    """The translation both ways, for one arm, whatever ROS carries it.

    Args:
        config: the bridge's settings; ``Bridge`` reads its ``BridgeConfig`` part.
        publish: publishes our ``JointState`` on the bus.
        now_ns: the bus node's clock, which stamps the published joint states.
    """

    def __init__(self, config: C, publish: Callable[[JointState], None], now_ns: Callable[[], int]) -> None:
        self.config = config
        self.spec = spec = config.spec
        self.stats = BridgeStats()
        self._send: Callable[[Any], None] | None = None  # the driver's command publisher's, while there is one
        self._publish = publish
        self._now_ns = now_ns
        self._logger = logging.getLogger(type(self).__module__)
        self._n_arm = len(spec.arm_joint_names)
        self._lower = np.asarray(spec.joint_lower_rad, dtype=np.float64)
        self._upper = np.asarray(spec.joint_upper_rad, dtype=np.float64)
        self._index_cache: dict[tuple[str, ...], np.ndarray | None] = {}
        self._warned_missing: set[str] = set()
        self._seq = 0
        self.first_state = asyncio.Event()
        self.last_q: np.ndarray | None = None  # newest measured arm positions
        self.last_state_ns: int | None = None  # time.monotonic_ns() when it arrived
        self._transit: collections.deque[tuple[int, int]] = collections.deque()  # (arrival, transit): increasing
        self.period_s = 1.0 / spec.hardware_rate_hz
        self.max_age_ns = None if config.max_command_age_s is None else round(config.max_command_age_s * 1e9)

    @abc.abstractmethod
    def ros_command(self, q: np.ndarray, duration_s: float = 0.0) -> Any:
        """The driver's command message for arm positions ``q``."""

    @abc.abstractmethod
    def driver_stamp_ns(self, msg: Any) -> int:
        """The driver's stamp of a joint state (ROS time, ns; 0 if unstamped)."""

    # ------------------------------------------------------------------------------------------- ROS -> bus

    def _index(self, names: tuple[str, ...]) -> np.ndarray | None:
        """Where each of our ``joint_state_names`` sits in a ROS message with ``names`` (-1: absent), or None when
        an arm joint is absent."""
        try:
            return self._index_cache[names]
        except KeyError:
            pass
        where = {n: i for i, n in enumerate(names)}
        idx = np.array([where.get(n, -1) for n in self.spec.joint_state_names], dtype=np.intp)
        missing_arm = [n for n, i in zip(self.spec.arm_joint_names, idx, strict=False) if i < 0]
        if missing_arm:
            self._logger.error(
                "%s: joint states on %s lack the arm joint(s) %s (they name %s); dropping such messages",
                self.spec.name,
                self.config.joint_states,
                missing_arm,
                list(names),
            )
            self._index_cache[names] = None
            return None
        for n, i in zip(self.spec.joint_state_names, idx, strict=True):
            if i < 0 and n not in self._warned_missing:
                self._warned_missing.add(n)
                self._logger.warning(
                    "%s: joint states on %s have no %r; it reads 0.0", self.spec.name, self.config.joint_states, n
                )
        self._index_cache[names] = idx
        return idx

    def on_ros_state(self, msg: Any) -> None:
        """A ``sensor_msgs`` joint state from the driver: republish it as ours, in our joint order."""
        idx = self._index(tuple(msg.name))
        if idx is None:
            self.stats.states_dropped += 1
            return
        n = len(self.spec.joint_state_names)
        fields = []
        for arr in (msg.position, msg.velocity, msg.effort):
            a = np.asarray(arr, dtype=np.float64)
            out = np.zeros(n)
            if a.shape == (len(msg.name),):  # ROS allows empty velocity / effort arrays
                present = idx >= 0
                out[present] = a[idx[present]]
            fields.append(out)
        if not np.all(np.isfinite(fields[0])):
            self.stats.states_dropped += 1
            self._logger.warning("%s: dropped a joint state with non-finite positions %s", self.spec.name, fields[0])
            return
        self._seq += 1
        self.stats.states_in += 1
        self.last_q = fields[0][: self._n_arm].copy()
        self.last_state_ns = time.monotonic_ns()
        queued = self.queued_ns(self.driver_stamp_ns(msg), time.time_ns(), self.last_state_ns)
        self._publish(
            JointState(
                header=Header(stamp_ns=self._now_ns() - queued, seq=self._seq, frame_id=msg.header.frame_id),
                name=self.spec.joint_state_names,
                position=fields[0],
                velocity=fields[1],
                effort=fields[2],
            )
        )
        self.first_state.set()

    def queued_ns(self, driver_stamp_ns: int, wall_ns: int, now_ns: int) -> int:
        """How much longer than the quickest joint state of the last ``TRANSIT_WINDOW_S`` this one (stamped
        ``driver_stamp_ns`` by the driver, ROS time) took to arrive (``wall_ns``, our wall clock): the time it
        waited on the way, in a socket buffer or a cut link. Its stamp on the bus is that much before its arrival,
        so an env counts it as old as it is (states a healed link delivers in a burst look fresh otherwise). An
        offset between the driver's clock and ours cancels out, as does a delay every state has; 0 for a state
        the driver did not stamp."""
        if driver_stamp_ns <= 0:
            return 0
        transit = wall_ns - driver_stamp_ns
        q = self._transit
        while q and q[-1][1] >= transit:
            q.pop()
        q.append((now_ns, transit))
        horizon = now_ns - round(TRANSIT_WINDOW_S * 1e9)
        while len(q) > 1 and q[0][0] < horizon:
            q.popleft()
        return max(0, transit - q[0][1])

    # ------------------------------------------------------------------------------------------- bus -> ROS

    def state_age_s(self) -> float | None:
        """Seconds since the newest joint state arrived (None before the first)."""
        return None if self.last_state_ns is None else (time.monotonic_ns() - self.last_state_ns) / 1e9

    def states_stale(self) -> bool:
        """Whether the newest joint state is older than ``max_command_age_s`` (never when unguarded)."""
        if self.max_age_ns is None:
            return False
        return self.last_state_ns is None or time.monotonic_ns() - self.last_state_ns > self.max_age_ns

    def on_command(self, cmd: JointCommand) -> None:
        """One of our ``JointCommand``: checked, then sent as one message of the driver's command type."""
        if self.states_stale():
            self.stats.commands_stale += 1
            if self.stats.commands_stale == 1 or self.stats.commands_stale % 100 == 0:
                self._logger.warning(
                    "%s: command not sent to %s: the newest joint state is %.2f s old (max_command_age_s=%s); "
                    "%d refused so far",
                    self.spec.name,
                    self.config.command,
                    self.state_age_s() or float("inf"),
                    self.config.max_command_age_s,
                    self.stats.commands_stale,
                )
            return
        q = np.asarray(cmd.position, dtype=np.float64)
        if q.shape != (self._n_arm,) or not np.all(np.isfinite(q)):
            self._reject(f"expected {self._n_arm} finite positions {self.spec.arm_joint_names}, got {q.tolist()}")
            return
        outside = (q < self._lower - LIMIT_CLAMP_RAD) | (q > self._upper + LIMIT_CLAMP_RAD)
        if outside.any():
            bad = {
                j: f"{v:.4f} not in [{lo:.4f}, {hi:.4f}]"
                for j, v, lo, hi, o in zip(self.spec.arm_joint_names, q, self._lower, self._upper, outside, strict=True)
                if o
            }
            self._reject(f"beyond the joint limits (by more than {LIMIT_CLAMP_RAD} rad): {bad}")
            return
        clamped = np.clip(q, self._lower, self._upper)
        if not np.array_equal(clamped, q):
            self.stats.commands_clamped += 1
        self._send_ros(self.ros_command(clamped, cmd.duration_s))

    def _send_ros(self, msg: Any) -> bool:
        """Send ``msg`` to the driver; False (counted as stale) while the command publisher is being replaced or
        was closed under it. Never raises that: it runs in the command topic's callback, whose error would end the
        bridge."""
        send = self._send
        if send is None:
            self.stats.commands_stale += 1
            return False
        try:
            send(msg)
        except TransportClosedError:
            self.stats.commands_stale += 1
            return False
        self.stats.commands_out += 1
        return True

    def _reject(self, why: str) -> None:
        self.stats.commands_rejected += 1
        self._logger.warning("%s: command not sent to %s: %s", self.spec.name, self.config.command, why)

    # ------------------------------------------------------------------------------------------- services

    async def serve_on(self, node: Node) -> None:
        """Take the ``command`` topic of ``node`` (the bridge's bus node) and serve ``hold`` and ``stats`` there."""
        await node.create_subscription(JointCommand, "command", self.on_command, qos=latest())
        await node.create_service(Empty, Trigger, "hold", self.srv_hold)
        await node.create_service(Empty, Data, "stats", self.srv_stats)

    def srv_hold(self, req: Empty) -> Trigger:
        if self.last_q is None:
            return Trigger(success=False, message="no joint state from the driver yet")
        if self.states_stale():
            self.stats.commands_stale += 1
            return Trigger(
                success=False,
                message=f"the newest joint state is {self.state_age_s():.2f} s old "
                f"(max_command_age_s={self.config.max_command_age_s}): not commanding a position that old",
            )
        if not self._send_ros(self.ros_command(self.last_q)):
            return Trigger(success=False, message="the command publisher is being replaced; try again")
        return Trigger(success=True, message=f"holding at {np.round(self.last_q, 4).tolist()}")

    def srv_stats(self, req: Empty) -> Data:
        return Data(value=dataclasses.asdict(self.stats))

    def log_bridged(self, namespace: str, t0: float, where: str = "") -> None:
        """Log that the bridge serves in bus namespace ``namespace``, ``where`` naming the ROS graph if need be
        (`` in ROS 2 domain 0``), ``t0`` (``time.monotonic()``) when it started to wait for the driver."""
        self._logger.info(
            "%s: bridged %s -> %s/joint_states and %s/command -> %s (%s)%s in %.2f s",
            self.spec.name,
            self.config.joint_states,
            namespace,
            namespace,
            self.config.command,
            self.config.command_type,
            where,
            time.monotonic() - t0,
        )


async def serve_bridge(
    open_bridge: Callable[..., AbstractAsyncContextManager[object]],
    config: Any,
    *,
    host: str,
    port: int,
    namespace: str | None,
    on_ready: Callable[[str], Any] | None,
    options: TransportOptions | None,
    tls: bool = False,
) -> None:
    """Run ``open_bridge(config, ...)`` (``open_ros1_bridge``, ``open_ros2_bridge``) in an own domain on
    ``tcp://host:port`` (``tls``: ``tls://host:port``, mutual TLS) until cancelled; cancelling leaves the bridge and
    the domain closed.

    The bridge's node joins with the domain's options, listening at ``host``: a peer on another machine reaches the
    arm's topics at the address it reached the domain at, with the same key or certificates. It reaches its peers
    over the domain's scheme only (no shm endpoint), as an arm's PC on the network is reached.

    Args:
        open_bridge: opens the bridge on a domain (``domain``, ``namespace``, ``transport`` and ``options``
            keywords).
        config: its config.
        host: the domain's address and the bridge node's (under tls, the certificate must name it).
        port: the domain's port (0: any free one).
        namespace: the bridge's bus namespace; None: ``/<robot>``.
        on_ready: called with the domain URI once the arm's joint states flow (the CLI prints it).
        options: the domain's and the bridge node's transport options (``auth_key``; ``insecure`` for a non-loopback
            host without one; ``tls_*`` files, else ``$UNIROS_TLS_*``); None: ``options_from_environ()``.
        tls: serve the domain on ``tls://``.

    Raises:
        ConfigError: (``tls``) the certificate, key or CA missing; a non-loopback ``tcp://`` host without a key (or
            ``insecure``).
    """
    scheme = "tls" if tls else "tcp"
    node_options = dataclasses.replace(options or options_from_environ(), bind_host=host)
    async with (
        open_domain(f"{scheme}://{host}:{port}", options=node_options) as dom,
        open_bridge(config, domain=dom, namespace=namespace, transport=scheme, options=node_options),
    ):
        if on_ready is not None:
            on_ready(dom.uri)
        await asyncio.Event().wait()  # until cancelled
