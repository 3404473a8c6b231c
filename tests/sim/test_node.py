"""ServoSimNode in the caller's process: topics, rates, services, markers, the emulated arm (real bus, real MuJoCo)."""

from __future__ import annotations

import asyncio
import collections
import statistics
import time

import numpy as np
import pytest

from uniros_async.bus import open_domain, open_node, reliable
from uniros_async.bus.messages import Data, Empty, Header, JointCommand, JointState, Marker, Text, Trigger
from uniros_async.errors import SimulationError
from uniros_async.sim.emulated import EmulationConfig, LatencyModel
from uniros_async.sim.node import open_servo_sim
from uniros_async.sim_clock import SimClock

GOALS = {"rx200": [0.5, 0.3, -0.4, 0.6, 1.0], "ned2": [0.5, -0.3, 0.4, 0.6, -0.5, 1.0]}


def command(q, duration_s: float = 0.0) -> JointCommand:  # type: ignore[no-untyped-def]
    return JointCommand(header=Header(), position=np.asarray(q, dtype=np.float64), duration_s=duration_s)


@pytest.mark.parametrize("robot", ["rx200", "ned2"])
async def test_command_over_the_bus_reaches_target(robot: str) -> None:
    async with open_domain("memory://") as domain:
        clock = SimClock(time_scale=None)
        async with (
            open_servo_sim(robot, domain=domain, clock=clock) as sim_node,
            open_node("env", domain=domain, clock=clock) as env,
        ):
            assert sim_node.topic("joint_states") == f"/{robot}/joint_states"
            states = await env.create_subscription(JointState, f"/{robot}/joint_states")
            pub = await env.create_publisher(JointCommand, f"/{robot}/command")
            await clock.sleep(0.05)
            pub.publish(command(GOALS[robot]))
            await clock.sleep(2.5)
            state = states.latest()
    assert state is not None
    n = len(GOALS[robot])
    assert np.abs(state.position[:n] - GOALS[robot]).max() < 0.03
    assert sim_node.stats.commands == 1


@pytest.mark.slow
@pytest.mark.serial  # counts messages against the hardware rate
@pytest.mark.parametrize(("robot", "rate_hz"), [("rx200", 10.0), ("ned2", 25.0)])
async def test_joint_states_arrive_at_the_hardware_rate(robot: str, rate_hz: float) -> None:
    """Wall clock. One joint state per tick of the node's timer, and the ticks' deadlines are the multiples of the
    hardware period (absolute, so a tick a busy machine delays shifts no later one). How late the ticks are is the
    host's, printed only (``uniros bench timers`` measures it)."""
    period_ns = round(1e9 / rate_hz)
    n = 8
    async with open_domain("memory://") as domain:
        async with open_servo_sim(robot, domain=domain) as sim_node, open_node("env", domain=domain) as env:
            states = await env.create_subscription(JointState, f"/{robot}/joint_states", qos=reliable(1000))
            stamps: list[int] = []
            async with asyncio.timeout(30):
                while len(stamps) < n:
                    stamps.append((await states.receive()).header.stamp_ns)
            deadlines = list(sim_node.timer.deadlines_ns)
            fires = list(sim_node.timer.fire_times_ns)
    assert sim_node.timer.period_ns == period_ns
    assert all(d % period_ns == 0 for d in deadlines), "the ticks' deadlines are on the clock's grid of the period"
    # one state per tick, none lost: each state is stamped during its own tick, after that tick's fire and before
    # the next one's, and the states belong to consecutive ticks
    first = max(i for i, f in enumerate(fires) if f <= stamps[0])
    for k, stamp in enumerate(stamps):
        assert fires[first + k] <= stamp, (k, stamps, fires)
        assert first + k + 1 == len(fires) or stamp < fires[first + k + 1], (k, stamps, fires)
    late_ms = [(f - d) / 1e6 for f, d in zip(fires, deadlines, strict=True)]
    print(
        f"\n{robot} joint_states: ticks late by median {statistics.median(late_ms):.3f} ms, max {max(late_ms):.3f} ms"
    )


async def test_env_polling_at_50hz_sees_each_state_repeated() -> None:
    """As on the real arm: an env loop faster than the hardware loop reads the same joint state several times."""
    async with open_domain("memory://") as domain:
        clock = SimClock(time_scale=None)
        async with (
            open_servo_sim("rx200", domain=domain, clock=clock),
            open_node("env", domain=domain, clock=clock) as env,
        ):
            states = await env.create_subscription(JointState, "/rx200/joint_states")
            seen: list[int] = []

            def poll() -> None:
                msg = states.latest()
                seen.append(msg.header.seq if msg is not None else -1)

            timer = env.create_timer(0.02, poll, start_ns=clock.now_ns() + 10_000_000)
            await clock.sleep(2.0)
            timer.cancel()
    counts = collections.Counter(s for s in seen if s >= 0)
    assert len(counts) >= 19
    assert all(c == 5 for c in list(counts.values())[1:-1]), f"each 10 Hz state is read 5 times at 50 Hz: {counts}"


async def test_services_hold_stop_mode_reset_stats() -> None:
    async with open_domain("memory://") as domain:
        clock = SimClock(time_scale=None)
        async with (
            open_servo_sim("ned2", domain=domain, clock=clock) as sim_node,
            open_node("env", domain=domain, clock=clock) as env,
        ):
            pub = await env.create_publisher(JointCommand, "/ned2/command")

            def client(req, resp, name):  # type: ignore[no-untyped-def]
                return env.create_client(req, resp, f"/ned2/{name}")

            hold, stop = client(Empty, Trigger, "hold"), client(Empty, Trigger, "stop")
            set_mode, reset = client(Text, Trigger, "set_mode"), client(Data, Trigger, "reset")
            stats = client(Empty, Data, "stats")
            r = await hold.call(Empty())
            assert r.success and "holding" in r.message and sim_node.sim.mode == "hold"
            pub.publish(command(GOALS["ned2"]))
            await clock.sleep(0.2)
            assert (await stats.call(Empty())).value["ignored"] == 1
            bad = await set_mode.call(Text(data="dance"))
            assert not bad.success and "expected one of" in bad.message
            assert (await set_mode.call(Text(data="position"))).success
            pub.publish(command(GOALS["ned2"]))
            await clock.sleep(0.5)
            assert (await stop.call(Empty())).success and sim_node.sim.mode == "stop"
            assert (await reset.call(Data(value={"q": [0.1, 0, 0, 0, 0, 0]}))).success
            assert sim_node.sim.mode == "position" and sim_node.sim.qpos[0] == pytest.approx(0.1)
            await clock.sleep(0.3)
            assert sim_node.sim.qpos[0] == pytest.approx(0.1, abs=0.03), "no stale command acts after reset"
            refused = await reset.call(Data(value={"q": [9.0, 0, 0, 0, 0, 0]}))
            assert not refused.success and "outside the joint limits" in refused.message
            assert (await reset.call(Data())).success and sim_node.sim.qpos[0] == 0.0
            s = (await stats.call(Empty())).value
            assert s["mode"] == "position" and s["commands"] >= 1 and s["published"] > 0


async def test_bad_commands_over_the_bus_are_counted_and_logged(caplog) -> None:  # type: ignore[no-untyped-def]
    async with open_domain("memory://") as domain:
        clock = SimClock(time_scale=None)
        async with (
            open_servo_sim("rx200", domain=domain, clock=clock) as sim_node,
            open_node("env", domain=domain, clock=clock) as env,
        ):
            pub = await env.create_publisher(JointCommand, "/rx200/command")
            pub.publish(command([np.nan, 0, 0, 0, 0]))
            await clock.sleep(0.15)
            pub.publish(command([0.1, 0.2]))
            await clock.sleep(0.15)
            pub.publish(command([5.0, 0, 0, 0, 0]))
            await clock.sleep(0.15)
    assert sim_node.stats.rejected == 2 and sim_node.stats.clipped == 1
    assert "non-finite" in caplog.text and "got shape (2,)" in caplog.text


async def test_markers_from_api_and_topic() -> None:
    async with open_domain("memory://") as domain:
        clock = SimClock(time_scale=None)
        async with (
            open_servo_sim("rx200", domain=domain, clock=clock, publish_markers=True) as sim_node,
            open_node("viz", domain=domain, clock=clock) as viz,
        ):
            got: list[Marker] = []
            await viz.create_subscription(Marker, "/rx200/markers", got.append, qos=reliable(100))
            to_sim = await viz.create_publisher(Marker, "/rx200/markers_in")
            sim_node.set_goal_marker((0.3, 0.1, 0.2))
            await clock.sleep(0.15)
            goal = [m for m in got if m.ns == "goal"]
            ee = [m for m in got if m.ns == "ee"]
            assert goal and np.allclose(goal[0].position, (0.3, 0.1, 0.2))
            assert ee and np.allclose(ee[-1].position, (0.408575, 0, 0.30457), atol=0.02), "EE at home"
            to_sim.publish(
                Marker(
                    header=Header(),
                    ns="goal",
                    position=np.array([0.2, 0.0, 0.1]),
                    scale=np.full(3, 0.02),
                    color=np.array([1.0, 0.0, 0.0, 1.0]),
                )
            )
            await clock.sleep(0.05)
            assert np.allclose(sim_node.goal_marker, (0.2, 0.0, 0.1))


@pytest.mark.slow  # ~1 s: closing a node whose TaskGroup aborted waits for the registry (bus/node.py)
async def test_divergence_ends_the_node_with_simulation_error() -> None:
    async with open_domain("memory://") as domain:
        clock = SimClock(time_scale=None)
        with pytest.raises(BaseExceptionGroup) as info:
            async with open_servo_sim("rx200", domain=domain, clock=clock) as sim_node:
                await clock.sleep(0.15)
                sim_node.sim.data.qvel[:] = 1e30
                await clock.sleep(1.0)
    assert info.group_contains(SimulationError, match="diverged")


async def test_emulated_arm_is_perturbed_noisy_and_delayed() -> None:
    emu = EmulationConfig(
        seed=3,
        command_latency=LatencyModel(base_s=0.25, jitter_s=0.0, distribution="constant"),
        state_latency=LatencyModel(base_s=0.03, jitter_s=0.0, distribution="constant"),
    )
    async with open_domain("memory://") as domain:
        clock = SimClock(time_scale=None)
        async with (
            open_servo_sim("rx200", domain=domain, clock=clock, emulation=emu) as sim_node,
            open_node("env", domain=domain, clock=clock) as env,
        ):
            f = sim_node.perturbation
            assert np.all(np.abs(f["mass"] - 1) <= 0.10) and np.all(np.abs(f["kp"] - 1) <= 0.15)
            assert np.abs(f["kp"] - 1).max() > 0.0, "gains were actually perturbed"
            states = await env.create_subscription(JointState, "/rx200/joint_states", qos=reliable(100))
            pub = await env.create_publisher(JointCommand, "/rx200/command")
            await clock.sleep(0.5)
            first = states.latest()
            assert first is not None and np.abs(first.position[:5]).max() > 0.0, "sensor noise"
            assert env.now_ns() - first.header.stamp_ns == 30_000_000 + 70_000_000, "30 ms late, stamped at the tick"
            pub.publish(command([0.4, 0, 0, 0, 0]))
            await clock.sleep(0.2)
            assert sim_node.sim.stats.commands == 0, "the command is still on the emulated network"
            await clock.sleep(0.12)  # delivered at 0.75 s, taken by the tick at 0.8 s
            assert sim_node.sim.stats.commands == 1
            await clock.sleep(1.5)
            assert abs(states.latest().position[0] - 0.4) < 0.03


@pytest.mark.parametrize("emulated", [False, True], ids=["sim", "emulated"])
async def test_joint_states_echo_the_newest_command_received(emulated: bool) -> None:
    """Wall clock: every state echoes the stamp of the newest command the arm received and how long before its own
    stamp that command came (the env's round trip of the link, envs/transit.py); -1 before any. An emulated arm's
    command latency (0.15 s here) counts as the link's: it is in the round trip."""
    latency_s = 0.15 if emulated else 0.0
    emu = EmulationConfig(
        seed=1,
        command_latency=LatencyModel(base_s=latency_s, jitter_s=0.0, distribution="constant"),
        state_latency=LatencyModel(base_s=0.0, jitter_s=0.0, distribution="constant"),
    )
    async with open_domain("memory://") as domain:
        async with (
            open_servo_sim("rx200", domain=domain, emulation=emu if emulated else None),
            open_node("env", domain=domain) as env,
        ):
            states = await env.create_subscription(JointState, "/rx200/joint_states")
            pub = await env.create_publisher(JointCommand, "/rx200/command")
            async with asyncio.timeout(5):
                first = await states.receive()
            assert first.command_stamp_ns is None and first.command_age_ns == -1
            sent_ns = time.monotonic_ns()
            pub.publish(JointCommand(header=Header(stamp_ns=sent_ns, seq=7), position=np.zeros(5)))
            async with asyncio.timeout(5):
                while (echo := await states.receive()).command_stamp_ns != sent_ns:
                    pass
            arrival_ns = states.latest_recv_ns
    age = echo.command_age_ns
    assert age is not None and 0 <= age <= arrival_ns - sent_ns
    round_trip_s = (arrival_ns - sent_ns - age) / 1e9
    assert latency_s <= round_trip_s < latency_s + 1.0, round_trip_s  # the latency each command is held, at least
