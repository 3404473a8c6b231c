"""Faults on the link to a ROS 1 arm: a real rosmaster and our sim as the arm's ROS 1 driver (``uniros robot serve
--ros1-master``) in one network namespace, the agent with the ROS 1 bridge in its env (``robot="ros1://..."``) in
another, joined by a veth pair (``rig.netfault``). Each fault lasts each of ``DURATIONS_S``; measured as in
test_tcp_arm_faults.py.

ROS 1 cannot authenticate peers, so the driver and the bridge are allowed beyond loopback (``--insecure``,
``ros1={"insecure": True}``): only the two namespaces the test creates can reach them.

A command's age at the arm is not checked here: the driver's ``interbotix_xs_msgs/JointGroupCommand`` carries no
stamp, so the arm can only count from a command's arrival (``--max-command-age`` is refused for this driver). That no
command older than the robot timeout reaches it after a partition is test_ros1_stale_commands.py.
"""

from __future__ import annotations

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
    require_ros1,
    start_agent,
    start_ros1_driver,
    start_rosmaster,
    stopping,
)
from ._faults import DURATIONS_S, Link, run_fault

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("netfault_ready")]

ROS1_FAULTS = ["partition", "loss 10 %", "tcp reset", "link down", "frozen arm (SIGSTOP)"]


@pytest.fixture(scope="module")
def ros1_link(netfault_ready: None, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Link]:
    require_ros1()
    home = Path(tmp_path_factory.mktemp("ros_home"))
    with open_netns_pair() as pair, stopping() as peers:
        master_uri, _ = start_rosmaster(pair, peers, home)
        arm = start_ros1_driver(pair, peers, master_uri, ["--command-timeout", str(COMMAND_TIMEOUT_S), "--trace"])
        agent = start_agent(pair, peers, f"ros1://{pair.arm_ip}:{MASTER_PORT}", ros_host=pair.env_ip)
        agent.wait_for(0, "step", START_S, "the agent's first step")
        yield Link(pair, arm, agent)


@pytest.mark.parametrize(("name", "duration_s"), [(n, d) for n in ROS1_FAULTS for d in DURATIONS_S])
def test_ros1_fault(ros1_link: Link, name: str, duration_s: float) -> None:
    run_fault(
        ros1_link,
        name,
        duration_s,
        robot="ros1",
        robot_timeout_s=ROBOT_TIMEOUT_S,
        command_timeout_s=COMMAND_TIMEOUT_S,
        period_s=PERIOD_S,
        check_ages=False,
    )
