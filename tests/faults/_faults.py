"""What the fault tests share: the faults, and one fault's run and measurement (see test_tcp_arm_faults.py)."""

from __future__ import annotations

import json
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from uniros_async.testing.netfault import EventPeer, NetnsPair, fault_figures

FAULT_S = 2.0
RECOVER_S = 15.0
SLACK_S = 0.5
"""Scheduling slack on a shared 2-core machine: both ends run real-time when permitted, yet a hold or a notice came
up to 0.4 s late in about one run of three while other jobs loaded the host (docs/reliability.md reports the figures
themselves)."""


@dataclass
class Link:
    pair: NetnsPair
    arm: EventPeer
    agent: EventPeer


def _freeze(link: Link) -> Callable[[], None]:
    os.kill(link.arm.proc.pid, signal.SIGSTOP)
    return lambda: os.kill(link.arm.proc.pid, signal.SIGCONT)


def _nft(apply: Callable[[NetnsPair], None]) -> Callable[[Link], Callable[[], None]]:
    def inject(link: Link) -> Callable[[], None]:
        apply(link.pair)
        return link.pair.clear

    return inject


def _link_down(link: Link) -> Callable[[], None]:
    link.pair.link_down()
    return link.pair.link_up


FAULTS: dict[str, tuple[Callable[[Link], Callable[[], None]], bool]] = {
    # name: (inject -> clear, whether the agent must notice)
    "partition": (_nft(NetnsPair.partition), True),
    "loss 1 %": (_nft(lambda p: p.loss(1)), False),
    "loss 10 %": (_nft(lambda p: p.loss(10)), False),
    "loss 50 %": (_nft(lambda p: p.loss(50)), False),
    "tcp reset": (_nft(NetnsPair.tcp_reset), True),
    "starved link (tbf 8 kbit/s)": (_nft(lambda p: p.starve("8kbit")), False),
    "link down": (_link_down, True),
    "frozen arm (SIGSTOP)": (_freeze, True),
}


def _report(row: dict[str, Any]) -> None:
    path = os.environ.get("UNIROS_FAULT_REPORT")
    if path:
        with open(path, "a") as f:
            f.write(json.dumps(row) + "\n")


def run_fault(
    link: Link,
    name: str,
    *,
    robot: str,
    robot_timeout_s: float,
    command_timeout_s: float,
    period_s: float,
    check_ages: bool = True,
) -> dict[str, Any]:
    """Inject fault ``name`` for ``FAULT_S``, clear it, wait for the agent's recovery, check the goals; returns
    the figures (``fault_figures``), also appended to ``$UNIROS_FAULT_REPORT`` when set."""
    inject, must_notice = FAULTS[name]
    arm, agent = link.arm, link.agent
    agent.wait_for(time.monotonic_ns(), "step", RECOVER_S, "a step before the fault")
    # the fault is in effect once its command has returned (spawning ip/nft can take a while on a loaded machine)
    clear = inject(link)
    t_fault = time.monotonic_ns()
    try:
        time.sleep(FAULT_S)  # the fault's duration: the thing under test runs meanwhile
    finally:
        clear()
        t_clear = time.monotonic_ns()
    recovered = agent.wait_for(t_clear, "step", RECOVER_S, "recovery after the fault was cleared")
    time.sleep(0.5)  # what the arm applies right after recovery is judged too
    row = fault_figures(
        name,
        arm,
        agent,
        t_fault=t_fault,
        t_clear=t_clear,
        recovered_ns=recovered["t_ns"],
        robot_timeout_s=robot_timeout_s,
    )
    row["link"] = robot
    _report(row)
    print(json.dumps(row))
    uncaught = [e for e in agent.events if e["ev"] == "error"]
    assert not uncaught, uncaught[0]["tb"]
    if check_ages:
        assert row["stale_commands_applied"] == 0, row
        # no step returned on a state older than the timeout, by its own stamp (the arm shares this clock)
        assert row["max_state_stamp_age_at_step_s"] <= robot_timeout_s + 0.05, row
    assert any(e["ev"] == "cmd" and e["applied"] and e["t_ns"] <= t_fault for e in arm.events), "no command before"
    if must_notice:
        assert row["robot_errors"], f"{name}: the agent saw no RobotError"
        assert row["notice_after_fault_s"] <= robot_timeout_s + period_s + SLACK_S, row
        assert "s old" in row["agent_saw"] and "rx200" in row["agent_saw"], row["agent_saw"]
    if row["hold_after_last_command_s"] is not None:
        assert row["hold_after_last_command_s"] <= command_timeout_s + period_s + SLACK_S, row
    return row
