"""SimClock: a discrete-event clock driven by the sim; env-side timers follow it exactly."""

from __future__ import annotations

import asyncio
import time
from typing import Any

import numpy as np
import pytest

from uniros_async.bus import open_domain, open_node, reliable
from uniros_async.bus.messages import ClockTick, Header, JointCommand, JointState
from uniros_async.errors import ConfigError
from uniros_async.sim.node import open_servo_sim
from uniros_async.sim_clock import SimClock, follow_clock


async def test_sleepers_wake_in_deadline_order_and_cancel_cleanly() -> None:
    clock = SimClock()
    order: list[tuple[str, int]] = []

    async def sleeper(name: str, deadline: int) -> None:
        await clock.sleep_until(deadline)
        order.append((name, clock.now_ns()))

    async with asyncio.TaskGroup() as tg:
        tg.create_task(sleeper("c", 300))
        tg.create_task(sleeper("a", 100))
        tg.create_task(sleeper("b", 100))
        doomed = tg.create_task(sleeper("x", 200))
        await asyncio.sleep(0)
        assert clock.next_deadline_ns() == 100 and clock.pending == 4
        doomed.cancel()
        await asyncio.sleep(0)
        assert clock.pending == 3
        assert clock.advance_to(150) == 2
        await asyncio.sleep(0)
        assert order == [("a", 150), ("b", 150)], "ties wake first come, first served"
        clock.advance_to(50)  # never backwards
        assert clock.now_ns() == 150
        clock.advance_to(300)
    assert order[-1] == ("c", 300) and clock.next_deadline_ns() is None


async def test_driver_jumps_to_each_deadline() -> None:
    clock = SimClock(time_scale=None)
    fired: list[int] = []
    async with asyncio.TaskGroup() as tg:
        driver = tg.create_task(clock.run())

        async def periodic() -> None:
            nxt = 0
            for _ in range(5):
                nxt += 7_000_000
                await clock.sleep_until(nxt)
                fired.append(clock.now_ns())

        t0 = time.perf_counter()
        await tg.create_task(periodic())
        await clock.sleep(3600.0)  # an hour of sim time at once
        elapsed = time.perf_counter() - t0
        driver.cancel()
    assert fired == [7_000_000 * k for k in range(1, 6)]
    assert clock.now_ns() == 35_000_000 + 3600 * 10**9 and elapsed < 1.0
    with pytest.raises(ConfigError, match="follower"):
        await SimClock(follower=True).run()
    with pytest.raises(ConfigError, match="time_scale"):
        SimClock(time_scale=0.0)


async def test_unbounded_sim_with_env_timer_runs_much_faster_than_real_time() -> None:
    """rx200 at 10 Hz and an env loop at 10 Hz in one process (the lead's benchmark prints the tight figure)."""
    sim_s = 30.0
    async with open_domain("memory://") as domain:
        clock = SimClock(time_scale=None)
        async with (
            open_servo_sim("rx200", domain=domain, clock=clock) as sim_node,
            open_node("env", domain=domain, clock=clock) as env,
        ):
            states = await env.create_subscription(JointState, "/rx200/joint_states")
            pub = await env.create_publisher(JointCommand, "/rx200/command")
            goal = np.array([0.5, 0.3, -0.4, 0.6, 1.0])
            stamps: list[int] = []

            def env_step() -> None:
                msg = states.latest()
                stamps.append(msg.header.stamp_ns if msg else -1)
                pub.publish(JointCommand(header=Header(stamp_ns=env.now_ns()), position=goal))

            timer = env.create_timer(0.1, env_step, start_ns=clock.now_ns() + 50_000_000)  # between servo ticks
            wall0, cpu0 = time.perf_counter(), time.process_time()
            await clock.sleep(sim_s)
            wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
            timer.cancel()
            final = states.latest()
    speedup, cpu_speedup = sim_s / wall, sim_s / cpu
    print(
        f"\nSimClock unbounded, rx200 10 Hz + env 10 Hz: {speedup:.0f}x real time (wall), "
        f"{cpu_speedup:.0f}x per CPU second"
    )
    assert speedup >= 20, f"only {speedup:.1f}x real time"
    assert sim_node.stats.ticks == round(sim_s * 10) + 1
    deadlines, fires = list(timer.deadlines_ns), list(timer.fire_times_ns)
    assert fires == deadlines, "in-process timers fire exactly at their sim-time deadlines"
    assert stamps[1:] == [d - 50_000_000 for d in deadlines[1:]], "the env sees the state of the tick before"
    assert final is not None and np.abs(final.position[:5] - goal).max() < 0.03


async def test_time_scale_paces_against_wall_time() -> None:
    clock = SimClock(time_scale=10.0)
    async with asyncio.TaskGroup() as tg:
        driver = tg.create_task(clock.run())
        t0 = time.perf_counter()
        for _ in range(10):
            await clock.sleep(0.05)
        wall = time.perf_counter() - t0
        driver.cancel()
    assert clock.now_ns() >= 500_000_000
    assert 0.04 < wall < 0.4, f"0.5 s of sim time at 10x took {wall:.3f} s"  # paced, and faster than real time


async def test_follower_clock_follows_clock_ticks() -> None:
    async with open_domain("memory://") as domain:
        source = SimClock(time_scale=None)
        follower = SimClock(follower=True)
        async with open_node("watcher", domain=domain, clock=follower) as watcher:
            await follow_clock(watcher, follower)
            ticks = await watcher.create_subscription(ClockTick, "/clock")
            async with open_servo_sim("ned2", domain=domain, clock=source):
                async with asyncio.timeout(5):
                    await follower.sleep_until(1_000_000_000)  # woken by /clock from the source
            assert follower.now_ns() >= 1_000_000_000
            assert ticks.latest() is not None
    with pytest.raises(ConfigError, match="follower"):
        async with open_domain("memory://") as domain, open_node("n", domain=domain) as n:
            await follow_clock(n, SimClock())


async def test_pause_freezes_time_until_resume() -> None:
    async with open_domain("memory://") as domain:
        clock = SimClock(time_scale=None)
        async with open_servo_sim("rx200", domain=domain, clock=clock) as sim_node:
            await clock.sleep(0.45)  # between two servo ticks
            clock.pause()
            frozen, ticks = clock.now_ns(), sim_node.stats.ticks
            await asyncio.sleep(0.05)  # wall time passes, sim time does not
            assert clock.paused and clock.now_ns() == frozen and sim_node.stats.ticks == ticks
            clock.resume()
            await clock.sleep(0.5)
            assert clock.now_ns() >= frozen + 500_000_000 and sim_node.stats.ticks == ticks + 5


async def test_paced_sim_stamps_are_exact_hardware_periods() -> None:
    async with open_domain("memory://") as domain:
        clock = SimClock(time_scale=10.0)
        async with (
            open_servo_sim("ned2", domain=domain, clock=clock),
            open_node("env", domain=domain, clock=clock) as env,
        ):
            stamps: list[int] = []
            await env.create_subscription(
                JointState, "/ned2/joint_states", lambda m: stamps.append(m.header.stamp_ns), qos=reliable(100)
            )
            t0 = time.perf_counter()
            await clock.sleep(0.4)
            wall = time.perf_counter() - t0
    assert len(stamps) >= 9 and set(np.diff(stamps)) == {40_000_000}, "sim-time stamps, exact at any time scale"
    assert 0.02 < wall < 0.3, f"0.4 s of sim time at 10x took {wall:.3f} s"  # paced, and faster than real time


async def test_two_drivers_on_one_loop_settle_at_once_and_still_wait_for_runnable_work(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Two sims' clocks driven on one event loop (a worker process hosting two envs): each driver's yields are
    the other's only runnable work, which must not keep either from settling (each would otherwise yield up to
    10,000 times per sim event); a task with work left still keeps both from settling."""
    import types

    from uniros_async import sim_clock

    yields = [0]
    real_sleep = asyncio.sleep

    async def counting_sleep(delay: float) -> None:
        yields[0] += 1
        await real_sleep(delay)

    monkeypatch.setattr(sim_clock, "asyncio", types.SimpleNamespace(sleep=counting_sleep))
    loop = asyncio.get_running_loop()
    settling = sim_clock._settling(loop)
    await asyncio.gather(sim_clock._settle(loop, settling), sim_clock._settle(loop, settling))
    assert yields[0] <= 6

    done = asyncio.Event()
    settled_after_work: list[bool] = []

    async def busy() -> None:
        for _ in range(50):
            await real_sleep(0)
        done.set()

    async def settle() -> None:
        await sim_clock._settle(loop, settling)
        settled_after_work.append(done.is_set())

    yields[0] = 0
    await asyncio.gather(busy(), settle(), settle())
    assert settled_after_work == [True, True] and yields[0] <= 2 * 60


async def test_two_envs_on_one_loop_step_as_they_would_alone() -> None:
    """Two attached rx200 envs on this loop (as in a worker hosting two): their steps return the same
    observations as one env stepped alone, stepped at once (both sims' clocks driven on this loop together)."""
    import gymnasium as gym

    import uniros_async  # noqa: F401
    from uniros_async.envs.runtime import deferred_start
    from uniros_async.runtime.attached import areset_through, astep_through

    kw: dict[str, Any] = {"turn_based": True, "action_mode": "absolute", "max_episode_steps": 10**9}

    async def envs(k: int) -> list[Any]:
        out = []
        for _ in range(k):
            with deferred_start():
                env = gym.make("uniros/Rx200Reach-v0", **kw)
            await env.unwrapped.astart()  # type: ignore[attr-defined]
            await areset_through(env, 3, None)
            out.append(env)
        return out

    (alone,) = await envs(1)
    pair = await envs(2)
    alone.action_space.seed(0)
    actions = [alone.action_space.sample() for _ in range(4)]
    try:
        for a in actions:
            want, *_ = await astep_through(alone, a)
            (first, *_), (second, *_) = await asyncio.gather(astep_through(pair[0], a), astep_through(pair[1], a))
            np.testing.assert_allclose(first, want)
            np.testing.assert_allclose(second, want)
    finally:
        for env in (alone, *pair):
            await env.unwrapped.aclose()
