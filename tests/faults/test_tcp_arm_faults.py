"""Faults on the link to a served arm (``uniros robot serve`` over tcp), the arm and the agent each in a network
namespace of their own joined by a veth pair (``rig.netfault``).

Four arms, each with its agent, run for the whole module, each pair of them in namespaces of their own; each test
injects a round of faults at once, one per rig, for each of ``DURATIONS_S`` (0.5 s, 5 s, 30 s: short, past the
robot timeout and a reset, past every keepalive), clears them, and measures each from both sides' event lines (one
``time.monotonic_ns()`` clock across the namespaces):

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

import contextlib
from collections.abc import Callable, Iterator

import pytest
from rig.netfault import EventPeer, NetnsPair, open_netns_pair

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
from ._faults import DURATIONS_S, FAULTS, Link, Trial, run_faults

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("netfault_ready")]


RIGS = 3
"""Served arms (``uniros robot serve``), each with its agent in a namespace pair of its own, beside the rig whose
registry runs in a process of its own: the faults of a round run at once, one per rig, so that the suite waits
for a 30 s fault once per round rather than once per fault."""
ROUNDS = [
    ["registry restarted", "partition", "loss 1 %", "loss 10 %"],
    ["registry port blocked", "loss 50 %", "tcp reset", "starved link (tbf 8 kbit/s)"],
    ["arm address removed", "arm output dropped", "link down", "frozen arm (SIGSTOP)"],
]
"""The faults of each round, in the order of ``rigs``: the registry's own rig first. Every fault once."""
assert sorted(n for r in ROUNDS for n in r) == sorted(FAULTS)


def _start_served_rig(pair: NetnsPair, peers: list[EventPeer], env: dict[str, str]) -> Link:
    arm, uri = start_tcp_arm(pair, peers, env)
    return Link(pair, arm, start_agent(pair, peers, uri, env=env), domain=uri, env=env)


def _start_registry_rig(pair: NetnsPair, peers: list[EventPeer], env: dict[str, str]) -> Link:
    """The arm joined to a registry in a process of its own (both in the arm's namespace), the agent on it."""
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
    return Link(pair, arm, agent, domain=uri, env=env, restart_registry=restart)


@pytest.fixture(scope="module")
def rigs(netfault_ready: None) -> Iterator[list[tuple[str, Link]]]:
    """The registry's own rig, then ``RIGS`` served arms: (name in the figures, link) each."""
    env, shm = auth_env(), shm_names()
    with contextlib.ExitStack() as stack:
        pairs = [stack.enter_context(open_netns_pair()) for _ in range(RIGS + 1)]
        peers = stack.enter_context(stopping())
        links = [("tcp (registry in its own process)", _start_registry_rig(pairs[0], peers, env))]
        links += [("tcp", _start_served_rig(pair, peers, env)) for pair in pairs[1:]]
        for _, link in links:
            link.agent.wait_for(0, "step", START_S, "the agent's first step")
        yield links
    for pair in pairs:
        assert_nothing_left(pair, peers, shm)


@pytest.mark.parametrize(
    ("faults", "duration_s"),
    [(r, d) for r in ROUNDS for d in DURATIONS_S],
    ids=[f"{'+'.join(r)}-{d:g}s" for r in ROUNDS for d in DURATIONS_S],
)
def test_faults(rigs: list[tuple[str, Link]], faults: list[str], duration_s: float) -> None:
    trials = [Trial(link, name, robot) for name, (robot, link) in zip(faults, rigs, strict=False)]
    run_faults(
        trials,
        duration_s,
        robot_timeout_s=ROBOT_TIMEOUT_S,
        command_timeout_s=COMMAND_TIMEOUT_S,
        period_s=PERIOD_S,
    )
