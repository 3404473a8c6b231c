"""Faults on the link to a served arm (``uniros robot serve`` over tcp), the arm and the agent each in a network
namespace of their own joined by a veth pair (``rig.netfault``).

One arm and one agent run for the whole module; each test injects one fault for each of ``DURATIONS_S`` (0.5 s,
5 s, 30 s: short, past the robot timeout and a reset, past every keepalive), clears it, and measures from both sides'
event lines (one ``time.monotonic_ns()`` clock across the namespaces):

- hold: from the fault to the arm's watchdog holding it, and from the last command it applied to that hold;
- notice: from the fault to the agent's first ``RobotError`` (or none, when the link still carried enough);
- recovery: from clearing the fault to the agent's next successful step, in the same agent process (the goal: within
  the robot timeout and 2 s), and then a new process in the env's namespace sees the arm's topics and gets a state;
- stale: commands the arm applied that were older than the robot timeout (must be none), and those it dropped;
- uncaught: exceptions other than ``RobotError`` the agent saw (must be none).

``UNIROS_FAULT_REPORT=PATH`` appends each fault's figures as a JSON line to PATH (docs/reliability.md's tables).
Besides the faults on the link, those that cut the arm from its own registry: the arm's namespace sends nothing
(loopback included: the served arm's node and its domain's registry share a process), its address removed and
restored, the registry's port blocked; and, on a second rig whose registry runs in a process of its own, the
registry killed and started again at the same URI. Delay and jitter are in test_tcp_arm_delay.py (this kernel has
no netem: the tests' own relay adds them).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest
from rig.netfault import open_netns_pair

from ._arm import (
    COMMAND_TIMEOUT_S,
    PERIOD_S,
    REGISTRY_PORT,
    ROBOT_TIMEOUT_S,
    START_S,
    assert_nothing_left,
    auth_env,
    shm_names,
    start_agent,
    start_arm_in_domain,
    start_registry,
    start_tcp_arm,
    stopping,
)
from ._faults import DURATIONS_S, FAULTS, Link, run_fault

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("netfault_ready")]


@pytest.fixture(scope="module")
def link(netfault_ready: None) -> Iterator[Link]:
    env, shm = auth_env(), shm_names()
    with open_netns_pair() as pair, stopping() as peers:
        arm, uri = start_tcp_arm(pair, peers, env)
        agent = start_agent(pair, peers, uri, env=env)
        agent.wait_for(0, "step", START_S, "the agent's first step")
        yield Link(pair, arm, agent, domain=uri, env=env)
    assert_nothing_left(pair, peers, shm)


@pytest.fixture(scope="module")
def registry_link(netfault_ready: None) -> Iterator[Link]:
    """The arm joined to a registry in a process of its own (both in the arm's namespace), the agent on it."""
    env, shm = auth_env(), shm_names()
    with open_netns_pair() as pair, stopping() as peers:
        uri = f"tcp://{pair.arm_ip}:{REGISTRY_PORT}"
        registry = [start_registry(pair, peers, env, uri)]

        def restart() -> Callable[[], None]:
            registry[0].proc.kill()
            registry[0].stop()

            def start() -> None:
                registry[0] = start_registry(pair, peers, env, uri)

            return start

        arm = start_arm_in_domain(pair, peers, env, uri)
        agent = start_agent(pair, peers, uri, env=env)
        agent.wait_for(0, "step", START_S, "the agent's first step")
        yield Link(pair, arm, agent, domain=uri, env=env, restart_registry=restart)
    assert_nothing_left(pair, peers, shm)


LINK_FAULTS = [name for name in FAULTS if name != "registry restarted"]


@pytest.mark.parametrize(("name", "duration_s"), [(n, d) for n in LINK_FAULTS for d in DURATIONS_S])
def test_fault(link: Link, name: str, duration_s: float) -> None:
    run_fault(
        link,
        name,
        duration_s,
        robot="tcp",
        robot_timeout_s=ROBOT_TIMEOUT_S,
        command_timeout_s=COMMAND_TIMEOUT_S,
        period_s=PERIOD_S,
    )


@pytest.mark.parametrize("duration_s", DURATIONS_S)
def test_registry_restarted(registry_link: Link, duration_s: float) -> None:
    run_fault(
        registry_link,
        "registry restarted",
        duration_s,
        robot="tcp (registry in its own process)",
        robot_timeout_s=ROBOT_TIMEOUT_S,
        command_timeout_s=COMMAND_TIMEOUT_S,
        period_s=PERIOD_S,
    )
