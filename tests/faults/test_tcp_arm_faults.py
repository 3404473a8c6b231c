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
Delay and jitter are in test_tcp_arm_delay.py (this kernel has no netem: the tests' own relay adds them).
"""

from __future__ import annotations

import os
import secrets
import sys
from collections.abc import Iterator

import pytest

from uniros_async.testing.netfault import EventPeer, open_netns_pair

from ._faults import FAULTS, Link, run_fault

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("netfault_ready")]

ROBOT_TIMEOUT_S = 0.5
COMMAND_TIMEOUT_S = 0.5
PERIOD_S = 0.1  # rx200: 10 Hz
PORT = 7000


@pytest.fixture(scope="module")
def link(netfault_ready: None) -> Iterator[Link]:
    py = sys.executable
    # a listener beyond loopback needs the domain's key: the arm's domain and the env's node both read it
    env = {**os.environ, "UNIROS_AUTH_KEY": secrets.token_hex(16)}
    with open_netns_pair() as pair:
        arm_proc = pair.popen(
            "arm",
            [py, "-m", "uniros_async.cli", "robot", "serve", "rx200", "--host", pair.arm_ip, "--port", str(PORT),
             "--command-timeout", str(COMMAND_TIMEOUT_S), "--max-command-age", str(ROBOT_TIMEOUT_S), "--trace"],
            env=env,
        )  # fmt: skip
        arm = EventPeer(arm_proc)
        agent: EventPeer | None = None
        try:
            assert arm_proc.stdout is not None
            uri = arm_proc.stdout.readline().strip().split("=", 1)[-1]  # export UNIROS_DOMAIN=tcp://...
            assert uri == f"tcp://{pair.arm_ip}:{PORT}", uri
            arm.start_reader()
            agent_proc = pair.popen(
                "env",
                [py, "-m", "uniros_async.testing.netfault", "drive", "--robot", uri,
                 "--robot-timeout", str(ROBOT_TIMEOUT_S), "--action-cycle", "0.2"],
                env=env,
            )  # fmt: skip
            agent = EventPeer(agent_proc)
            agent.start_reader()
            agent.wait_for(0, "step", 60, "the agent's first step")
            yield Link(pair, arm, agent)
        finally:
            if agent is not None:
                agent.stop()
            arm.stop()


@pytest.mark.parametrize("name", list(FAULTS))
def test_fault(link: Link, name: str) -> None:
    run_fault(
        link,
        name,
        robot="tcp",
        robot_timeout_s=ROBOT_TIMEOUT_S,
        command_timeout_s=COMMAND_TIMEOUT_S,
        period_s=PERIOD_S,
    )
