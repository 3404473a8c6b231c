"""Faults on the link to a ROS 1 arm: a real rosmaster and our sim as the arm's ROS 1 driver (``uniros robot serve
--ros1-master``) in one network namespace, the agent with the ROS 1 bridge in its env (``robot="ros1://..."``) in
another, joined by a veth pair (``uniros_async.testing.netfault``). Measured as in test_tcp_arm_faults.py.

ROS 1 cannot authenticate peers, so the driver and the bridge are allowed beyond loopback (``--insecure``,
``ros1={"insecure": True}``): only the two namespaces the test creates can reach them.

A command's age at the arm is not checked here: the driver's ``interbotix_xs_msgs/JointGroupCommand`` carries no
stamp, so the arm can only count from a command's arrival (``--max-command-age`` is refused for this driver). That no
command older than the robot timeout reaches it after a partition is test_ros1_stale_commands.py.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from uniros_async.testing.netfault import EventPeer, open_netns_pair
from uniros_async.testing.ros1 import ros1_missing, ros_env, rosmaster_bin

from ._faults import Link, run_fault

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("netfault_ready")]

ROBOT_TIMEOUT_S = 0.5
COMMAND_TIMEOUT_S = 0.5
PERIOD_S = 0.1  # rx200: 10 Hz
MASTER_PORT = 11311
ROS1_FAULTS = ["partition", "loss 10 %", "tcp reset", "link down", "frozen arm (SIGSTOP)"]


@pytest.fixture(scope="module")
def ros1_link(netfault_ready: None, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Link]:
    reason = ros1_missing()
    if reason is not None:
        if os.environ.get("UNIROS_REQUIRE_ROS") == "1":  # .ci/run: ROS 1 must be there
            pytest.fail(f"UNIROS_REQUIRE_ROS=1 but {reason}")
        pytest.skip(reason)
    py = sys.executable
    home = Path(tmp_path_factory.mktemp("ros_home"))
    with open_netns_pair() as pair:
        master_uri = f"http://{pair.arm_ip}:{MASTER_PORT}/"
        env = {**ros_env(master_uri, home=home), "ROS_HOSTNAME": pair.arm_ip}
        master = EventPeer(pair.popen("arm", [rosmaster_bin(), "--core", "-p", str(MASTER_PORT)], env=env, stderr=None))
        arm: EventPeer | None = None
        agent: EventPeer | None = None
        try:
            arm_proc = pair.popen(
                "arm",
                [py, "-m", "uniros_async.cli", "robot", "serve", "rx200", "--ros1-master", master_uri,
                 "--ros-host", pair.arm_ip, "--insecure", "--command-timeout", str(COMMAND_TIMEOUT_S), "--trace"],
            )  # fmt: skip
            arm = EventPeer(arm_proc)
            assert arm_proc.stdout is not None
            ready = arm_proc.stdout.readline().strip()
            assert ready == f"export ROS_MASTER_URI={master_uri}", ready
            arm.start_reader()
            agent = EventPeer(
                pair.popen(
                    "env",
                    [
                        py,
                        "-m",
                        "uniros_async.testing.netfault",
                        "drive",
                        "--robot",
                        f"ros1://{pair.arm_ip}:{MASTER_PORT}",
                        "--ros-host",
                        pair.env_ip,
                        "--robot-timeout",
                        str(ROBOT_TIMEOUT_S),
                        "--action-cycle",
                        "0.2",
                    ],
                )  # fmt: skip
            )
            agent.start_reader()
            agent.wait_for(0, "step", 60, "the agent's first step")
            yield Link(pair, arm, agent)
        finally:
            if agent is not None:
                agent.stop()
            if arm is not None:
                arm.stop()
            master.stop()


@pytest.mark.parametrize("name", ROS1_FAULTS)
def test_ros1_fault(ros1_link: Link, name: str) -> None:
    run_fault(
        ros1_link,
        name,
        robot="ros1",
        robot_timeout_s=ROBOT_TIMEOUT_S,
        command_timeout_s=COMMAND_TIMEOUT_S,
        period_s=PERIOD_S,
        check_ages=False,
    )
