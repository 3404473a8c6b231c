"""Hostile peers against a live domain and a served arm (`uniros robot serve rx200`, a real process): every attack
of ``_attacks`` on the domain's port and on the arm node's own tcp port, while a legitimate node reads every joint
state (reliable QoS: none may be missing) and keeps asking the domain for a parameter.

Asserted: the server process survives, no legitimate message is lost, every parameter request is answered, the
server's RSS grows by less than 64 MiB while 1,000 connections are held, and its log stays rate-limited.
"""

from __future__ import annotations

import asyncio
import subprocess
import time
from pathlib import Path

import pytest

from tests.hostile import _attacks, _served
from uniros_async.bus import open_node
from uniros_async.bus.messages import JointState
from uniros_async.bus.qos import reliable

pytestmark = pytest.mark.slow


def _start_serve(log: Path) -> tuple[subprocess.Popen[str], str]:
    """The served arm, and its domain's URI (the line a shell would run: ``export UNIROS_DOMAIN=tcp://...``)."""
    proc, line = _served.start_serve([], log, unset=("UNIROS_AUTH_KEY",))
    uri = line.removeprefix("export UNIROS_DOMAIN=")
    if not uri.startswith("tcp://"):
        _served.stop_serve(proc)
        raise AssertionError(f"robot serve printed {line!r}; its log:\n{log.read_text()[-2000:]}")
    return proc, uri


async def test_domain_and_served_arm_keep_serving_under_attack(tmp_path: Path) -> None:
    _attacks.raise_fd_limit()  # before the server starts: it inherits the limit
    log = tmp_path / "serve.log"
    proc, domain_uri = _start_serve(log)
    try:
        async with asyncio.timeout(240), open_node("legit", domain=domain_uri, transport="tcp") as node:
            seqs: list[int] = []
            got_one = asyncio.Event()

            def on_state(msg: JointState) -> None:
                seqs.append(msg.header.seq)
                got_one.set()

            await node.create_subscription(JointState, "/rx200/joint_states", callback=on_state, qos=reliable(2000))
            await got_one.wait()
            pubs = await node._registry.request("subscribe", topic="/rx200/joint_states", type="JointState", node="/p")
            arm_uri = next(p["endpoints"]["tcp"] for p in pubs if "tcp" in p["endpoints"])
            await node.set_parameter("/hostile/probe", 42)

            answers = 0
            stop = asyncio.Event()

            async def ask_domain() -> None:
                nonlocal answers
                while not stop.is_set():
                    async with asyncio.timeout(5):
                        assert await node.get_parameter("/hostile/probe") == 42
                    answers += 1
                    await asyncio.sleep(0.05)

            t0 = time.monotonic()
            async with asyncio.TaskGroup() as tg:
                asker = tg.create_task(ask_domain())
                reports = {}
                for what, uri in (("domain", domain_uri), ("arm node", arm_uri)):
                    host, port = _served.host_port(uri)
                    proto = _attacks.uniros_tcp()
                    reports[what] = await _attacks.run_attacks(host, port, proto, server_pid=proc.pid, hold=1000)
                    # and a thousand that complete the handshake, then say nothing
                    reports[what + " (handshaken)"] = await _attacks.run_attacks(
                        host, port, proto, server_pid=proc.pid, hold=1000, hold_prefix=proto.valid_prefix, rounds=0
                    )
                n_before = len(seqs)
                await asyncio.sleep(1.0)  # the arm keeps publishing after the attacks
                stop.set()
                await asker
            elapsed = time.monotonic() - t0

            assert proc.poll() is None, f"robot serve died; its log:\n{log.read_text()[-3000:]}"
            _served.check_stream_whole(seqs, n_before)
            assert answers >= 10, f"only {answers} parameter requests answered in {elapsed:.1f} s"
            _served.check_rss_bounded(reports, "server")
            for what, r in reports.items():
                assert r.held >= 1000 or r.refused, f"{what}: {r}"
    finally:
        _served.stop_serve(proc)
    _served.check_log_rate_limited(log, elapsed, reports)
