"""Faults on the link to a ROS 1 arm: a real rosmaster and our sim as the arm's ROS 1 driver (``uniros robot serve
--ros1-master``) in one network namespace, the agent with the ROS 1 bridge in its env (``robot="ros1://..."``) in
another, joined by a veth pair (``rig.netfault``); three such rigs, a round of faults at once, one per rig, each
lasting each of ``DURATIONS_S``; measured as in test_tcp_arm_faults.py.

ROS 1 cannot authenticate peers, so the driver and the bridge are allowed beyond loopback (``--insecure``,
``ros1={"insecure": True}``): only the two namespaces the test creates can reach them.

A command's age at the arm is not checked here: the driver's ``interbotix_xs_msgs/JointGroupCommand`` carries no
stamp, so the arm can only count from a command's arrival (``--max-command-age`` is refused for this driver). That no
command older than the robot timeout reaches it after a partition is test_ros1_stale_commands.py.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import pytest
from rig.netfault import open_netns_pair

from ._arm import (
    COMMAND_TIMEOUT_S,
    MASTER_PORT,
    PERIOD_S,
    ROBOT_TIMEOUT_S,
    START_S,
    assert_nothing_left,
    require_ros1,
    shm_names,
    start_agent,
    start_ros1_driver,
    start_rosmaster,
    stopping,
)
from ._faults import DURATIONS_S, Link, Trial, groups, run_faults

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("netfault_ready")]

ROS1_FAULTS = ["partition", "loss 10 %", "tcp reset", "link down", "frozen arm (SIGSTOP)", "arm output dropped"]
RIGS = 3
"""ROS 1 arms (rosmaster, driver, agent), each in a namespace pair of its own: a round's faults run at once."""
ROUNDS = groups(ROS1_FAULTS, RIGS)


@pytest.fixture(scope="module")
def ros1_rigs(netfault_ready: None, tmp_path_factory: pytest.TempPathFactory) -> Iterator[list[Link]]:
    require_ros1()
    shm = shm_names()
    with contextlib.ExitStack() as stack:
        pairs = [stack.enter_context(open_netns_pair()) for _ in range(RIGS)]
        peers = stack.enter_context(stopping())
        links = []
        for pair in pairs:
            home = Path(tmp_path_factory.mktemp("ros_home"))
            master_uri, _ = start_rosmaster(pair, peers, home)
            arm = start_ros1_driver(pair, peers, master_uri, ["--command-timeout", str(COMMAND_TIMEOUT_S), "--trace"])
            agent = start_agent(pair, peers, f"ros1://{pair.arm_ip}:{MASTER_PORT}", ros_host=pair.env_ip)
            links.append(Link(pair, arm, agent, ros1_master=master_uri, ros1_home=home))
        for link in links:
            link.agent.wait_for(0, "step", START_S, "the agent's first step")
        yield links
    for pair in pairs:
        assert_nothing_left(pair, peers, shm)


@pytest.mark.parametrize(
    ("faults", "duration_s"),
    [(r, d) for r in ROUNDS for d in DURATIONS_S],
    ids=[f"{'+'.join(r)}-{d:g}s" for r in ROUNDS for d in DURATIONS_S],
)
def test_ros1_faults(ros1_rigs: list[Link], faults: list[str], duration_s: float) -> None:
    run_faults(
        [Trial(link, name, "ros1", check_ages=False) for name, link in zip(faults, ros1_rigs, strict=False)],
        duration_s,
        robot_timeout_s=ROBOT_TIMEOUT_S,
        command_timeout_s=COMMAND_TIMEOUT_S,
        period_s=PERIOD_S,
    )
