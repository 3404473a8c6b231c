"""What the fault tests share: the faults, and one fault's run and measurement (see test_tcp_arm_faults.py)."""

from __future__ import annotations

import math
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rig.netfault import EventPeer, NetnsPair, fault_figures

from ._arm import report, uncaught

FAULT_S = 2.0
RECOVER_S = 15.0
"""A bound against a hang, not a goal: how long the agent may take to step again after the fault is cleared."""
CODE_PATH_S = 0.05
"""What the code between a check and its event line may take (no wait in it)."""
STALL_S = 1.0
"""How late a process's loop may run on the loaded 2-core host before it counts as stalled (the latest seen: 0.6 s
for the arm's tick that held it, 0.4 s for the agent's), for the wall-clock hold: the watchdog itself is judged in
the arm's own ticks, exactly."""


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
    # what the arm applies right after recovery is judged too: wait until it applied one half a second later
    arm.wait_for(recovered["t_ns"] + 500_000_000, "cmd", RECOVER_S, "a command applied after recovery")
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
    report(row)
    errors = uncaught(agent)
    assert not errors, errors[0]["tb"]
    if check_ages:
        assert row["stale_commands_applied"] == 0, row
        # no step returned on a state older than the timeout, by its own stamp (the arm shares this clock)
        assert row["max_state_stamp_age_at_step_s"] <= robot_timeout_s + CODE_PATH_S, row
    assert any(e["ev"] == "cmd" and e["applied"] and e["t_ns"] <= t_fault for e in arm.events), "no command before"
    if must_notice:
        assert row["robot_errors"], f"{name}: the agent saw no RobotError"
        # the robot timeout after the last state (which came within a period before the fault), plus how late the
        # agent's own loop ran meanwhile (measured from its tick times: the host's scheduling, not the env's logic)
        assert row["notice_after_fault_s"] <= (robot_timeout_s + period_s + row["agent_loop_late_s"] + CODE_PATH_S), row
        assert "s old" in row["agent_saw"] and "rx200" in row["agent_saw"], row["agent_saw"]
        age = float(row["agent_saw"].split(" s old")[0].rsplit(" ", 1)[1])
        # it reports a state that is stale, never a fresh one (the message rounds to 10 ms)
        assert age >= round(robot_timeout_s, 2), row["agent_saw"]
    if row["hold_ticks_after_last_command"] is not None:
        # the watchdog, in the arm's own ticks (one period of sim time each): the first tick past its timeout
        assert row["hold_ticks_after_last_command"] <= math.ceil(command_timeout_s / period_s - 1e-9) + 1, row
        assert row["hold_after_last_command_s"] <= command_timeout_s + period_s + STALL_S, row
    return row
