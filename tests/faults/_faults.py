"""What the fault tests share: the faults, their durations, and one fault's run and measurement (see
test_tcp_arm_faults.py)."""

from __future__ import annotations

import math
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rig.netfault import EventPeer, NetnsPair, fault_figures

from ._arm import probe_domain, probe_ros1, report, uncaught

DURATIONS_S = (0.5, 5.0, 30.0)
"""How long each fault lasts: shorter than the robot timeout and a reset; past them; past every lease and keepalive
(the tcp keepalive breaks an idle connection after about 5 s, the registry then forgets the node)."""
NOTICE_FROM_S = 2.0
"""A fault that cuts the states for at least this long must be noticed (a shorter one may heal, TCP retransmitting,
before the newest state turns older than the robot timeout)."""
RECOVER_S = 45.0
"""A bound against a hang, not the goal: how long the test waits for the agent to step again after the fault."""
RECOVER_GOAL_S = 2.0
"""The goal: the agent's next good step within ``robot_timeout_s`` and this of the link's return."""
CODE_PATH_S = 0.05
"""What the code between a check and its event line may take (no wait in it)."""
STALL_S = 1.0
"""How late a process's loop may run on the loaded 2-core host before it counts as stalled (the latest seen: 0.6 s
for the arm's tick that held it, 0.4 s for the agent's), for the wall-clock hold: the watchdog itself is judged in
the arm's own ticks, exactly."""


@dataclass
class Link:
    """One arm and one agent, and what a fault needs of them: ``domain`` (the arm's bus domain, for a new process to
    look at after each fault; None for a ROS 1 arm), ``ros1_master`` and ``ros1_home`` (a ROS 1 arm's master, for a
    new rospy process to look at instead), ``env`` (the processes' environment) and ``restart_registry`` (kills the
    domain's registry process and returns what starts it again at the same URI; None when the registry lives in the
    arm's process)."""

    pair: NetnsPair
    arm: EventPeer
    agent: EventPeer
    domain: str | None = None
    env: dict[str, str] = field(default_factory=dict)
    restart_registry: Callable[[], Callable[[], None]] | None = None
    ros1_master: str | None = None
    ros1_home: Path | None = None


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


def _drop_output(link: Link) -> Callable[[], None]:
    link.pair.drop_output()
    return link.pair.clear


def _remove_address(link: Link) -> Callable[[], None]:
    link.pair.remove_address()
    return link.pair.restore_address


def _block_registry_port(link: Link) -> Callable[[], None]:
    assert link.domain is not None
    link.pair.block_port(int(link.domain.rsplit(":", 1)[1]))
    return link.pair.clear


def _restart_registry(link: Link) -> Callable[[], None]:
    assert link.restart_registry is not None, "this link's registry is in the arm's process"
    return link.restart_registry()


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
    # the arm's connection to its own registry cut too
    "arm output dropped": (_drop_output, True),
    "arm address removed": (_remove_address, True),
    "registry port blocked": (_block_registry_port, False),  # data does not pass through the registry
    "registry restarted": (_restart_registry, False),
}


@dataclass
class Trial:
    """One fault on one link, and how to judge it (``robot``: the link's name in the figures; ``check_ages``: the
    arm checks command stamps)."""

    link: Link
    name: str
    robot: str
    check_ages: bool = True
    t_fault: int = 0
    t_clear: int = 0


def groups(names: list[str], links: int) -> list[list[str]]:
    """``names`` in groups of at most ``links``: the faults that run at once, each on a link of its own."""
    return [names[i : i + links] for i in range(0, len(names), links)]


def run_faults(
    trials: list[Trial],
    duration_s: float,
    *,
    robot_timeout_s: float,
    command_timeout_s: float,
    period_s: float,
) -> list[dict[str, Any]]:
    """Inject each trial's fault on its own link at once, for ``duration_s``, clear them, then judge each as
    ``run_fault`` does; every trial's figures are reported before the first failure is raised."""
    for trial in trials:
        left = trial.link.pair.faults_left()
        assert not left, f"{trial.robot}: the link is not clean before {trial.name!r}: {left}"
        try:
            trial.link.agent.wait_for(time.monotonic_ns(), "step", RECOVER_S, "a step before the fault")
        except AssertionError as exc:
            raise AssertionError(f"{trial.robot}, before {trial.name!r} ({duration_s} s): {exc}") from None
    clears: list[Callable[[], None]] = []
    try:
        for trial in trials:
            # the fault is in effect once its command has returned (spawning ip/nft can take a while when loaded)
            clears.append(FAULTS[trial.name][0](trial.link))
            trial.t_fault = time.monotonic_ns()
        time.sleep(duration_s)  # the fault's duration: the things under test run meanwhile
    finally:
        # Every trial's fault is cleared, each even when another's clear fails, and a link whose injection raised
        # half way is cleared too: a fault left in place would fail every later round on that link.
        failed: list[str] = []
        for i, trial in enumerate(trials):
            clear = clears[i] if i < len(clears) else trial.link.pair.clear
            try:
                clear()
            except Exception as exc:  # noqa: BLE001 - reported below, after the others were cleared
                failed.append(f"clearing {trial.name!r} on {trial.robot}: {exc!r}")
            trial.t_clear = time.monotonic_ns()
        if failed:
            raise RuntimeError("\n".join(failed))
    rows, failures = [], []
    for trial in trials:
        try:
            rows.append(
                _judge(
                    trial,
                    duration_s,
                    robot_timeout_s=robot_timeout_s,
                    command_timeout_s=command_timeout_s,
                    period_s=period_s,
                )  # fmt: skip
            )
        except AssertionError as exc:
            failures.append(f"{trial.name} on {trial.robot} ({duration_s} s): {exc}")
    assert not failures, "\n".join(failures)
    return rows


def run_fault(
    link: Link,
    name: str,
    duration_s: float,
    *,
    robot: str,
    robot_timeout_s: float,
    command_timeout_s: float,
    period_s: float,
    check_ages: bool = True,
) -> dict[str, Any]:
    """Inject fault ``name`` for ``duration_s``, clear it, wait for the agent's recovery, check the goals (and, on a
    bus arm, that a new process sees the arm's topics and gets its states); returns the figures (``fault_figures``,
    with ``duration_s`` and the probe's), also appended to ``$UNIROS_FAULT_REPORT`` when set."""
    trial = Trial(link, name, robot, check_ages)
    return run_faults(
        [trial], duration_s, robot_timeout_s=robot_timeout_s, command_timeout_s=command_timeout_s, period_s=period_s
    )[0]


def _judge(
    trial: Trial, duration_s: float, *, robot_timeout_s: float, command_timeout_s: float, period_s: float
) -> dict[str, Any]:
    link, name, check_ages = trial.link, trial.name, trial.check_ages
    t_fault, t_clear = trial.t_fault, trial.t_clear
    must_notice = FAULTS[name][1]
    arm, agent = link.arm, link.agent
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
    row["link"] = trial.robot
    row["duration_s"] = duration_s
    if link.domain is not None:
        seen = probe_domain(link.pair, link.env, link.domain, "/rx200/joint_states", "/rx200/reset")
        row["new_process_sees_arm"] = seen["topics"].get("/rx200/joint_states") == ["/rx200/servo_sim"] and bool(
            seen["services_listed"].get("/rx200/reset")
        )
        row["new_process_first_state_s"] = seen["first_message_s"]["/rx200/joint_states"]
    elif link.ros1_master is not None and link.ros1_home is not None:
        seen = probe_ros1(link.pair, link.ros1_master, link.ros1_home, "/rx200/joint_states")
        row["new_process_sees_arm"] = "/rx200/joint_states" in seen["topics"]
        row["new_process_first_state_s"] = seen["first_message_s"]
    report(row)
    assert link.arm.proc.poll() is None and link.agent.proc.poll() is None, "no process restarted: both still run"
    # the goal: the next good step within the robot timeout and RECOVER_GOAL_S of the link's return
    assert row["recovery_after_clear_s"] <= robot_timeout_s + RECOVER_GOAL_S, row
    if "new_process_sees_arm" in row:
        assert row["new_process_sees_arm"], seen
        assert row["new_process_first_state_s"] is not None, seen
    errors = uncaught(agent)
    assert not errors, errors[0]["tb"]
    if check_ages:
        assert row["stale_commands_applied"] == 0, row
        # no step returned on a state older than the timeout, by its own stamp (the arm shares this clock)
        assert row["max_state_stamp_age_at_step_s"] <= robot_timeout_s + CODE_PATH_S, row
    assert any(e["ev"] == "cmd" and e["applied"] and e["t_ns"] <= t_fault for e in arm.events), "no command before"
    if must_notice and duration_s >= NOTICE_FROM_S:
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
