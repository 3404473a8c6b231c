"""Nodes rejoin a restarted registry: the registry killed and started again at the same URI (a new process, or the
same process), and the graph comes back from the nodes (``bus/registry_client.py``)."""

from __future__ import annotations

import asyncio
import json
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import pytest
from rig.bus_peers import BusPeer

from uniros_async.bus import open_domain, open_node
from uniros_async.bus.messages import Data, Header, JointState

REJOIN_S = 10.0
"""A bound against a hang: how long the nodes may take to find the registry back."""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def _registry_process(uri: str) -> Iterator[subprocess.Popen[str]]:
    """``rig.domain_peer registry`` at ``uri``, ready; killed and reaped on leaving."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "rig.domain_peer", "registry", "--uri", uri], stdout=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "ready"
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(10)
        assert proc.stdout is not None
        proc.stdout.close()


async def _probe(uri: str, *args: str) -> dict[str, Any]:
    """What a new process sees of the domain (``rig.domain_peer probe``)."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "rig.domain_peer", "probe", "--domain", uri, *args, stdout=subprocess.PIPE
    )
    async with asyncio.timeout(60):
        out, _ = await proc.communicate()
    assert proc.returncode == 0, out
    return dict(json.loads(out))


async def _wait_listed(node: Any, topic: str, publisher: str, service: str) -> None:
    async with asyncio.timeout(REJOIN_S):
        while True:
            try:
                topics = {t["topic"]: t["publishers"] for t in await node.list_topics()}
                services = {s["service"] for s in await node.list_services()}
            except Exception:  # noqa: BLE001 - the node's own registry connection may not be back yet
                topics, services = {}, set()
            if publisher in topics.get(topic, []) and service in services:
                return
            await asyncio.sleep(0.05)


@pytest.mark.slow
async def test_a_registry_killed_and_restarted_in_a_new_process_gets_the_graph_back() -> None:
    uri = f"tcp://127.0.0.1:{_free_port()}"
    with _registry_process(uri) as first:
        async with open_node("listener", domain=uri) as node, BusPeer(uri, "talker", "tcp"):
            await node.set_parameter("/arm/gain", 3)
            sub = await node.create_subscription(JointState, "/chatter")
            await sub.wait_for_publishers(1, timeout_s=10)
            old_id = node.domain_id
            first.send_signal(signal.SIGKILL)
            first.wait(10)
            async with asyncio.timeout(REJOIN_S):
                while not node._registry.closed:  # noqa: ASYNC110 - the node's view of its connection, polled
                    await asyncio.sleep(0.01)
            with _registry_process(uri):
                async with asyncio.timeout(REJOIN_S):
                    await node._registry.rejoined.wait()
                assert node.domain_id != old_id, "a new registry is a new domain id"
                await _wait_listed(node, "/chatter", "/talker", "/add")
                seen = await _probe(uri, "--topic", "/chatter", "--service", "/add", "--param", "/arm/gain")
                assert seen["topics"]["/chatter"] == ["/talker"], seen
                assert seen["first_message_s"]["/chatter"] is not None, seen
                assert seen["services_listed"] == {"/add": True}, seen
                assert seen["params"] == {"/arm/gain": 3}, seen
                assert {"/listener", "/talker"} <= set(seen["nodes"]), seen
                received = sub.received
                async with asyncio.timeout(5):
                    while sub.received < received + 10:  # noqa: ASYNC110 - counted arrivals, polled
                        await asyncio.sleep(0.01)
                client = node.create_client(Data, Data, "/add")
                assert (await client.call(Data(value=[1, 2]), timeout_s=5)).value == 3


async def test_a_registry_restarted_in_the_same_process_gets_the_graph_back() -> None:
    uri = f"tcp://127.0.0.1:{_free_port()}"
    domain = open_domain(uri)
    await domain.__aenter__()
    try:
        async with (
            open_node("talker", domain=uri) as talker,
            open_node("near", domain=uri) as near,  # in this process: delivered in-process
            open_node("far", domain=uri, transport="tcp") as far,  # over tcp, as from another process
        ):
            pub = await talker.create_publisher(JointState, "/chatter")
            await talker.create_service(Data, Data, "/add", lambda r: Data(value=sum(r.value)))
            await talker.set_parameter("/arm", {"gain": 3, "name": "rx200"})
            near_sub = await near.create_subscription(JointState, "/chatter")
            far_sub = await far.create_subscription(JointState, "/chatter")
            await far_sub.wait_for_publishers(1, timeout_s=5)
            seq = 0

            def publish() -> None:
                nonlocal seq
                seq += 1
                z = np.zeros(1)
                pub.publish(JointState(header=Header(seq=seq), name=("a",), position=z, velocity=z, effort=z))

            timer = talker.create_timer(0.01, publish)
            await domain.__aexit__(None, None, None)
            async with asyncio.timeout(REJOIN_S):
                while not talker._registry.closed:  # noqa: ASYNC110 - the node's view of its connection, polled
                    await asyncio.sleep(0.01)
            domain = open_domain(uri)
            await domain.__aenter__()
            async with asyncio.timeout(REJOIN_S):
                for n in (talker, near, far):
                    await n._registry.rejoined.wait()
            async with open_node("late", domain=uri) as late:
                assert late.domain_id == talker.domain_id == near.domain_id
                topics = {t["topic"]: t for t in await late.list_topics()}
                assert topics["/chatter"]["publishers"] == ["/talker"]
                assert topics["/chatter"]["subscribers"] == ["/far", "/near"]
                assert "/add" in {s["service"] for s in await late.list_services()}
                assert await late.get_parameter("/arm") == {"gain": 3, "name": "rx200"}
                late_sub = await late.create_subscription(JointState, "/chatter")
                counts = [(s, s.received) for s in (near_sub, far_sub, late_sub)]
                async with asyncio.timeout(5):
                    while any(s.received < n + 5 for s, n in counts):  # noqa: ASYNC110 - arrivals, polled
                        await asyncio.sleep(0.01)
                client = far.create_client(Data, Data, "/add")
                assert (await client.call(Data(value=[4, 5]), timeout_s=5)).value == 9
            timer.cancel()
    finally:
        await domain.__aexit__(None, None, None)


async def test_a_registry_that_answers_again_is_rejoined_without_waiting_out_a_hung_attempt() -> None:
    """While the registry is gone, something at its port accepts connections and never answers (as a cut link
    holds an attempt until its bound, ``REJOIN_ATTEMPT_S``); the real registry comes back just after an attempt
    started hanging. The node does not wait for that attempt to run out: a new one starts within ``REJOIN_MAX_S``."""
    from uniros_async.bus.registry_client import REJOIN_ATTEMPT_S, REJOIN_MAX_S

    port = _free_port()
    uri = f"tcp://127.0.0.1:{port}"
    hung: list[asyncio.StreamWriter] = []
    arrived = asyncio.Event()

    async def hold(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        hung.append(writer)  # accepted and never answered: the attempt waits for the registry's hello
        arrived.set()

    domain = open_domain(uri)
    await domain.__aenter__()
    try:
        async with open_node("arm", domain=uri) as node:
            await domain.__aexit__(None, None, None)
            mute = await asyncio.start_server(hold, "127.0.0.1", port, reuse_address=True)
            async with asyncio.timeout(REJOIN_S):
                await arrived.wait()
            arrived.clear()
            async with asyncio.timeout(REJOIN_S):
                await arrived.wait()  # a later attempt, so that the backoff is past its first short delays
            await asyncio.sleep(0.05)
            mute.close()
            domain = open_domain(uri)
            await domain.__aenter__()
            back = asyncio.get_running_loop().time()
            async with asyncio.timeout(REJOIN_S):
                await node._registry.rejoined.wait()
            took = asyncio.get_running_loop().time() - back
            # one attempt waiting out its bound would take REJOIN_ATTEMPT_S less the 0.05 s, plus the backoff
            assert took < REJOIN_MAX_S + 0.3 < REJOIN_ATTEMPT_S, took
            assert "/arm" in await node.list_nodes()
    finally:
        for writer in hung:
            writer.close()
        await domain.__aexit__(None, None, None)


async def test_a_node_whose_connection_broke_takes_its_registration_over() -> None:
    """The registry has not noticed a node's old connection end yet: the same node (its incarnation id) registering
    over a new connection takes over what it held; another node of that name is still refused."""
    from uniros_async.bus import codec
    from uniros_async.transports.base import TransportOptions, connect

    async def request(conn: Any, op: str, **kw: Any) -> dict[str, Any]:
        await conn.send(codec.encode_plain({"op": op, "id": 1, **kw}))
        while True:
            reply = codec.decode_plain(await conn.receive())
            if reply.get("id") == 1:
                return dict(reply)

    hello = {"token": "t", "host": "h", "pid": 1, "endpoints": {"tcp": "tcp://127.0.0.1:9"}}
    async with open_domain() as domain, open_node("observer", domain=domain) as observer:
        old, new, other = [await connect(domain.uri, TransportOptions()) for _ in range(3)]
        for conn in (old, new, other):
            await request(conn, "hello", **hello)
        assert (await request(old, "register_node", name="/arm", incarnation="i1"))["ok"]
        await request(old, "advertise", topic="/arm/js", type="JointState", node="/arm")
        await request(old, "advertise_service", name="/arm/hold", node="/arm", req="Data", resp="Data")
        refused = await request(other, "register_node", name="/arm", incarnation="i2")
        assert refused["kind"] == "name_conflict", refused
        assert (await request(new, "register_node", name="/arm", incarnation="i1"))["ok"]
        assert (await request(new, "advertise_service", name="/arm/hold", node="/arm", req="Data", resp="Data"))["ok"]
        await old.aclose()  # the old connection ends: the node, now held by the new one, stays
        await asyncio.sleep(0.2)
        assert "/arm" in await observer.list_nodes()
        topics = {t["topic"]: t for t in await observer.list_topics()}
        assert topics["/arm/js"]["publishers"] == ["/arm"]
        assert [s["service"] for s in await observer.list_services()] == ["/arm/hold"]
        await new.aclose()  # and when that one ends, everything of the node goes
        await asyncio.sleep(0.2)
        assert "/arm" not in await observer.list_nodes()
        assert await observer.list_services() == []
        await other.aclose()


@pytest.mark.slow
async def test_a_subscription_reconnects_to_a_publisher_that_comes_back() -> None:
    """The talker's process killed (the registry drops it), then a new talker process of the same name: the same
    subscription reads from it, with no call of ours."""
    async with open_domain() as domain, open_node("listener", domain=domain, transport="tcp") as node:
        sub = await node.create_subscription(JointState, "/chatter")
        first = BusPeer(domain.uri, "talker", "tcp")
        async with first:
            await sub.wait_for_publishers(1, timeout_s=10)
            async with asyncio.timeout(REJOIN_S):
                while (await sub.receive()).header.seq <= 200:  # the first talker's seq past what a new one starts at
                    pass
            first.kill()
            async with asyncio.timeout(REJOIN_S):
                while sub.publisher_count:  # noqa: ASYNC110 - the reader's connection, polled
                    await asyncio.sleep(0.02)
        async with BusPeer(domain.uri, "talker", "tcp"):
            async with asyncio.timeout(REJOIN_S):
                while (await sub.receive()).header.seq > 100:  # a message of the new talker: its seq starts from 1
                    pass
            assert sub.publisher_count == 1
