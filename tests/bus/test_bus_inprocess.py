"""The bus within one process: domains, names, pub/sub with both QoS, timers, services, parameters."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from uniros_async.bus import latest, open_domain, open_node, reliable
from uniros_async.bus.messages import Data, Empty, Header, JointState, Pose, Text, Trigger
from uniros_async.errors import CodecError, ConfigError, DomainError, NameConflictError, ServiceError

NAMES = ("a", "b", "c")


def js(i: int) -> JointState:
    return JointState(
        header=Header(stamp_ns=i, seq=i),
        name=NAMES,
        position=np.full(3, float(i)),
        velocity=np.zeros(3),
        effort=np.zeros(3),
    )


@pytest.fixture(params=["memory://", "tcp://127.0.0.1:0"])
async def domain(request):  # type: ignore[no-untyped-def]
    async with open_domain(request.param) as d:
        yield d


async def test_in_process_subscriber_gets_the_object_itself(domain) -> None:  # type: ignore[no-untyped-def]
    async with open_node("talker", domain=domain) as a, open_node("listener", domain=domain) as b:
        pub = await a.create_publisher(JointState, "/rx200/joint_states")
        sub = await b.create_subscription(JointState, "/rx200/joint_states", qos=reliable(10))
        msg = js(1)
        pub.publish(msg)
        async with asyncio.timeout(2):
            got = await sub.receive()
        assert got is msg
        assert sub.latest() is msg


async def test_latest_keeps_only_newest_reliable_keeps_order(domain) -> None:  # type: ignore[no-untyped-def]
    async with open_node("n", domain=domain) as node:
        pub = await node.create_publisher(JointState, "js")
        last = await node.create_subscription(JointState, "js", qos=latest())
        every = await node.create_subscription(JointState, "js", qos=reliable(5))
        for i in range(8):
            pub.publish(js(i))
        async with asyncio.timeout(2):
            assert (await last.receive()).header.seq == 7
            seqs = [(await every.receive()).header.seq for _ in range(5)]
        assert seqs == [3, 4, 5, 6, 7], "reliable(5) keeps the newest 5 in order"
        assert every.dropped == 3 and last.dropped == 0
        assert every.received == 8


async def test_callbacks_and_async_iteration(domain) -> None:  # type: ignore[no-untyped-def]
    got: list[int] = []
    done = asyncio.Event()

    async def on_msg(m: JointState) -> None:
        got.append(m.header.seq)
        if len(got) == 3:
            done.set()

    async with open_node("n", domain=domain) as node:
        pub = await node.create_publisher(JointState, "js", qos=reliable(10))
        await node.create_subscription(JointState, "js", on_msg, qos=reliable(10))
        it = await node.create_subscription(JointState, "js", qos=reliable(10))
        for i in range(3):
            pub.publish(js(i))
        async with asyncio.timeout(2):
            await done.wait()
            seen = []
            async for m in it:
                seen.append(m.header.seq)
                if len(seen) == 3:
                    break
        assert got == [0, 1, 2] and seen == [0, 1, 2]


async def test_namespaces_resolve_and_isolate(domain) -> None:  # type: ignore[no-untyped-def]
    async with (
        open_node("env", domain=domain, namespace="/rx200_1") as n1,
        open_node("env", domain=domain, namespace="/rx200_2") as n2,
    ):
        assert n1.name == "/rx200_1/env" and n1.resolve("joint_states") == "/rx200_1/joint_states"
        assert n1.resolve("~/status") == "/rx200_1/env/status" and n1.resolve("/clock") == "/clock"
        p1 = await n1.create_publisher(JointState, "joint_states")
        s2 = await n2.create_subscription(JointState, "joint_states")
        p1.publish(js(1))
        await asyncio.sleep(0.05)
        assert s2.latest() is None, "a robot in another namespace must not see this one's topic"
        assert "/rx200_1/env" in await n1.list_nodes() and "/rx200_2/env" in await n1.list_nodes()


async def test_domains_do_not_cross_talk() -> None:
    async with open_domain() as d1, open_domain() as d2:
        assert d1.uri != d2.uri
        async with open_node("n", domain=d1) as a, open_node("n", domain=d2) as b:
            pa = await a.create_publisher(Text, "/chatter")
            sb = await b.create_subscription(Text, "/chatter")
            pa.publish(Text(data="hello d1"))
            await asyncio.sleep(0.05)
            assert sb.latest() is None
            assert await a.list_nodes() == ["/n"] and await b.list_nodes() == ["/n"]


async def test_name_conflicts_and_type_mismatch(domain) -> None:  # type: ignore[no-untyped-def]
    async with open_node("dup", domain=domain) as a:
        with pytest.raises(NameConflictError, match="dup"):
            async with open_node("dup", domain=domain):
                pass
        await a.create_publisher(JointState, "/t")
        with pytest.raises(DomainError, match="carries JointState, not Pose"):
            await a.create_subscription(Pose, "/t")
        pub = await a.create_publisher(JointState, "/t2")
        with pytest.raises(CodecError, match="expected JointState, got Text"):
            pub.publish(Text(data="x"))  # type: ignore[arg-type]


@pytest.mark.serial  # holds a timer to its deadlines
async def test_timer_fires_at_absolute_deadlines(domain) -> None:  # type: ignore[no-untyped-def]
    """The deadlines are ``start + k * period`` whatever the host's load: a late fire delays neither the next
    deadline nor the grid (no drift), and every deadline skipped after a late fire is counted in ``overruns``.
    How late the fires are is the host's, measured by ``uniros bench timers``, not asserted here."""
    period_ns = 20_000_000
    n = 25
    async with open_node("n", domain=domain) as node:
        start_ns = node.now_ns() + period_ns
        done = asyncio.Event()
        overruns_at_fire: list[int] = []

        def tick() -> None:
            overruns_at_fire.append(t.overruns)
            if len(overruns_at_fire) == 5:
                time.sleep(0.05)  # a stall of the loop, as a loaded host makes: two deadlines pass during it
            if len(overruns_at_fire) == n:
                done.set()

        t = node.create_timer(period_ns / 1e9, tick, start_ns=start_ns)
        async with asyncio.timeout(30):
            await done.wait()
        t.cancel()
        fires = list(t.fire_times_ns)[:n]
        deadlines = list(t.deadlines_ns)[:n]
    assert deadlines[0] == start_ns
    # on the absolute grid: deadline k is start + (k + deadlines skipped before it) periods, exactly
    assert [(d - start_ns) for d in deadlines] == [(k + overruns_at_fire[k]) * period_ns for k in range(n)]
    assert all(f >= d for f, d in zip(fires, deadlines, strict=True)), "a timer never fires before its deadline"
    # a skipped deadline is skipped, not fired late in a burst: each deadline lies after the previous fire
    assert all(d > f for f, d in zip(fires, deadlines[1:], strict=False))
    assert overruns_at_fire[5] >= 2, overruns_at_fire


async def test_timer_overruns_are_counted_and_skipped(domain) -> None:  # type: ignore[no-untyped-def]
    async with open_node("n", domain=domain) as node:
        calls = 0

        async def slow() -> None:
            nonlocal calls
            calls += 1
            if calls == 2:
                await asyncio.sleep(0.055)  # misses two or three 20 ms deadlines

        t = node.create_timer(0.02, slow)
        await asyncio.sleep(0.3)
        t.cancel()
    assert t.overruns >= 2
    deadlines = list(t.deadlines_ns)
    assert all((b - a) % 20_000_000 == 0 for a, b in zip(deadlines, deadlines[1:], strict=False))


async def test_services_in_process_and_errors(domain) -> None:  # type: ignore[no-untyped-def]
    async with open_node("server", domain=domain) as s, open_node("client", domain=domain) as c:
        await s.create_service(Text, Text, "/echo", lambda r: Text(data=r.data.upper()))

        def broken(req: Empty) -> Trigger:
            raise RuntimeError("arm is on fire")

        await s.create_service(Empty, Trigger, "/reset", broken)
        cli = c.create_client(Text, Text, "/echo")
        assert (await cli.call(Text(data="hi"), timeout_s=2)).data == "HI"
        with pytest.raises(ServiceError, match="arm is on fire") as ei:
            await c.create_client(Empty, Trigger, "/reset").call(Empty(), timeout_s=2)
        assert "RuntimeError" in ei.value.remote_traceback
        with pytest.raises(NameConflictError):
            await c.create_service(Text, Text, "/echo", lambda r: r)
        assert (await cli.call(Text(data="still"), timeout_s=2)).data == "STILL"


async def test_service_timeout(domain) -> None:  # type: ignore[no-untyped-def]
    async with open_node("server", domain=domain) as s:

        async def stuck(req: Empty) -> Trigger:
            await asyncio.sleep(10)
            return Trigger(success=True)

        await s.create_service(Empty, Trigger, "/stuck", stuck)
        with pytest.raises(TimeoutError, match="/stuck"):
            await s.create_client(Empty, Trigger, "/stuck").call(Empty(), timeout_s=0.1)


async def test_parameters(domain, tmp_path) -> None:  # type: ignore[no-untyped-def]
    f = tmp_path / "rx200.yaml"
    f.write_text("rates:\n  env_loop_hz: 10\n  action_cycle_s: 0.8\nname: rx200\n")
    async with open_node("env", domain=domain, namespace="/rx200_1") as node:
        assert await node.load_parameters(f) == 3
        assert await node.get_parameter("rates/env_loop_hz") == 10
        assert await node.get_parameter("/rx200_1/rates") == {"env_loop_hz": 10, "action_cycle_s": 0.8}
        await node.set_parameter("~/gain", [1.0, 2.0])
        assert await node.get_parameter("/rx200_1/env/gain") == [1.0, 2.0]
        assert "/rx200_1/name" in await node.list_parameters("/rx200_1")
        with pytest.raises(KeyError, match="/rx200_1/missing"):
            await node.get_parameter("missing")
        assert await node.get_parameter("missing", default=3) == 3
        assert await node.delete_parameter("rates") == 2
        with pytest.raises(ConfigError, match="not valid YAML"):
            bad = tmp_path / "bad.yaml"
            bad.write_text("a: [1, 2\n")
            await node.load_parameters(bad)


async def test_data_message_and_node_name_checks(domain) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ConfigError, match="node name"):
        async with open_node("a/b", domain=domain):
            pass
    async with open_node("n", domain=domain) as node:
        pub = await node.create_publisher(Data, "/d")
        sub = await node.create_subscription(Data, "/d")
        pub.publish(Data(value={"x": [1, 2]}))
        async with asyncio.timeout(1):
            assert (await sub.receive()).value == {"x": [1, 2]}


async def test_missing_domain_is_a_clear_error(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.delenv("UNIROS_DOMAIN", raising=False)
    with pytest.raises(ConfigError, match="UNIROS_DOMAIN"):
        async with open_node("n"):
            pass
