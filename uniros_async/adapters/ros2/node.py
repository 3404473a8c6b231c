"""A ROS 2 participant in an asyncio process, with no ROS install: cyclonedds for the wire, rosbags for the bytes.

    async with open_ros2_node("bridge", domain_id=0) as ros:
        pub = ros.create_publisher("/rx200/commands/joint_group", "interbotix_xs_msgs/msg/JointGroupCommand")
        ros.create_subscription("/rx200/joint_states", "sensor_msgs/msg/JointState", on_state, qos=SENSOR_DATA)
        await pub.wait_for_subscribers(1, timeout_s=5.0)      # a RobotError names topic, types and domain
        pub.publish(msg)

What a ROS 2 node (rclpy over any rmw) sees is one DDS participant in domain ``ROS_DOMAIN_ID`` with endpoints on
``rt/<topic>`` of the type ``pkg::msg::dds_::Name_``, carrying ``typehash=RIHS01_...;`` in their USER_DATA as
Jazzy's rmw does, and with the QoS of the ROS profiles: ``SENSOR_DATA`` (best effort, keep last 5, volatile: the
profile to read joint states with, which matches a reliable and a best-effort publisher alike) and ``COMMANDS``
(reliable, keep last 10, volatile: ROS's default profile, what a driver's command subscription asks for).

Discovery stays on this host unless asked (``localhost_only=True``, the default, as ``ROS_AUTOMATIC_DISCOVERY_RANGE=
LOCALHOST`` does): the participant uses only the loopback interface (multicast on it, and unicast discovery to
127.0.0.1's participant ports). ``localhost_only=False`` uses cyclonedds' default interface selection, for a driver
on another machine.

Samples arrive on cyclonedds' receive thread; its data-available listener wakes the event loop
(``call_soon_threadsafe``), which takes and decodes every pending sample and calls the subscription's callback in
the loop. Before the first message goes out, ``wait_for_subscribers`` / ``wait_for_publishers`` look at the
discovered endpoints on the topic: one of another type, or of the same type with another RIHS01 hash, is a
``RobotError`` naming both types and hashes, and nothing is sent. Closing the node deletes its endpoints and, with
the process's last node, the participant; it is bounded (``close_timeout_s``). Fast DDS peers (rclpy's default)
were seen to drop our endpoints only when the participant's lease runs out, not on cyclonedds' goodbye, so the
lease is 3 s (cyclonedds' default: 10 s): a restarted env's stale endpoints leave the driver's graph that fast.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import os
import threading
import time
from collections.abc import AsyncIterator, Callable
from typing import Any

from uniros_async.adapters.ros2 import msgs
from uniros_async.errors import ConfigError, RobotError

__all__ = [
    "COMMANDS",
    "SENSOR_DATA",
    "Endpoint",
    "Ros2Node",
    "Ros2Publisher",
    "Ros2Qos",
    "Ros2Subscription",
    "domain_id_from_env",
    "open_ros2_node",
]

logger = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class Ros2Qos:
    """The QoS of one endpoint, as a ROS 2 profile sets it (durability volatile, liveliness automatic).

    Attributes:
        reliable: RELIABLE (True) or BEST_EFFORT.
        depth: KEEP_LAST depth.
    """

    reliable: bool
    depth: int


SENSOR_DATA = Ros2Qos(reliable=False, depth=5)
"""rclpy's ``qos_profile_sensor_data``: best effort, keep last 5."""
COMMANDS = Ros2Qos(reliable=True, depth=10)
"""ROS 2's default profile (``QoSProfile(depth=10)``): reliable, keep last 10; what drivers subscribe commands with."""


@dataclasses.dataclass(frozen=True)
class Endpoint:
    """A publication or subscription discovered on the ROS graph.

    Attributes:
        topic: the ROS topic (``/rx200/joint_states``).
        ros_type: its ROS type name (``sensor_msgs/msg/JointState``; the DDS name when it is not a ROS type).
        type_hash: the RIHS01 hash from its USER_DATA, or None when the peer sends none (before Jazzy).
        reliable: whether it is RELIABLE.
    """

    topic: str
    ros_type: str
    type_hash: str | None
    reliable: bool


def domain_id_from_env() -> int:
    """``ROS_DOMAIN_ID`` (0 when unset), as rclpy reads it.

    Raises:
        ConfigError: not an integer in 0..232.
    """
    raw = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not raw:
        return 0
    if not raw.isdigit() or not 0 <= int(raw) <= 232:
        raise ConfigError(f"ROS_DOMAIN_ID must be an integer in 0..232, got {raw!r}")
    return int(raw)


_LOCALHOST_CONFIG = """<CycloneDDS><Domain id="any">
<General><Interfaces><NetworkInterface address="127.0.0.1" multicast="true"/></Interfaces></General>
<Discovery><ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>32</MaxAutoParticipantIndex>
<LeaseDuration>3 s</LeaseDuration>
<Peers><Peer address="127.0.0.1"/></Peers></Discovery>
</Domain></CycloneDDS>"""


class _Participants:
    """One cyclonedds participant per (domain id) in a process, shared by the nodes in it and deleted with the last.

    cyclonedds configures a domain once per process, so two nodes on one domain id must agree on
    ``localhost_only``."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._open: dict[int, list[Any]] = {}  # domain id -> [Domain, participant, users, localhost_only]

    def acquire(self, domain_id: int, localhost_only: bool) -> Any:
        from cyclonedds.domain import Domain, DomainParticipant

        with self._lock:
            entry = self._open.get(domain_id)
            if entry is not None:
                if entry[3] != localhost_only:
                    raise ConfigError(
                        f"ROS 2 domain {domain_id} is already open in this process with localhost_only={entry[3]}; "
                        f"one process takes one discovery range per domain"
                    )
                entry[2] += 1
                return entry[1]
            domain = Domain(domain_id, _LOCALHOST_CONFIG) if localhost_only else None
            participant = DomainParticipant(domain_id)
            self._open[domain_id] = [domain, participant, 1, localhost_only]
            return participant

    def release(self, domain_id: int) -> None:
        with self._lock:
            entry = self._open[domain_id]
            entry[2] -= 1
            if entry[2] > 0:
                return
            del self._open[domain_id]
        _delete(entry[1])
        if entry[0] is not None:
            _delete(entry[0])


_PARTICIPANTS = _Participants()


def _delete(entity: Any) -> None:
    """Delete a cyclonedds entity now (its children with it), not when the garbage collector gets to it."""
    from cyclonedds.core import Entity

    ref = getattr(entity, "_ref", None)
    if ref is not None and Entity._entities.get(ref) is entity is not None:
        del Entity._entities[ref]
        entity._delete(ref)


def _qos(q: Ros2Qos, ros_type: str) -> Any:
    from cyclonedds.core import Policy, Qos
    from cyclonedds.util import duration

    rel = Policy.Reliability.Reliable(duration(seconds=1)) if q.reliable else Policy.Reliability.BestEffort
    user_data = f"typehash={msgs.type_hash(ros_type)};".encode()
    return Qos(
        rel,
        Policy.History.KeepLast(q.depth),
        Policy.Durability.Volatile,
        Policy.Userdata(data=user_data),
    )


def _endpoint(sample: Any) -> Endpoint:
    from cyclonedds.core import Policy

    topic = sample.topic_name
    topic = topic[2:] if topic.startswith("rt/") else topic
    type_hash = None
    reliable = True
    qos = sample.qos
    with contextlib.suppress(Exception):
        user = qos[Policy.Userdata].data.decode(errors="replace")
        for part in user.split(";"):
            key, _, value = part.partition("=")
            if key == "typehash" and value:
                type_hash = value
    with contextlib.suppress(Exception):
        reliable = not isinstance(qos[Policy.Reliability], Policy.Reliability.BestEffort)
    return Endpoint(topic, msgs.ros_type_from_dds(sample.type_name), type_hash, reliable)


class _Endpoint:
    """What a publisher and a subscription share: the topic, the type, the node, the peer checks."""

    kind = ""
    peer_kind = ""

    def __init__(self, node: Ros2Node, topic: str, ros_type: str, qos: Ros2Qos) -> None:
        self.node = node
        self.topic = topic
        self.ros_type = msgs.ros_type_name(ros_type)
        self.type_hash = msgs.type_hash(self.ros_type)
        self.qos = qos

    def peers(self) -> list[Endpoint]:
        """The other participants' endpoints of the opposite kind on this topic, of any type."""
        return [e for e in self.node.endpoints(self.peer_kind) if e.topic == self.topic]

    def check_peers(self) -> None:
        """Raise when a peer on the topic has another type, or the same type with another hash.

        Raises:
            RobotError: names the topic, both types and both hashes, and the domain.
        """
        for peer in self.peers():
            if peer.ros_type != self.ros_type or (peer.type_hash is not None and peer.type_hash != self.type_hash):
                raise RobotError(
                    f"ROS 2 type mismatch on {self.topic} (domain {self.node.domain_id}): a {self.peer_kind} there "
                    f"has {peer.ros_type} ({peer.type_hash or 'no type hash'}), this {self.kind} has {self.ros_type} "
                    f"({self.type_hash}); nothing is sent between them (give the driver's type, e.g. "
                    f"--command-type, or update the message definition)"
                )

    def matched(self) -> int:
        raise NotImplementedError

    async def _wait_matched(self, n: int, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            self.check_peers()
            if self.matched() >= n:
                return
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(
                    f"{self.kind} {self.topic} ({self.ros_type}, domain {self.node.domain_id}): "
                    f"{self.matched()} matched {self.peer_kind}(s) of {n} after {timeout_s} s"
                )
            await asyncio.sleep(min(0.02, left))


class Ros2Publisher(_Endpoint):
    """A DDS writer on a ROS 2 topic (``Ros2Node.create_publisher``)."""

    kind = "publisher"
    peer_kind = "subscription"

    def __init__(self, node: Ros2Node, topic: str, ros_type: str, qos: Ros2Qos) -> None:
        from cyclonedds._clayer import ddspy_write
        from cyclonedds.pub import DataWriter
        from cyclonedds.topic import Topic

        super().__init__(node, topic, ros_type, qos)
        dds_topic = Topic(node.participant, msgs.dds_topic_name(topic), msgs.idl_type(self.ros_type))
        self._writer = DataWriter(node.participant, dds_topic, qos=_qos(qos, self.ros_type))
        self._write = ddspy_write
        self._ref = self._writer._ref
        self.sent = 0

    def matched(self) -> int:
        return len(self._writer.get_matched_subscriptions())

    async def wait_for_subscribers(self, n: int = 1, timeout_s: float = 10.0) -> None:
        """Wait until ``n`` subscriptions of our type match (a type mismatch raises at once).

        Raises:
            TimeoutError: fewer within ``timeout_s`` (names topic, type and domain).
            RobotError: a subscription on the topic has another type or hash.
        """
        await self._wait_matched(n, timeout_s)

    def publish(self, msg: Any) -> None:
        """Send one message (a rosbags message of ``ros_type``)."""
        self.publish_raw(msgs.serialize(msg, self.ros_type))

    def publish_raw(self, data: bytes) -> None:
        """Send CDR bytes (with the encapsulation header) as one sample.

        Raises:
            RobotError: the node is closed or cyclonedds refused the sample.
        """
        if self.node.closed:
            raise RobotError(f"publisher {self.topic}: its ROS 2 node is closed")
        ret = self._write(self._ref, data)
        if ret < 0:
            raise RobotError(f"publisher {self.topic} ({self.ros_type}): cyclonedds refused the sample ({ret})")
        self.sent += 1


class Ros2Subscription(_Endpoint):
    """A DDS reader on a ROS 2 topic; calls its callback in the event loop (``Ros2Node.create_subscription``)."""

    kind = "subscription"
    peer_kind = "publisher"

    def __init__(
        self,
        node: Ros2Node,
        topic: str,
        ros_type: str,
        callback: Callable[[Any], None],
        qos: Ros2Qos,
        *,
        raw: bool = False,
    ) -> None:
        from cyclonedds._clayer import ddspy_take
        from cyclonedds.core import InstanceState, Listener, SampleState, ViewState
        from cyclonedds.sub import DataReader
        from cyclonedds.topic import Topic

        super().__init__(node, topic, ros_type, qos)
        self.callback = callback
        self.raw = raw
        self.received = 0
        self.dropped = 0
        self._take = ddspy_take
        self._mask = SampleState.Any | ViewState.Any | InstanceState.Any
        self._pending = False
        self._loop = node.loop
        self._listener = Listener(on_data_available=self._on_data_available)  # type: ignore[no-untyped-call]
        dds_topic = Topic(node.participant, msgs.dds_topic_name(topic), msgs.idl_type(self.ros_type))
        self._reader = DataReader(node.participant, dds_topic, qos=_qos(qos, self.ros_type), listener=self._listener)
        self._ref = self._reader._ref
        self._loop.call_soon(self._drain)  # samples that came before the listener was set

    def matched(self) -> int:
        return len(self._reader.get_matched_publications())

    async def wait_for_publishers(self, n: int = 1, timeout_s: float = 10.0) -> None:
        """Wait until ``n`` publishers of our type match (a type mismatch raises at once).

        Raises:
            TimeoutError: fewer within ``timeout_s`` (names topic, type and domain).
            RobotError: a publisher on the topic has another type or hash.
        """
        await self._wait_matched(n, timeout_s)

    def _on_data_available(self, reader: Any) -> None:  # cyclonedds' receive thread
        if self._pending or self.node.closed:
            return
        self._pending = True
        with contextlib.suppress(RuntimeError):  # the loop closed under a late sample
            self._loop.call_soon_threadsafe(self._drain)

    def _drain(self) -> None:
        self._pending = False
        if self.node.closed:
            return
        while True:
            got = self._take(self._ref, self._mask, 64)
            if isinstance(got, int) or not got:
                return
            for data, info in got:
                if not info.valid_data:
                    continue
                self.received += 1
                if self.raw:
                    self.callback(data)
                    continue
                try:
                    msg = msgs.deserialize(data, self.ros_type)
                except Exception as exc:  # a corrupt sample is dropped; the subscription keeps working
                    self.dropped += 1
                    logger.warning("subscription %s: dropped a sample: %s", self.topic, exc)
                    continue
                self.callback(msg)


class Ros2Node:
    """One ROS 2 participant's worth of endpoints for this process (built by ``open_ros2_node``)."""

    def __init__(self, name: str, domain_id: int, localhost_only: bool, loop: asyncio.AbstractEventLoop) -> None:
        self.name = name
        self.domain_id = domain_id
        self.localhost_only = localhost_only
        self.loop = loop
        self.closed = False
        self.participant = _PARTICIPANTS.acquire(domain_id, localhost_only)
        self._endpoints: list[_Endpoint] = []
        self._builtin: dict[str, Any] = {}

    def create_publisher(self, topic: str, ros_type: str, qos: Ros2Qos = COMMANDS) -> Ros2Publisher:
        """A publisher of ``ros_type`` (``pkg/msg/Name``) on the absolute ROS topic ``topic``."""
        pub = Ros2Publisher(self, topic, ros_type, qos)
        self._endpoints.append(pub)
        return pub

    def create_subscription(
        self,
        topic: str,
        ros_type: str,
        callback: Callable[[Any], None],
        qos: Ros2Qos = SENSOR_DATA,
        *,
        raw: bool = False,
    ) -> Ros2Subscription:
        """A subscription calling ``callback`` in the loop with each message (a rosbags message; with ``raw``: the
        sample's CDR bytes)."""
        sub = Ros2Subscription(self, topic, ros_type, callback, qos, raw=raw)
        self._endpoints.append(sub)
        return sub

    def endpoints(self, kind: str) -> list[Endpoint]:
        """The live ``publisher`` or ``subscription`` endpoints that other participants announced."""
        from cyclonedds.builtin import (
            BuiltinDataReader,
            BuiltinTopicDcpsPublication,
            BuiltinTopicDcpsSubscription,
        )
        from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState

        if kind not in self._builtin:
            topic = BuiltinTopicDcpsPublication if kind == "publisher" else BuiltinTopicDcpsSubscription
            reader = BuiltinDataReader(self.participant, topic)
            cond = ReadCondition(reader, SampleState.Any | ViewState.Any | InstanceState.Alive)
            self._builtin[kind] = (reader, cond)
        reader, cond = self._builtin[kind]
        me = self.participant.guid
        return [_endpoint(s) for s in reader.read(N=1024, condition=cond) if s.participant_key != me]

    def close(self) -> None:
        """Delete this node's endpoints (the participant goes with the process's last node)."""
        if self.closed:
            return
        self.closed = True
        for ep in self._endpoints:
            for attr in ("_reader", "_writer"):
                entity = getattr(ep, attr, None)
                if entity is not None:
                    _delete(entity)
        for reader, cond in self._builtin.values():
            _delete(cond)
            _delete(reader)
        _PARTICIPANTS.release(self.domain_id)


@contextlib.asynccontextmanager
async def open_ros2_node(
    name: str,
    *,
    domain_id: int | None = None,
    localhost_only: bool = True,
    close_timeout_s: float = 2.0,
) -> AsyncIterator[Ros2Node]:
    """A ROS 2 participant of ``domain_id`` (None: ``$ROS_DOMAIN_ID``, else 0) until the block ends.

    Raises:
        ConfigError: a bad domain id, or cyclonedds / rosbags missing (says what to install).
    """
    try:
        import cyclonedds  # noqa: F401
        import rosbags  # noqa: F401
    except ImportError as exc:
        raise ConfigError(
            f"the ROS 2 adapter needs cyclonedds and rosbags (pip install 'uniros-async[ros2]'): {exc}"
        ) from None
    did = domain_id_from_env() if domain_id is None else domain_id
    if not 0 <= did <= 232:
        raise ConfigError(f"a ROS 2 domain id is in 0..232, got {did}")
    loop = asyncio.get_running_loop()
    node = Ros2Node(name, did, localhost_only, loop)
    try:
        yield node
    finally:
        # deleting a participant says goodbye to its peers; off the loop and bounded, so a stuck network stack
        # cannot hold the caller's shutdown
        closing = loop.run_in_executor(None, node.close)
        try:
            await asyncio.wait_for(asyncio.shield(closing), close_timeout_s)
        except TimeoutError:
            logger.warning(
                "ROS 2 node %s: closing took over %.1f s; left to finish in the background", name, close_timeout_s
            )
