"""Delay and jitter on the link to a served arm (``uniros robot serve`` over tcp), from the tests' own delaying relay.

This kernel has no netem (CONFIG_NET_SCH_NETEM is off), so the delay is ``uniros_async.testing.delayrelay``: a tcp
relay in the arm's namespace that nftables sends every connection across the veth link to, either way
(``NetnsPair.delay_through``); it holds each chunk for the delay, give or take the jitter, keeping the order, with a
bounded buffer. Every byte between the env and the arm passes it once, so the delay is one way, each way.

For each delay a fresh arm, relay and agent (``netfault drive``: the rx200 reach env, ``robot_timeout_s=0.5``, a
0.2 s action cycle) run for ``WINDOW_S`` of steps; measured from both sides' event lines on one monotonic clock:
how old the joint states the steps returned on were (by the arm's stamp), the action cycle, RobotErrors, episode
ends and why (``info``), and the age of every command the arm took (``--max-command-age`` drops those older than
the robot timeout). ``UNIROS_FAULT_REPORT=PATH`` appends each run's figures to PATH (docs/reliability.md).

What must hold whatever the delay: no command older than the robot timeout is applied, no uncaught exception, the
env keeps stepping, and no step returns on a state older than the robot timeout plus the delay every state has
(the floor, ``delay - jitter``): the env's age of a state cannot see that floor, as it cannot tell it from an offset
between the arm's clock and its own (docs/reliability.md). A floor beyond the robot timeout: the arm drops every
command.
"""

from __future__ import annotations

import json
import os
import secrets
import statistics
import sys
import time
from collections.abc import Iterator
from typing import Any

import pytest

from uniros_async.testing.netfault import EventPeer, open_netns_pair

from ._faults import CODE_PATH_S, Link

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("netfault_ready")]

ROBOT_TIMEOUT_S = 0.5
COMMAND_TIMEOUT_S = 0.5
ACTION_CYCLE_S = 0.2
PORT = 7000
RELAY_PORT = 7100
RELAY_MARK = 1
WINDOW_S = 8.0
START_S = 90.0
"""A bound against a hang: the agent's first step, every round trip of its setup delayed twice."""
DELAYS = [(0.05, 0.01), (0.2, 0.05), (1.0, 0.2)]  # (delay, jitter) each way, s


@pytest.fixture(scope="module", params=DELAYS, ids=[f"{d * 1000:.0f}ms+-{j * 1000:.0f}ms" for d, j in DELAYS])
def delayed(request: pytest.FixtureRequest, netfault_ready: None) -> Iterator[tuple[Link, EventPeer, float, float]]:
    delay_s, jitter_s = request.param
    py = sys.executable
    env = {**os.environ, "UNIROS_AUTH_KEY": secrets.token_hex(16)}
    with open_netns_pair() as pair:
        relay = EventPeer(
            pair.popen(
                "arm",
                [
                    py,
                    "-m",
                    "uniros_async.testing.delayrelay",
                    "--port",
                    str(RELAY_PORT),
                    "--delay",
                    str(delay_s),
                    "--jitter",
                    str(jitter_s),
                    "--mark",
                    str(RELAY_MARK),
                ],
            )  # fmt: skip
        )
        peers = [relay]
        try:
            assert relay.proc.stdout is not None
            assert relay.proc.stdout.readline().strip() == "ready"
            relay.start_reader()
            pair.delay_through(RELAY_PORT, RELAY_MARK)  # before any connection crosses the link
            arm_proc = pair.popen(
                "arm",
                [py, "-m", "uniros_async.cli", "robot", "serve", "rx200", "--host", pair.arm_ip, "--port", str(PORT),
                 "--command-timeout", str(COMMAND_TIMEOUT_S), "--max-command-age", str(ROBOT_TIMEOUT_S), "--trace"],
                env=env,
            )  # fmt: skip
            arm = EventPeer(arm_proc)
            peers.append(arm)
            assert arm_proc.stdout is not None
            uri = arm_proc.stdout.readline().strip().split("=", 1)[-1]
            assert uri == f"tcp://{pair.arm_ip}:{PORT}", uri
            arm.start_reader()
            agent = EventPeer(
                pair.popen(
                    "env",
                    [
                        py,
                        "-m",
                        "uniros_async.testing.netfault",
                        "drive",
                        "--robot",
                        uri,
                        "--robot-timeout",
                        str(ROBOT_TIMEOUT_S),
                        "--action-cycle",
                        str(ACTION_CYCLE_S),
                    ],
                    env=env,
                )  # fmt: skip
            )
            peers.append(agent)
            agent.start_reader()
            agent.wait_for(0, "step", START_S, "the agent's first step")
            yield Link(pair, arm, agent), relay, delay_s, jitter_s
        finally:
            for peer in reversed(peers):
                peer.stop()


def _figures(link: Link, t0: int, t1: int, delay_s: float, jitter_s: float) -> dict[str, Any]:
    s = 1e-9
    steps = [e for e in link.agent.after(t0, "step") if e["t_ns"] <= t1]
    errors = [e for e in link.agent.after(t0, "robot_error") if e["t_ns"] <= t1]
    cmds = [e for e in link.arm.after(t0, "cmd") if e["t_ns"] <= t1]
    applied = [e for e in cmds if e["applied"]]
    cycles = [(b["t_ns"] - a["t_ns"]) * s for a, b in zip(steps, steps[1:], strict=False)]
    ages = sorted(e["state_stamp_age_s"] for e in steps)
    ends = [e for e in steps if e["terminated"] or e["truncated"]]
    return {
        "fault": f"delay {delay_s * 1000:.0f} ms +- {jitter_s * 1000:.0f} ms each way (relay)",
        "link": "tcp",
        "window_s": round((t1 - t0) * s, 1),
        "steps": len(steps),
        "state_age_at_step_median_s": round(statistics.median(ages), 3) if ages else None,
        "state_age_at_step_max_s": round(ages[-1], 3) if ages else None,
        "env_estimated_state_age_max_s": round(max((e["state_age_s"] for e in steps), default=-1.0), 3),
        "action_cycle_median_s": round(statistics.median(cycles), 3) if cycles else None,
        "action_cycle_max_s": round(max(cycles), 3) if cycles else None,
        "robot_errors": len(errors),
        "agent_saw": errors[0]["msg"] if errors else "no error",
        "episode_ends": len(ends),
        "end_info": ends[0]["info"] if ends else None,
        "truncated": sum(1 for e in ends if e["truncated"]),
        "commands_applied": len(applied),
        "commands_dropped_stale": len(cmds) - len(applied),
        "max_age_applied_s": round(max((e["age_ns"] for e in applied), default=0) * s, 3),
        "holds": len([e for e in link.arm.after(t0, "hold") if e["t_ns"] <= t1]),
        "uncaught_exceptions": len([e for e in link.agent.events if e["ev"] == "error"]),
    }


def test_delay(delayed: tuple[Link, EventPeer, float, float]) -> None:
    link, relay, delay_s, jitter_s = delayed
    agent = link.agent
    t0 = time.monotonic_ns()
    # the window: WINDOW_S of the agent stepping, judged once it is over (a step at or after its end)
    last = agent.wait_for(t0 + round(WINDOW_S * 1e9), "step", WINDOW_S + START_S, "a step at the window's end")
    row = _figures(link, t0, last["t_ns"], delay_s, jitter_s)
    print(json.dumps(row))
    path = os.environ.get("UNIROS_FAULT_REPORT")
    if path:
        with open(path, "a") as f:
            f.write(json.dumps(row) + "\n")
    uncaught = [e for e in agent.events if e["ev"] == "error"]
    assert not uncaught, uncaught[0]["tb"]
    # whatever the delay, the arm applies no command older than the robot timeout (its --max-command-age)
    assert row["max_age_applied_s"] <= ROBOT_TIMEOUT_S, row
    assert row["steps"] >= 2, row  # the env keeps stepping
    one_way_max = delay_s + jitter_s
    floor_s = delay_s - jitter_s  # the least a state spends on the way
    # the env's age of a state counts from its arrival plus how much longer than the quickest state of the last
    # 60 s took: the delay every state has (the quickest transit) is invisible to it, like an offset between the
    # clocks; so a step returns on a state at most the robot timeout plus that quickest transit old (by the arm's
    # stamp, on this clock). With the jitter uniform and hundreds of states a window, the quickest transit is
    # near the floor and well below the mean delay, the bound used here.
    assert row["state_age_at_step_max_s"] <= ROBOT_TIMEOUT_S + delay_s + CODE_PATH_S, row
    if 2 * one_way_max + ACTION_CYCLE_S < ROBOT_TIMEOUT_S:
        # a command's round trip fits in the timeout: the arm takes the commands
        assert row["commands_applied"] > 0, row
    if floor_s > ROBOT_TIMEOUT_S:
        # every command reaches the arm older than the timeout: dropped, the arm stays where it is
        assert row["commands_applied"] == 0 and row["commands_dropped_stale"] > 0, row
