"""The transit estimate starts afresh when the arm's registry restarts (a new domain id), on a real tcp domain.

The env's node rejoins a restarted registry by itself and keeps its subscription (``bus/registry_client.py``), so a
new subscription no longer marks a new arm: the domain id the node rejoined under does. Here the registry is stopped
and started again at the same URI in this process, and the arm after it stamps its states on a clock 5 s behind the
one before (a new arm process on another host): an estimate that kept the old arm's quickest state would judge every
new state 5 s old.
"""

from __future__ import annotations

import asyncio
import socket
import time

import numpy as np

from uniros_async.bus import open_domain, open_node
from uniros_async.bus.messages import Header, JointState
from uniros_async.bus.pubsub import Publisher, Subscription
from uniros_async.envs.transit import StateTransit

S = 1_000_000_000
REJOIN_S = 10.0
"""A bound against a hang: how long the nodes may take to find the registry back."""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _state(offset_ns: int) -> JointState:
    z = np.zeros(1)
    return JointState(
        header=Header(stamp_ns=time.monotonic_ns() + offset_ns), name=("a",), position=z, velocity=z, effort=z
    )


async def _publish_and_follow(
    pub: Publisher[JointState], sub: Subscription[JointState], transits: list[tuple[StateTransit, str]], offset_ns: int
) -> None:
    """Publish states stamped on a clock ``offset_ns`` from the env's until one arrives (the subscription may be
    reconnecting to the publisher), then let each transit follow it under its domain id."""
    stamps: set[int] = set()
    async with asyncio.timeout(5):
        while True:
            js = _state(offset_ns)
            stamps.add(js.header.stamp_ns)
            pub.publish(js)
            await asyncio.sleep(0.02)
            latest = sub.latest()
            if latest is not None and latest.header.stamp_ns in stamps:
                break
    for transit, domain_id in transits:
        transit.follow(sub, domain_id)


async def test_a_restarted_registry_starts_the_transit_estimate_afresh() -> None:
    uri = f"tcp://127.0.0.1:{_free_port()}"
    domain = open_domain(uri)
    await domain.__aenter__()
    try:
        async with (
            open_node("arm", domain=uri) as arm,
            open_node("env", domain=uri, transport="tcp") as env,  # over tcp, as from another process
        ):
            pub = await arm.create_publisher(JointState, "joint_states")
            sub = await env.create_subscription(JointState, "joint_states")
            await sub.wait_for_publishers(1, timeout_s=5)
            fresh, kept = StateTransit(stall_s=1000.0), StateTransit(stall_s=1000.0)
            first_id = env.domain_id
            for _ in range(3):  # the first arm: its clock 100 s ahead of the env's
                await _publish_and_follow(pub, sub, [(fresh, env.domain_id), (kept, first_id)], 100 * S)
            await domain.__aexit__(None, None, None)
            async with asyncio.timeout(REJOIN_S):
                while not env._registry.closed:  # noqa: ASYNC110 - the node's view of its connection, polled
                    await asyncio.sleep(0.01)
            domain = open_domain(uri)
            await domain.__aenter__()
            async with asyncio.timeout(REJOIN_S):
                for node in (arm, env):
                    await node._registry.rejoined.wait()
            assert env.domain_id != first_id
            # the env's first look after the rejoin: the state it holds (the old arm's) is not observed
            fresh.follow(sub, env.domain_id)
            assert fresh.transit_ns(sub.latest(), sub.latest_recv_ns) == 0
            for _ in range(3):  # the new arm: its clock 5 s behind the first's
                await _publish_and_follow(pub, sub, [(fresh, env.domain_id), (kept, first_id)], 95 * S)
            js = sub.latest()
            assert js is not None
            assert fresh.transit_ns(js, sub.latest_recv_ns) < S // 2  # judged by the new arm's states alone
            assert kept.transit_ns(js, sub.latest_recv_ns) > 4 * S  # the old arm's floor: 5 s too old
    finally:
        await domain.__aexit__(None, None, None)
