"""A real multi-node Ray cluster per test module, for the Ray backend's tests.

These modules run only inside a network namespace (``UNIROS_RAY_NETNS=1``, set by tests/runtime/test_runtime_ray.py,
which starts them under ``unshare --net`` with only ``lo`` up): outside one, Ray would bind the host's own interface.
Collected anywhere else, they are left out. The cluster: a head (where the agent runs) and an "arm PC" node that
alone advertises ``rx200_arm: 1``, small CPU counts, no dashboard. On teardown no Ray process and no new /dev/shm
segment may be left.
"""

from __future__ import annotations

import os
import subprocess
import time
from collections.abc import Iterator
from typing import Any

import pytest

if os.environ.get("UNIROS_RAY_NETNS") != "1":
    collect_ignore_glob = ["test_*.py"]

RAY_PROCESSES = "raylet|gcs_server|ray::|dashboard/agent.py|log_monitor.py|runtime_env/agent"
OURS_IN_DEV_SHM = ("plasma", "ray", "uniros", "psm_")
"""/dev/shm names Ray's object store, our code or multiprocessing could create (our shm transport uses memfds and
creates none); other users of this shared host make their own (ROS 2's fastrtps_*), which are not ours to judge."""
OBJECT_STORE_BYTES = 80 * 1024 * 1024


def ray_processes() -> list[str]:
    """The Ray processes running now (command lines)."""
    out = subprocess.run(["pgrep", "-af", RAY_PROCESSES], capture_output=True, text=True, check=False).stdout
    return [line for line in out.splitlines() if "pgrep" not in line]


def host_processes() -> list[str]:
    """The uniros worker-host actors running now (their process titles)."""
    return [p for p in ray_processes() if "_WorkerHost" in p]


def dev_shm() -> set[str]:
    """The /dev/shm entries that Ray, multiprocessing or uniros could have made."""
    return {n for n in os.listdir("/dev/shm") if n.startswith(OURS_IN_DEV_SHM)}


def wait_until(predicate: Any, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout_s} s: {what}")
        time.sleep(0.05)


def alive_hosts() -> list[dict[str, Any]]:
    """The uniros worker-host actors the cluster's GCS holds alive."""
    import ray

    return [
        a
        for a in ray._private.state.actors().values()  # the GCS's actor table (the state API needs the dashboard)
        if a.get("State") not in ("DEAD",) and "_WorkerHost" in str(a.get("ActorClassName", ""))
    ]


@pytest.fixture(scope="module")
def cluster() -> Iterator[dict[str, Any]]:
    """A head node (the agent's) and an arm node (``rx200_arm: 1``); ``ray`` connected; torn down after the module."""
    import ray
    from ray.cluster_utils import Cluster

    wait_until(lambda: not ray_processes(), 20.0, f"Ray processes before the cluster started: {ray_processes()}")
    shm_before = dev_shm()
    c = Cluster(
        initialize_head=True,
        head_node_args={"num_cpus": 4, "include_dashboard": False, "object_store_memory": OBJECT_STORE_BYTES},
    )
    try:
        arm = c.add_node(num_cpus=4, resources={"rx200_arm": 1}, object_store_memory=OBJECT_STORE_BYTES)
        ray.init(address=c.address, log_to_driver=True)
        head_id = ray.get_runtime_context().get_node_id()
        yield {"cluster": c, "address": c.address, "head_id": head_id, "arm": arm, "arm_id": arm.node_id}
    finally:
        ray.shutdown()
        c.shutdown()
    wait_until(lambda: not ray_processes(), 20.0, f"Ray processes left: {ray_processes()}")
    left = dev_shm() - shm_before
    assert not left, f"/dev/shm segments left: {sorted(left)}"


@pytest.fixture
def nothing_left(cluster: dict[str, Any]) -> Iterator[None]:
    """After the test: no worker-host actor alive in the GCS, none as a process, no new /dev/shm segment."""
    shm_before = dev_shm()
    yield
    wait_until(lambda: not alive_hosts(), 10.0, f"actors left: {alive_hosts()}")
    wait_until(lambda: not host_processes(), 10.0, f"actor processes left: {host_processes()}")
    left = dev_shm() - shm_before
    assert not left, f"/dev/shm segments left: {sorted(left)}"
