"""A ``latest`` topic over tcp stays fresh on a link slower than the topic: the subscriber gets the newest messages
at the rate the link carries, not every message ever later out of a growing send buffer.

A publisher in the arm's namespace sends a 7-joint JointState at 10 Hz (about 3.5 kB/s with the headers) over a
link starved to 8 kbit/s (``NetnsPair.starve``: a ``tbf`` qdisc on both ends); a subscriber in the env's namespace
prints each message's age by its stamp (one monotonic clock for every namespace of the machine). Without the
sink's wait for its last frame to leave (``pubsub._Sink``), the ages grew by about 0.8 s a second here.
"""

from __future__ import annotations

import json
import os
import secrets
import statistics
import subprocess
import sys
import time

import pytest
from rig.netfault import open_netns_pair

pytestmark = pytest.mark.slow

STARVE_S = 15.0
PORT = 7455

_PUBLISHER = """
import asyncio, dataclasses, sys, time
import numpy as np
from uniros_async.bus import open_domain, open_node, latest
from uniros_async.bus.messages import Header, JointState
from uniros_async.transports.base import options_from_environ

async def main(host, port):
    opts = dataclasses.replace(options_from_environ(), bind_host=host)
    async with open_domain(f"tcp://{host}:{port}", options=opts) as domain:
        async with open_node("arm", domain=domain, transport="tcp", options=opts) as node:
            pub = await node.create_publisher(JointState, "/js", qos=latest())
            print("ready", flush=True)
            names, zeros, seq = [f"joint_{i}" for i in range(7)], np.zeros(7), 0
            while True:
                seq += 1
                header = Header(seq=seq, stamp_ns=time.monotonic_ns())
                pub.publish(JointState(header=header, name=names, position=zeros, velocity=zeros, effort=zeros))
                await asyncio.sleep(0.1)

asyncio.run(main(sys.argv[1], int(sys.argv[2])))
"""

_SUBSCRIBER = """
import asyncio, json, sys, time
from uniros_async.bus import open_node, latest
from uniros_async.bus.messages import JointState

async def main(uri):
    async with open_node("env", domain=uri, transport="tcp") as node:
        sub = await node.create_subscription(JointState, "/js", qos=latest())
        async for msg in sub:
            now = time.monotonic_ns()
            age_s = (now - msg.header.stamp_ns) / 1e9
            print(json.dumps({"t_ns": now, "seq": msg.header.seq, "age_s": age_s}), flush=True)

asyncio.run(main(sys.argv[1]))
"""


def _read_until(proc: subprocess.Popen[str], t_end: float, into: list[dict[str, float]]) -> None:
    assert proc.stdout is not None
    while time.monotonic() < t_end:
        line = proc.stdout.readline()
        if not line:
            raise AssertionError(f"the subscriber exited ({proc.poll()})")
        into.append(json.loads(line))


def test_a_latest_topic_stays_fresh_on_a_starved_link(netfault_ready: None) -> None:
    env = {**os.environ, "UNIROS_AUTH_KEY": secrets.token_hex(16)}
    with open_netns_pair() as pair:
        procs = []
        try:
            pub = pair.popen("arm", [sys.executable, "-c", _PUBLISHER, pair.arm_ip, str(PORT)], env=env)
            procs.append(pub)
            assert pub.stdout is not None and pub.stdout.readline().strip() == "ready"
            sub = pair.popen("env", [sys.executable, "-c", _SUBSCRIBER, f"tcp://{pair.arm_ip}:{PORT}"], env=env)
            procs.append(sub)
            before: list[dict[str, float]] = []
            _read_until(sub, time.monotonic() + 3.0, before)
            assert before and max(e["age_s"] for e in before[-10:]) < 0.2, before[-10:]
            pair.starve("8kbit")
            t_starve = time.monotonic_ns()
            starved: list[dict[str, float]] = []
            try:
                _read_until(sub, time.monotonic() + STARVE_S, starved)
            finally:
                pair.clear()
            t_clear = time.monotonic_ns()
            after: list[dict[str, float]] = []
            _read_until(sub, time.monotonic() + 4.0, after)
        finally:
            for p in procs:
                p.kill()
                p.wait(10)
                if p.stdout is not None:
                    p.stdout.close()
    # the second half of the starved stretch: the link carries a fraction of the messages, each of them fresh
    late = [e["age_s"] for e in starved if e["t_ns"] >= t_starve + STARVE_S / 2 * 1e9]
    assert len(late) >= 5, f"{len(late)} messages in the last {STARVE_S / 2} s of the starved link"
    assert statistics.median(late) < 2.5 and max(late) < 4.0, late
    # the link back: fresh again within a couple of seconds, the seqs still in order
    fresh = [e["age_s"] for e in after if e["t_ns"] >= t_clear + 2e9]
    assert fresh and max(fresh) < 0.2, after
    seqs = [e["seq"] for e in before + starved + after]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
