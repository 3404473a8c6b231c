"""The rig's ``clear()`` undoes every fault it can inject, and ``faults_left()`` names each one in effect: a fault
left in place by one round would otherwise fail every later round on the same link."""

from __future__ import annotations

import subprocess
import sys

import pytest
from rig.netfault import NetnsPair, open_netns_pair

_SERVE = """
import socket, sys
s = socket.create_server((sys.argv[1], 0))
print(s.getsockname()[1], flush=True)
s.settimeout(10)
c, _ = s.accept()
c.sendall(b"ok")
"""
_CONNECT = """
import socket, sys
print(socket.create_connection((sys.argv[1], int(sys.argv[2])), timeout=5).recv(2).decode())
"""


def _carries(pair: NetnsPair) -> bool:
    """Whether a tcp connection from the env's namespace to the arm's gets the arm's answer."""
    server = pair.popen("arm", [sys.executable, "-c", _SERVE, pair.arm_ip])
    try:
        assert server.stdout is not None
        port = server.stdout.readline().strip()
        argv = ["ip", "netns", "exec", pair.env_ns, sys.executable, "-c", _CONNECT, pair.arm_ip, port]
        return subprocess.run(argv, capture_output=True, text=True, timeout=20).stdout.strip() == "ok"
    finally:
        server.kill()
        server.wait(5)
        assert server.stdout is not None
        server.stdout.close()


@pytest.mark.parametrize(
    ("inject", "named"),
    [
        (NetnsPair.partition, "uniros_fault"),
        (lambda p: p.starve("8kbit"), "tbf"),
        (NetnsPair.link_down, "is down"),
        (NetnsPair.remove_address, "has no address"),
        (lambda p: p.delay_through(7999, 77), "uniros_delay"),
    ],
    ids=["partition", "starve", "link down", "address removed", "delay table"],
)
def test_clear_removes_each_fault(netfault_ready: None, inject, named: str) -> None:
    with open_netns_pair() as pair:
        assert pair.faults_left() == []
        inject(pair)
        left = pair.faults_left()
        assert any(named in what for what in left), left
        pair.clear()
        assert pair.faults_left() == []
        assert _carries(pair), "the link carries a connection again after clear()"


def test_clear_removes_every_fault_at_once(netfault_ready: None) -> None:
    with open_netns_pair() as pair:
        pair.starve("8kbit")
        pair.partition()  # replaces nothing of the qdiscs: both are in effect
        pair.remove_address()
        pair.link_down()
        assert len(pair.faults_left()) == 5, pair.faults_left()  # two qdiscs, the table, the address, the link
        pair.clear()
        assert pair.faults_left() == []
        assert _carries(pair)
