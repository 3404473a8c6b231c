"""Faults on the link to a served arm (``uniros robot serve`` over tcp), the arm and the agent each in a network
namespace of their own joined by a veth pair (``uniros_async.testing.netfault``).

One arm and one agent run for the whole module; each test injects one fault for ``FAULT_S``, clears it, and
measures from both sides' event lines (one ``time.monotonic_ns()`` clock across the namespaces):

- hold: from the fault to the arm's watchdog holding it, and from the last command it applied to that hold;
- notice: from the fault to the agent's first ``RobotError`` (or none, when the link still carried enough);
- recovery: from clearing the fault to the agent's next successful step, in the same agent process;
- stale: commands the arm applied that were older than the robot timeout (must be none), and those it dropped;
- uncaught: exceptions other than ``RobotError`` the agent saw (must be none).

``UNIROS_FAULT_REPORT=PATH`` appends each fault's figures as a JSON line to PATH (docs/reliability.md's tables).
No delay or jitter fault here: this kernel has no netem, and a delaying relay is not part of this suite.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest

from uniros_async.testing.netfault import NetnsPair, open_netns_pair

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("netfault_ready")]

ROBOT_TIMEOUT_S = 0.5
COMMAND_TIMEOUT_S = 0.5
PERIOD_S = 0.1  # rx200: 10 Hz
FAULT_S = 2.0
RECOVER_S = 15.0
SLACK_S = 0.25
"""Scheduling slack on a shared 2-core machine."""
PORT = 7000


@dataclass
class Peer:
    proc: subprocess.Popen[str]
    events: list[dict[str, Any]] = field(default_factory=list)
    lines: list[str] = field(default_factory=list)
    reader: threading.Thread | None = None

    def start_reader(self) -> None:
        def read() -> None:
            assert self.proc.stdout is not None
            for line in self.proc.stdout:
                self.lines.append(line)
                if line.startswith("{"):
                    self.events.append(json.loads(line))

        self.reader = threading.Thread(target=read, daemon=True)
        self.reader.start()

    def after(self, t_ns: int, ev: str) -> list[dict[str, Any]]:
        return [e for e in list(self.events) if e["ev"] == ev and e["t_ns"] >= t_ns]

    def wait_for(self, t_ns: int, ev: str, timeout_s: float, what: str) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        while True:
            found = self.after(t_ns, ev)
            if found:
                return found[0]
            if self.proc.poll() is not None or time.monotonic() > deadline:
                tail = "".join(self.lines[-20:])
                raise AssertionError(f"no {ev!r} event ({what}) within {timeout_s} s; output:\n{tail}")
            time.sleep(0.02)


@dataclass
class Link:
    pair: NetnsPair
    arm: Peer
    agent: Peer


def _stop(proc: subprocess.Popen[str], peer: Peer | None = None) -> None:
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGCONT)  # a frozen arm cannot handle SIGTERM
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
    if peer is not None and peer.reader is not None:
        peer.reader.join(5)
    if proc.stdout is not None:
        proc.stdout.close()


@pytest.fixture(scope="module")
def link(netfault_ready: None) -> Iterator[Link]:
    py = sys.executable
    with open_netns_pair() as pair:
        arm_proc = pair.popen(
            "arm",
            [py, "-m", "uniros_async.cli", "robot", "serve", "rx200", "--host", pair.arm_ip, "--port", str(PORT),
             "--command-timeout", str(COMMAND_TIMEOUT_S), "--max-command-age", str(ROBOT_TIMEOUT_S), "--trace"],
        )  # fmt: skip
        agent_proc: subprocess.Popen[str] | None = None
        arm = Peer(arm_proc)
        agent: Peer | None = None
        try:
            assert arm_proc.stdout is not None
            uri = arm_proc.stdout.readline().strip()
            assert uri == f"tcp://{pair.arm_ip}:{PORT}", uri
            arm.start_reader()
            agent_proc = pair.popen(
                "env",
                [py, "-m", "uniros_async.testing.netfault", "drive", "--robot", uri,
                 "--robot-timeout", str(ROBOT_TIMEOUT_S), "--action-cycle", "0.2"],
            )  # fmt: skip
            agent = Peer(agent_proc)
            agent.start_reader()
            agent.wait_for(0, "step", 60, "the agent's first step")
            yield Link(pair, arm, agent)
        finally:
            if agent_proc is not None:
                _stop(agent_proc, agent)
            _stop(arm_proc, arm)


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


@pytest.mark.parametrize("name", list(FAULTS))
def test_fault(link: Link, name: str) -> None:
    inject, must_notice = FAULTS[name]
    arm, agent = link.arm, link.agent
    agent.wait_for(time.monotonic_ns(), "step", RECOVER_S, "a step before the fault")
    t_fault = time.monotonic_ns()
    clear = inject(link)
    try:
        time.sleep(FAULT_S)  # the fault's duration: the thing under test runs meanwhile
    finally:
        t_clear = time.monotonic_ns()
        clear()
    recovered = agent.wait_for(t_clear, "step", RECOVER_S, "recovery after the fault was cleared")
    time.sleep(0.5)  # what the arm applies right after recovery is judged too

    s = 1e-9
    errors = [e for e in agent.events if e["ev"] == "robot_error" and t_fault <= e["t_ns"] <= t_clear]
    uncaught = [e for e in agent.events if e["ev"] == "error"]
    holds = arm.after(t_fault, "hold")
    cmds = [e for e in arm.events if e["ev"] == "cmd" and e["t_ns"] >= t_fault]
    applied_before = [e for e in arm.events if e["ev"] == "cmd" and e["applied"] and e["t_ns"] <= t_fault]
    stale_applied = [e for e in arm.events if e["ev"] == "cmd" and e["applied"] and e["age_ns"] > ROBOT_TIMEOUT_S / s]
    dropped = [e for e in cmds if not e["applied"]]
    hold = holds[0] if holds else None
    last_cmd = [e for e in arm.events if e["ev"] == "cmd" and e["applied"] and hold and e["t_ns"] < hold["t_ns"]]
    row = {
        "fault": name,
        "hold_after_fault_s": round((hold["t_ns"] - t_fault) * s, 3) if hold else None,
        "hold_after_last_command_s": round((hold["t_ns"] - last_cmd[-1]["t_ns"]) * s, 3) if hold and last_cmd else None,
        "notice_after_fault_s": round((errors[0]["t_ns"] - t_fault) * s, 3) if errors else None,
        "agent_saw": errors[0]["msg"] if errors else "no error",
        "robot_errors": len(errors),
        "recovery_after_clear_s": round((recovered["t_ns"] - t_clear) * s, 3),
        "stale_commands_applied": len(stale_applied),
        "stale_commands_dropped": len(dropped),
        "max_age_applied_s": round(max((e["age_ns"] for e in cmds if e["applied"]), default=0) * s, 3),
        "uncaught_exceptions": len(uncaught),
    }
    _report(row)
    print(json.dumps(row))
    assert not uncaught, uncaught[0]["tb"]
    assert not stale_applied, stale_applied[:3]
    assert applied_before, "the arm applied no command before the fault"
    if must_notice:
        assert errors, f"{name}: the agent saw no RobotError"
        assert errors[0]["t_ns"] - t_fault <= (ROBOT_TIMEOUT_S + PERIOD_S + SLACK_S) / s, row
        assert "s old" in errors[0]["msg"] and "rx200" in errors[0]["msg"], errors[0]["msg"]
    if hold is not None and last_cmd:
        assert hold["t_ns"] - last_cmd[-1]["t_ns"] <= (COMMAND_TIMEOUT_S + PERIOD_S + SLACK_S) / s, row
