"""A ROS 1 node in pure asyncio: registers with a rosmaster, serves the slave XML-RPC API, speaks TCPROS.

No rospy in our process: the arm drivers (Interbotix rx200, Niryo Ned2, ros_control) stay ROS 1 nodes, and our envs
talk to them through this client::

    async with open_ros1_node("/uniros_bridge") as node:
        states = await node.subscribe("/rx200/joint_states", JointState)
        cmd = await node.advertise("/rx200/commands/joint_group", JointGroupCommand)
        await states.wait_for_publishers()
        cmd.publish(JointGroupCommand("arm", np.zeros(5, np.float32)))

Every task of the node belongs to the TaskGroup held open by ``open_ros1_node``; leaving the block unregisters every
topic from the master (bounded by ``timeout_s``), then closes the XML-RPC server and every TCPROS connection.

A restarted master knows nothing of the graph. The node asks the master for its pid every ``MASTER_WATCH_S``; when
the master answers again after it did not, or with another pid (a new rosmaster at the same URI), the node registers
every publication and subscription again, and each subscription connects to the publishers the master names. rospy
and roscpp register only at start, so a ROS 1 driver of theirs stays unknown to a restarted master until it is
restarted too; ours come back by themselves.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import re
from collections.abc import AsyncIterator, Callable, Coroutine
from typing import Any, TypeVar

from uniros_async.adapters.ros1 import _tcpros
from uniros_async.adapters.ros1._xmlrpc import XmlRpcServer, call_ros
from uniros_async.adapters.ros1.msgs import Ros1Message
from uniros_async.adapters.ros1.topics import (
    Ros1Publisher,
    Ros1Subscriber,
    _log_limit,
    _Publication,
    _Subscription,
    _type_mismatch,
)
from uniros_async.bus.tasks import unwrap_task_group
from uniros_async.errors import CodecError, ConfigError, RobotError, TransportClosedError
from uniros_async.transports.exposure import check_exposure

__all__ = ["DEFAULT_MASTER_URI", "Ros1Node", "Ros1Publisher", "Ros1Subscriber", "open_ros1_node"]

logger = logging.getLogger(__name__)

M = TypeVar("M", bound=Ros1Message)

DEFAULT_MASTER_URI = "http://127.0.0.1:11311/"
_NAME = re.compile(r"^/?[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*$")
_TOPIC = re.compile(r"^[~/]?[A-Za-z][A-Za-z0-9_]*(/[A-Za-z0-9_]+)*$")
MASTER_WATCH_S = 1.0
"""How often the node checks that its master is the one it registered with (see the module docstring)."""


class Ros1Node:
    """One ROS 1 node: its slave API (XML-RPC), one TCPROS server for its publications, and its subscriptions.

    Made by ``open_ros1_node``. Attributes: ``name`` (global, "/uniros_bridge"), ``master_uri``, ``uri`` (this
    node's slave API), ``timeout_s`` (bound on every call to the master or a peer).
    """

    def __init__(self, name: str, master_uri: str, host: str, timeout_s: float) -> None:
        self.name = name
        self.master_uri = master_uri
        self.host = host
        self.timeout_s = timeout_s
        self.uri = ""
        self.tcpros_port = 0
        self._tg: asyncio.TaskGroup | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._subscriptions: dict[str, _Subscription] = {}
        self._publications: dict[str, _Publication] = {}
        self._closed = False
        self._xmlrpc = XmlRpcServer(
            {
                "getBusStats": self._get_bus_stats,
                "getBusInfo": self._get_bus_info,
                "getMasterUri": lambda caller_id: [1, "", self.master_uri],
                "shutdown": self._shutdown_request,
                "getPid": lambda caller_id: [1, "", os.getpid()],
                "getSubscriptions": lambda caller_id: [1, "", self._topic_types(self._subscriptions)],
                "getPublications": lambda caller_id: [1, "", self._topic_types(self._publications)],
                "paramUpdate": lambda caller_id, key, value: [1, "", 0],
                "publisherUpdate": self._publisher_update,
                "requestTopic": self._request_topic,
            },
            self._spawn,
        )
        self._tcpros_server: asyncio.Server | None = None
        self._tcpros_writers: set[asyncio.StreamWriter] = set()

    # ------------------------------------------------------------------------------------------ public API

    def resolve(self, topic: str) -> str:
        """The global name of ``topic``: relative names resolve in the node's namespace, ``~x`` under the node."""
        if not _TOPIC.match(topic):
            raise ConfigError(f"{topic!r} is not a valid ROS 1 topic name (letters, digits, _ and /)")
        if topic.startswith("/"):
            return topic
        if topic.startswith("~"):
            return f"{self.name}/{topic[1:].lstrip('/')}"
        return f"{self.name.rsplit('/', 1)[0]}/{topic}"

    async def subscribe(
        self, topic: str, msg_type: type[M], callback: Callable[[M], None] | None = None
    ) -> Ros1Subscriber[M]:
        """Subscribe to ``topic`` and connect to every publisher the master names (now and later).

        ``callback`` runs in the event loop for each message; its exceptions are logged, not raised.

        Raises:
            ConfigError: a bad topic name, or the node already subscribes to it with another type.
            RobotError: the master refused or did not answer within ``timeout_s``.
        """
        topic = self._check_open(topic, msg_type)
        sub = self._subscriptions.get(topic)
        if sub is not None:
            if sub.msg_type is not msg_type:
                raise ConfigError(f"{topic}: already subscribed as {sub.msg_type._type}, not {msg_type._type}")
            handle = Ros1Subscriber(sub, msg_type, callback)
            sub.handles.append(handle)
            return handle
        sub = _Subscription(self, topic, msg_type)
        handle = Ros1Subscriber(sub, msg_type, callback)
        sub.handles.append(handle)
        self._subscriptions[topic] = sub  # before registering: the master's publisherUpdate may come first
        try:
            publishers = await self._master("registerSubscriber", topic, msg_type._type, self.uri)
        except BaseException:
            del self._subscriptions[topic]
            raise
        sub.update_publishers(publishers)
        return handle

    async def advertise(
        self, topic: str, msg_type: type[M], *, latch: bool = False, queue_size: int = 10
    ) -> Ros1Publisher[M]:
        """Publish ``topic``: register with the master and accept subscribers on this node's TCPROS port.

        Args:
            topic: the topic name.
            msg_type: the message class.
            latch: send the last message to every new subscriber at once (rospy ``latch=True``).
            queue_size: frames kept per subscriber that reads slower than we publish; older ones are dropped.

        Raises:
            ConfigError: a bad topic name or queue_size, or the node already publishes it with another type/latch.
            RobotError: the master refused or did not answer within ``timeout_s``.
        """
        topic = self._check_open(topic, msg_type)
        if queue_size < 1:
            raise ConfigError(f"queue_size={queue_size}: expected at least 1")
        pub = self._publications.get(topic)
        if pub is not None:
            if pub.msg_type is not msg_type or pub.latch != latch:
                raise ConfigError(
                    f"{topic}: already advertised as {pub.msg_type._type} latch={pub.latch}, "
                    f"not {msg_type._type} latch={latch}"
                )
            pub.handles += 1
            return Ros1Publisher(pub, msg_type)
        pub = _Publication(self, topic, msg_type, latch, queue_size)
        pub.handles = 1
        self._publications[topic] = pub  # before registering: subscribers may call requestTopic at once
        try:
            await self._master("registerPublisher", topic, msg_type._type, self.uri)
        except BaseException:
            del self._publications[topic]
            raise
        return Ros1Publisher(pub, msg_type)

    # ------------------------------------------------------------------------------------------ internals

    def _check_open(self, topic: str, msg_type: type[Ros1Message]) -> str:
        if self._closed:
            raise TransportClosedError(f"the ROS 1 node {self.name} is closed")
        if not (isinstance(msg_type, type) and issubclass(msg_type, Ros1Message)):
            raise ConfigError(f"expected a ROS 1 message class (from adapters.ros1.msgs), got {msg_type!r}")
        return self.resolve(topic)

    def _spawn(self, coro: Coroutine[Any, Any, None], *, name: str | None = None) -> asyncio.Task[None]:
        assert self._tg is not None
        task = self._tg.create_task(coro, name=name)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    async def _master(self, method: str, *args: Any) -> Any:
        try:
            code, status, value = await call_ros(self.master_uri, method, self.name, *args, timeout_s=self.timeout_s)
        except (OSError, TimeoutError) as exc:
            raise RobotError(
                f"ROS master at {self.master_uri} did not answer {method}{args[:1]} within {self.timeout_s} s "
                f"({exc!r}); is roscore still running?"
            ) from exc
        if code != 1:
            raise RobotError(f"ROS master at {self.master_uri} refused {method}{args[:2]}: {status}")
        return value

    async def _watch_master(self, pid: Any) -> None:
        """Register everything again with a master that answers after a silence, or with another pid."""
        lost = False
        while True:
            await asyncio.sleep(MASTER_WATCH_S)
            try:
                _, _, now = await call_ros(
                    self.master_uri, "getPid", self.name, timeout_s=min(self.timeout_s, MASTER_WATCH_S)
                )
            except (OSError, TimeoutError) as exc:
                if not lost:
                    logger.warning(
                        "ROS master at %s does not answer (%r); registering again when it does", self.master_uri, exc
                    )
                lost = True
                continue
            if lost or now != pid:
                try:
                    await self._register_all()
                except RobotError as exc:
                    logger.warning("registering again with the ROS master at %s failed: %s", self.master_uri, exc)
                    lost = True
                    continue
                logger.warning(
                    "registered %s again with the ROS master at %s (pid %s)", self.name, self.master_uri, now
                )
                lost, pid = False, now

    async def _register_all(self) -> None:
        for topic, pub in list(self._publications.items()):
            await self._master("registerPublisher", topic, pub.msg_type._type, self.uri)
        for topic, sub in list(self._subscriptions.items()):
            sub.update_publishers(await self._master("registerSubscriber", topic, sub.msg_type._type, self.uri))

    async def _start(self) -> None:
        try:
            _, _, pid = await call_ros(self.master_uri, "getPid", self.name, timeout_s=self.timeout_s)
        except (OSError, TimeoutError) as exc:
            raise RobotError(
                f"cannot reach the ROS master at {self.master_uri} ({exc!r}): start roscore (or rosmaster --core) "
                "there, or set ROS_MASTER_URI (or master_uri=) to the running master"
            ) from exc
        port = await self._xmlrpc.start(self.host)
        self.uri = f"http://{self.host}:{port}/"
        self._tcpros_server = await asyncio.start_server(self._on_tcpros, self.host, 0)
        self.tcpros_port = int(self._tcpros_server.sockets[0].getsockname()[1])
        logger.info(
            "ROS 1 node %s at %s (TCPROS port %d), master %s", self.name, self.uri, self.tcpros_port, self.master_uri
        )
        self._spawn(self._watch_master(pid), name=f"ros1 {self.name} master watch")

    async def _aclose(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            async with asyncio.timeout(self.timeout_s), asyncio.TaskGroup() as tg:
                for topic in self._subscriptions:
                    tg.create_task(self._unregister("unregisterSubscriber", topic))
                for topic in self._publications:
                    tg.create_task(self._unregister("unregisterPublisher", topic))
        except TimeoutError:
            logger.warning(
                "ROS master at %s did not confirm unregistering %s within %s s; it may list stale topics",
                self.master_uri,
                self.name,
                self.timeout_s,
            )
        finally:
            # Synchronous, so it runs even when the close itself is cancelled.
            for sub in self._subscriptions.values():
                sub.close()
            for pub in self._publications.values():
                pub.close()
            self._xmlrpc.close()
            if self._tcpros_server is not None:
                self._tcpros_server.close()
            for writer in self._tcpros_writers:
                writer.close()
            for task in list(self._tasks):
                task.cancel()

    async def _unregister(self, method: str, topic: str) -> None:
        try:
            await call_ros(self.master_uri, method, self.name, topic, self.uri, timeout_s=self.timeout_s)
        except (OSError, TimeoutError) as exc:
            logger.warning("%s %s at %s failed: %r", method, topic, self.master_uri, exc)

    # -------------------------------------------------------------------------------------- TCPROS server

    def _on_tcpros(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self._closed:
            writer.close()
            return
        self._tcpros_writers.add(writer)
        self._spawn(self._serve_tcpros(reader, writer), name=f"ros1 {self.name} tcpros connection")

    def _check_subscriber(self, header: dict[str, str]) -> str | None:
        """Why a subscriber's connection header is refused (the TCPROS ``error=`` text), or None."""
        if "service" in header:
            return f"{self.name} serves no ROS 1 services (asked for {header['service']})"
        topic = header.get("topic", "")
        pub = self._publications.get(topic)
        if pub is None:
            return f"{self.name} does not publish [{topic}]"
        md5 = header.get("md5sum", "")
        ours = pub.msg_type
        if md5 not in ("*", ours._md5sum):
            callerid = header.get("callerid", "?")
            if _log_limit(f"mismatch {self.name}"):
                logger.warning(_type_mismatch(topic, f"subscriber {callerid}", header.get("type", ""), md5, ours))
            # rospy's own words (rospy/impl/tcpros_pubsub.py), so ROS users recognise the failure
            if header.get("type", ours._type) != ours._type:
                return f"topic types do not match: [{header['type']}] vs. [{ours._type}]"
            return (
                f"Client [{callerid}] wants topic [{topic}] to have datatype/md5sum [{header.get('type', '')}/{md5}], "
                f"but our version has [{ours._type}/{ours._md5sum}] Dropping connection."
            )
        return None

    async def _serve_tcpros(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        try:
            _tcpros.tune_socket(writer)
            try:
                async with asyncio.timeout(self.timeout_s):
                    header = await _tcpros.read_header(reader)
            except (OSError, TimeoutError, asyncio.IncompleteReadError, CodecError) as exc:
                if _log_limit(f"tcpros header {self.name}"):
                    logger.info("TCPROS connection from %s sent no valid header: %r", peer, exc)
                return
            error = self._check_subscriber(header)
            if error is not None:
                writer.write(_tcpros.encode_header({"error": error}))
                async with asyncio.timeout(self.timeout_s):
                    await writer.drain()
                return
            pub = self._publications[header["topic"]]
            writer.write(_tcpros.encode_header(pub.header()))
            if header.get("probe") == "1":  # rostopic's probe: wants the header only
                return
            await pub.serve(header.get("callerid", str(peer)), reader, writer)
        except (OSError, TimeoutError) as exc:
            logger.debug("TCPROS connection from %s ended: %r", peer, exc)
        except Exception:  # a peer's bad input must not take the node (and its TaskGroup) down
            if _log_limit(f"tcpros failed {self.name}"):
                logger.exception("TCPROS connection from %s failed; dropped it", peer)
        finally:
            self._tcpros_writers.discard(writer)
            writer.close()

    # ------------------------------------------------------------------------------------------ slave API

    def _request_topic(self, caller_id: str, topic: str, protocols: list[Any]) -> list[Any]:
        if topic not in self._publications or self._closed:
            return [-1, f"Not a publisher of [{topic}]", []]
        if not any(isinstance(p, list) and p[:1] == ["TCPROS"] for p in protocols):
            return [0, "no supported protocol implementations (uniros_async offers TCPROS only)", []]
        return [1, f"ready on {self.host}:{self.tcpros_port}", ["TCPROS", self.host, self.tcpros_port]]

    def _publisher_update(self, caller_id: str, topic: str, publishers: list[str]) -> list[Any]:
        if not isinstance(publishers, list):
            return [-1, f"publishers must be a list of URIs, got {type(publishers).__name__}", 0]
        sub = self._subscriptions.get(topic)
        if sub is not None:
            sub.update_publishers(publishers)
        return [1, "", 0]

    def _shutdown_request(self, caller_id: str, msg: str = "") -> list[Any]:
        # The master sends this when another node registers our name. We keep running: the caller owns our life.
        if _log_limit(f"shutdown {self.name}"):
            logger.warning("%s: %s asked this ROS 1 node to shut down (%s); ignoring", self.name, caller_id, msg)
        return [1, "", 0]

    @staticmethod
    def _topic_types(topics: dict[str, Any]) -> list[list[str]]:
        return [[topic, t.msg_type._type] for topic, t in topics.items()]

    def _get_bus_stats(self, caller_id: str) -> list[Any]:
        pub_stats = [
            [topic, sum(link.bytes for link in pub.links), [[lk.id, lk.bytes, lk.count, True] for lk in pub.links]]
            for topic, pub in self._publications.items()
        ]
        sub_stats = [
            [topic, [[c.id, c.bytes, -1, True] for c in sub.connected.values()]]
            for topic, sub in self._subscriptions.items()
        ]
        return [1, "", [pub_stats, sub_stats, [0, 0, 0]]]

    def _get_bus_info(self, caller_id: str) -> list[Any]:
        info: list[list[Any]] = []
        for topic, sub in self._subscriptions.items():
            for c in sub.connected.values():
                info.append([c.id, c.uri, "i", "TCPROS", topic, True, f"TCPROS connection to [{c.callerid}]"])
        for topic, pub in self._publications.items():
            for lk in pub.links:
                info.append([lk.id, lk.callerid, "o", "TCPROS", topic, True, f"TCPROS connection to [{lk.callerid}]"])
        return [1, "", info]


@contextlib.asynccontextmanager
async def open_ros1_node(
    name: str,
    *,
    master_uri: str | None = None,
    host: str = "127.0.0.1",
    timeout_s: float = 5.0,
    insecure: bool = False,
) -> AsyncIterator[Ros1Node]:
    """Run a ROS 1 node called ``name`` for the duration of the block.

    Args:
        name: the node name ("/uniros_bridge"; a leading "/" is added if missing). The master shuts down an older
            node of the same name; two of our nodes on one master need different names.
        master_uri: the rosmaster's URI; default ``$ROS_MASTER_URI``, else ``http://127.0.0.1:11311/``.
        host: the address this node listens on and tells peers (must be reachable by the driver's machine).
        timeout_s: bound on every call to the master or a peer, and on unregistering at close.
        insecure: allow a ``host`` beyond loopback. ROS 1 cannot authenticate peers: whoever reaches the node's
            XML-RPC and TCPROS ports may publish to its subscribers and read its topics.

    Raises:
        RobotError: the master is unreachable (the message names the URI and how to start one).
        ConfigError: ``name`` is not a valid ROS 1 node name, or ``host`` is beyond loopback without ``insecure``.

    Leaving the block (also by cancellation) unregisters every topic from the master within ``timeout_s`` (a dead
    master costs at most that), then closes the XML-RPC server and every TCPROS connection.
    """
    if not _NAME.match(name):
        raise ConfigError(f"{name!r} is not a valid ROS 1 node name (letters, digits, _ and /, e.g. /uniros_bridge)")
    if timeout_s <= 0:
        raise ConfigError(f"timeout_s={timeout_s}: expected > 0")
    check_exposure(
        f"{host} (ROS 1 node {name}: XML-RPC and TCPROS)",
        host,
        authenticated=False,
        insecure=insecure,
        how="ROS 1 cannot authenticate its peers: keep the ROS graph on a trusted network and say so with "
        "insecure=True (--insecure, or insecure: true in the env's ros1 settings)",
    )
    uri = master_uri or os.environ.get("ROS_MASTER_URI") or DEFAULT_MASTER_URI
    node = Ros1Node(name if name.startswith("/") else f"/{name}", uri, host, timeout_s)
    async with unwrap_task_group() as tg:
        node._tg = tg
        try:
            await node._start()
            yield node
        finally:
            await node._aclose()
