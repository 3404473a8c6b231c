"""Faults on the link to a served arm (``uniros robot serve`` over tcp), the arm and the agent each in a network
namespace of their own joined by a veth pair (``rig.netfault``).

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

from collections.abc import Iterator

import pytest
from rig.netfault import open_netns_pair

from ._arm import COMMAND_TIMEOUT_S, PERIOD_S, ROBOT_TIMEOUT_S, START_S, auth_env, start_agent, start_tcp_arm, stopping
from ._faults import FAULTS, Link, run_fault

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("netfault_ready")]


@pytest.fixture(scope="module")
def link(netfault_ready: None) -> Iterator[Link]:
    env = auth_env()
    with open_netns_pair() as pair, stopping() as peers:
        arm, uri = start_tcp_arm(pair, peers, env)
        agent = start_agent(pair, peers, uri, env=env)
        agent.wait_for(0, "step", START_S, "the agent's first step")
        yield Link(pair, arm, agent)


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
