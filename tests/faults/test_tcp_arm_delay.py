"""Delay and jitter on the link to a served arm (``uniros robot serve`` over tcp), from the tests' own delaying relay.

This kernel has no netem (CONFIG_NET_SCH_NETEM is off), so the delay is ``rig.delayrelay``: a tcp
relay in the arm's namespace that nftables sends every connection across the veth link to, either way
(``NetnsPair.delay_through``); it holds each chunk for the delay, give or take the jitter, keeping the order, with a
bounded buffer. Every byte between the env and the arm passes it once, so the delay is one way, each way.

For each delay a fresh arm, relay and agent (``netfault drive``: the rx200 reach env, ``robot_timeout_s=0.5``, a
0.2 s action cycle) run for ``WINDOW_S``; measured from the three's event lines on one monotonic clock: how old the
joint states the steps and resets returned on were (by the arm's stamp), the env's own estimate, the link's round
trip the env measured (the arm echoes the stamp of the newest command it received in its joint states:
``uniros_async.envs.transit``), the action cycle, RobotErrors, episode ends and why (``info``), and the age of every
command the arm took (``--max-command-age`` drops those older than the robot timeout). ``UNIROS_FAULT_REPORT=PATH``
appends each run's figures to PATH (docs/reliability.md).

What must hold whatever the delay: no step or reset returns on a state older than the robot timeout, no command older
than it is applied, no uncaught exception, and every round trip measured is at least twice the least delay the relay
holds a chunk. Below the timeout the env keeps stepping, measuring a round trip of about twice the delay; when even
the quickest transit exceeds it, the env reports (RobotError naming the round trip) and never steps, the arm drops
every command, and once the relay's delay is taken down (the link stays up) the same env steps again by itself.
"""

from __future__ import annotations

import math
import statistics
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pytest
from rig.netfault import EventPeer, NetnsPair, open_netns_pair

from ._arm import (
    COMMAND_TIMEOUT_S,
    PERIOD_S,
    ROBOT_TIMEOUT_S,
    auth_env,
    report,
    start_agent,
    start_tcp_arm,
    stopping,
    uncaught,
)
from ._faults import CODE_PATH_S, RECOVER_S, STALL_S, Link

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("netfault_ready")]

RELAY_PORT = 7100
RELAY_MARK = 1
WINDOW_S = 8.0
START_S = 90.0
"""A bound against a hang: the agent's first step (or report), every round trip of its setup delayed twice."""
DELAYS = [(0.05, 0.01), (0.2, 0.05), (0.75, 0.05), (1.0, 0.2)]  # (delay, jitter) each way, s; 0.75: 1.5 timeouts
RECOVERY_DELAY = (0.05, 0.01)
"""What the relay's delay is taken down to, to see the env recover by itself."""
MEASURE_SLACK_S = 1e-3
"""Below the least round trip the relay allows: the arm's echo age is read a few microseconds after its stamp."""


def _reports(delay_s: float, jitter_s: float) -> bool:
    """Whether the env must report rather than step: even its lowest estimate of a state's transit (the quickest
    transit, less the error of half the quickest round trip's asymmetry, at most the jitter) exceeds the timeout."""
    return delay_s - 2 * jitter_s > ROBOT_TIMEOUT_S


@dataclass
class Delayed:
    link: Link
    relay: EventPeer
    delay_s: float
    jitter_s: float


@pytest.fixture(scope="module", params=DELAYS, ids=[f"{d * 1000:.0f}ms+-{j * 1000:.0f}ms" for d, j in DELAYS])
def delayed(request: pytest.FixtureRequest, netfault_ready: None) -> Iterator[Delayed]:
    delay_s, jitter_s = request.param
    with open_netns_pair() as pair, stopping() as peers:
        relay, arm, agent = _start_delayed(pair, peers, delay_s, jitter_s)
        first = "robot_error" if _reports(delay_s, jitter_s) else "step"
        agent.wait_for(0, first, START_S, f"the agent's first {first}")
        yield Delayed(Link(pair, arm, agent), relay, delay_s, jitter_s)


def _start_delayed(
    pair: NetnsPair, peers: list[EventPeer], delay_s: float, jitter_s: float
) -> tuple[EventPeer, EventPeer, EventPeer]:
    """The relay (delaying every tcp connection across the link), a served arm and an agent on it."""
    env = auth_env()
    argv = [sys.executable, "-m", "rig.delayrelay", "--port", str(RELAY_PORT), "--delay",
            str(delay_s), "--jitter", str(jitter_s), "--mark", str(RELAY_MARK), "--control"]  # fmt: skip
    relay = EventPeer(pair.popen("arm", argv, stdin=subprocess.PIPE))
    peers.append(relay)
    assert relay.proc.stdout is not None
    assert relay.proc.stdout.readline().strip() == "ready"
    relay.start_reader()
    pair.delay_through(RELAY_PORT, RELAY_MARK)  # before any connection crosses the link
    arm, uri = start_tcp_arm(pair, peers, env)
    return relay, arm, start_agent(pair, peers, uri, env=env)


def _set_delay(relay: EventPeer, delay_s: float, jitter_s: float) -> int:
    """Give the relay a new delay (for what it reads from then on); when it took it."""
    assert relay.proc.stdin is not None
    t_set = time.monotonic_ns()
    relay.proc.stdin.write(f"delay {delay_s} {jitter_s}\n")
    relay.proc.stdin.flush()
    relay.wait_for(t_set, "delay", RECOVER_S, "the relay's new delay")
    return t_set


def _round_trips(events: list[dict[str, Any]]) -> list[float]:
    return sorted(e["round_trip_s"] for e in events if e.get("round_trip_s") is not None)


def _figures(d: Delayed, t0: int, t1: int) -> dict[str, Any]:
    s = 1e-9
    agent, arm = d.link.agent, d.link.arm

    def between(peer: EventPeer, ev: str) -> list[dict[str, Any]]:
        return [e for e in peer.after(t0, ev) if e["t_ns"] <= t1]

    steps, errors, cmds = between(agent, "step"), between(agent, "robot_error"), between(arm, "cmd")
    applied = [e for e in cmds if e["applied"]]
    cycles = [(b["t_ns"] - a["t_ns"]) * s for a, b in zip(steps, steps[1:], strict=False)]
    ages = sorted(e["state_stamp_age_s"] for e in steps)
    ends = [e for e in steps if e["terminated"] or e["truncated"]]
    trips = _round_trips(steps + errors)
    # the first report that names a measured round trip (before the first echo, one names the commands unechoed)
    saw = [e for e in errors if "round trip to the arm measured" in e["msg"]] or errors
    # since the agent started, not only in the window: its first reset too
    returned = agent.after(0, "step") + agent.after(0, "reset")
    all_cmds = [e for e in arm.after(0, "cmd") if e["t_ns"] <= t1]
    return {
        "fault": f"delay {d.delay_s * 1000:.0f} ms +- {d.jitter_s * 1000:.0f} ms each way (relay)",
        "link": "tcp",
        "window_s": round((t1 - t0) * s, 1),
        "steps": len(steps),
        "state_age_at_step_median_s": round(statistics.median(ages), 3) if ages else None,
        "state_age_at_step_max_s": round(ages[-1], 3) if ages else None,
        "oldest_state_returned_since_start_s": round(max((e["state_stamp_age_s"] for e in returned), default=-1), 3),
        "resets_since_start": len(agent.after(0, "reset")),
        "env_estimated_state_age_max_s": round(max((e["state_age_s"] for e in steps), default=-1.0), 3),
        "round_trip_median_s": round(statistics.median(trips), 3) if trips else None,
        "round_trip_min_s": round(trips[0], 3) if trips else None,
        "round_trip_max_s": round(trips[-1], 3) if trips else None,
        "round_trip_events": len(trips),
        "action_cycle_median_s": round(statistics.median(cycles), 3) if cycles else None,
        "action_cycle_max_s": round(max(cycles), 3) if cycles else None,
        "robot_errors": len(errors),
        "agent_saw": saw[0]["msg"] if saw else "no error",
        "first_report_since_start": next((e["msg"] for e in agent.after(0, "robot_error")), None),
        "episode_ends": len(ends),
        "end_info": ends[0]["info"] if ends else None,
        "truncated": sum(1 for e in ends if e["truncated"]),
        "commands_applied": len(applied),
        "commands_dropped_stale": len(cmds) - len(applied),
        "max_age_applied_s": round(max((e["age_ns"] for e in applied), default=0) * s, 3),
        "commands_since_start": len(all_cmds),
        "commands_applied_since_start": sum(1 for e in all_cmds if e["applied"]),
        "first_command_age_s": round(all_cmds[0]["age_ns"] * s, 3) if all_cmds else None,
        "holds": len(between(arm, "hold")),
        "uncaught_exceptions": len(uncaught(agent)),
    }


def _recover(d: Delayed) -> dict[str, Any]:
    """Take the relay's delay down to ``RECOVERY_DELAY`` (the link and every connection stay up) and wait until the
    same agent steps again and the arm applies a command; the figures of that."""
    agent, arm = d.link.agent, d.link.arm
    t_set = _set_delay(d.relay, *RECOVERY_DELAY)
    step = agent.wait_for(t_set, "step", RECOVER_S, "a step after the delay was taken down")
    cmd = arm.wait_for(t_set, "cmd", RECOVER_S, "a command applied after it", where=lambda e: bool(e["applied"]))
    return {
        "recovery_delay_s": RECOVERY_DELAY[0],
        "recovered_step_after_s": round((step["t_ns"] - t_set) / 1e9, 3),
        "recovered_step_state_stamp_age_s": round(step["state_stamp_age_s"], 3),
        "recovered_round_trip_s": step["round_trip_s"],
        "command_applied_after_s": round((cmd["t_ns"] - t_set) / 1e9, 3),
    }


def test_delay(delayed: Delayed) -> None:
    d = delayed
    agent = d.link.agent
    reports = _reports(d.delay_s, d.jitter_s)
    t0 = time.monotonic_ns()
    # the window: WINDOW_S of the agent stepping (or reporting), judged once it is over
    kind = "robot_error" if reports else "step"
    last = agent.wait_for(t0 + round(WINDOW_S * 1e9), kind, WINDOW_S + START_S, f"a {kind} at the window's end")
    row = _figures(d, t0, last["t_ns"])
    if reports:
        row.update(_recover(d))
    report(row)
    errors = uncaught(agent)
    assert not errors, errors[0]["tb"]
    # whatever the delay: the arm applies no command older than the robot timeout (its --max-command-age), and no
    # step or reset returns on a state older than the robot timeout by its own stamp (the arm shares this clock)
    assert row["max_age_applied_s"] <= ROBOT_TIMEOUT_S, row
    assert row["oldest_state_returned_since_start_s"] <= ROBOT_TIMEOUT_S + CODE_PATH_S, row
    # the round trip the env measured: each one at least the least the relay holds a chunk each way; the median
    # about twice the delay, within the spread of two uniform jitters (and the code path of the hosts' loops)
    low, high = 2 * (d.delay_s - d.jitter_s), 2 * (d.delay_s + d.jitter_s)
    assert row["round_trip_events"] > 0, row
    assert row["round_trip_min_s"] >= low - MEASURE_SLACK_S, row
    assert abs(row["round_trip_median_s"] - 2 * d.delay_s) <= 2 * d.jitter_s + CODE_PATH_S, row
    if not reports:
        assert row["steps"] >= 2 and row["robot_errors"] == 0, row  # the env keeps stepping, as without the echo
        assert row["commands_applied"] > 0, row
        return
    # even the quickest transit exceeds the timeout: the env reports instead of stepping, naming the round trip
    assert row["steps"] == 0 and row["resets_since_start"] == 0, row
    assert row["robot_errors"] >= 2, row
    saw = row["agent_saw"]
    assert "s old" in saw and "round trip to the arm measured" in saw, saw
    named = float(saw.split("round trip to the arm measured ")[1].split(" s", 1)[0])
    assert low - MEASURE_SLACK_S <= named <= high + CODE_PATH_S, saw
    age = float(saw.split(" s old")[0].rsplit(" ", 1)[1])
    assert age > ROBOT_TIMEOUT_S, saw
    # the arm never moved: what the env sent before it knew (its first reset's commands) came too old
    assert row["commands_applied_since_start"] == 0 and row["commands_since_start"] > 0, row
    # the delay taken down: the same env steps again by itself, on a fresh state, and the arm takes commands
    assert row["recovered_step_state_stamp_age_s"] <= ROBOT_TIMEOUT_S + CODE_PATH_S, row


ONSET = (0.75, 0.05)
"""A delay of 1.5 robot timeouts each way, setting in while the env steps on a 50 ms link."""


def test_a_delay_that_sets_in_raises_and_the_arm_holds(netfault_ready: None) -> None:
    """The env raises RobotError within the robot timeout (and the old link's delay, a period and its own loop's
    lateness) of a delay of 1.5 robot timeouts setting in, and the arm's watchdog holds it within the command
    timeout (the robot timeout) and one control period of the last command it applied: every later one comes too
    old and is dropped. Taken down again, the same env steps by itself."""
    with open_netns_pair() as pair, stopping() as peers:
        relay, arm, agent = _start_delayed(pair, peers, *RECOVERY_DELAY)
        agent.wait_for(0, "step", START_S, "the agent's first step")
        agent.wait_for(time.monotonic_ns() + round(2e9), "step", RECOVER_S, "steps on the 50 ms link")
        t_set = _set_delay(relay, *ONSET)
        error = agent.wait_for(t_set, "robot_error", RECOVER_S, "a RobotError after the delay set in")
        hold = arm.wait_for(t_set, "hold", RECOVER_S, "the arm's watchdog hold")
        time.sleep(3.0)  # the delay stays: nothing more is applied, nothing stepped
        t_down = _set_delay(relay, *RECOVERY_DELAY)
        step = agent.wait_for(t_down, "step", RECOVER_S, "a step after the delay was taken down")
    applied = [e for e in arm.after(0, "cmd") if e["applied"]]
    last = [e for e in applied if e["t_ns"] < hold["t_ns"]][-1]
    late_steps = [e for e in agent.after(t_set, "step") if e["t_ns"] < t_down]
    row = {
        "fault": f"delay setting in: {ONSET[0] * 1000:.0f} ms +- {ONSET[1] * 1000:.0f} ms each way (relay)",
        "link": "tcp",
        "notice_after_onset_s": round((error["t_ns"] - t_set) / 1e9, 3),
        "agent_loop_late_s": error["loop_late_s"],
        "agent_saw": error["msg"],
        "hold_after_last_command_s": round((hold["t_ns"] - last["t_ns"]) / 1e9, 3),
        "hold_ticks_after_last_command": hold["tick"] - last["tick"],
        "applied_after_hold": sum(1 for e in applied if hold["t_ns"] < e["t_ns"] < t_down),
        "max_age_applied_s": round(max(e["age_ns"] for e in applied) / 1e9, 3),
        "steps_while_delayed": sum(1 for e in late_steps if e["t_ns"] > error["t_ns"]),
        "oldest_state_a_step_returned_on_s": round(max((e["state_stamp_age_s"] for e in late_steps), default=-1), 3),
        "recovered_step_after_s": round((step["t_ns"] - t_down) / 1e9, 3),
        "uncaught_exceptions": len(uncaught(agent)),
    }
    report(row)
    assert not uncaught(agent), uncaught(agent)[0]["tb"]
    old_link_s = RECOVERY_DELAY[0] + RECOVERY_DELAY[1]  # what the newest state before the onset took to arrive
    limit = ROBOT_TIMEOUT_S + old_link_s + PERIOD_S + row["agent_loop_late_s"] + CODE_PATH_S
    assert row["notice_after_onset_s"] <= limit, row
    assert row["hold_ticks_after_last_command"] <= math.ceil(COMMAND_TIMEOUT_S / PERIOD_S - 1e-9) + 1, row
    assert row["hold_after_last_command_s"] <= COMMAND_TIMEOUT_S + PERIOD_S + STALL_S, row
    assert row["applied_after_hold"] == 0 and row["max_age_applied_s"] <= ROBOT_TIMEOUT_S, row
    assert row["steps_while_delayed"] == 0, row
    assert row["oldest_state_a_step_returned_on_s"] <= ROBOT_TIMEOUT_S + CODE_PATH_S, row
