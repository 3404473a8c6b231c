"""The `uniros` command as a user runs it: a real subprocess against a domain served by the test."""

from __future__ import annotations

import asyncio
import os
import re
import sys

import numpy as np
import pytest

from uniros_async.bus import open_domain, open_node, reliable
from uniros_async.bus.messages import Header, JointState, Text

pytestmark = pytest.mark.slow


async def uniros(*args: str, domain: str | None = None, timeout_s: float = 60) -> tuple[int, str, str]:
    env = dict(os.environ)
    env.pop("UNIROS_DOMAIN", None)
    if domain:
        env["UNIROS_DOMAIN"] = domain
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "uniros_async.cli",
        *args,
        env=env,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    try:
        async with asyncio.timeout(timeout_s):
            out, err = await proc.communicate()
    except TimeoutError:
        proc.kill()
        await proc.wait()
        raise
    return proc.returncode or 0, out.decode(), err.decode()


@pytest.mark.serial  # times replies against the bus's rates
async def test_introspection_commands() -> None:
    async with open_domain() as domain, open_node("arm", domain=domain, namespace="/rx200") as arm:
        pub = await arm.create_publisher(JointState, "joint_states")
        cmd_sub = await arm.create_subscription(Text, "/cmd", qos=reliable(10))
        seq = 0

        def tick() -> None:
            nonlocal seq
            seq += 1
            pub.publish(
                JointState(
                    header=Header(stamp_ns=arm.now_ns(), seq=seq),
                    name=("waist",),
                    position=np.array([0.5]),
                    velocity=np.zeros(1),
                    effort=np.zeros(1),
                )
            )

        arm.create_timer(0.02, tick)  # 50 Hz
        await arm.set_parameter("/rx200/rate_hz", 10)

        rc, out, err = await uniros("node", "list", domain=domain.uri)
        assert rc == 0, err
        assert "/rx200/arm" in out

        rc, out, err = await uniros("topic", "list", domain=domain.uri)
        assert rc == 0, err
        assert "/rx200/joint_states  [JointState]  pubs: /rx200/arm" in out

        rc, out, err = await uniros(
            "topic", "echo", "/rx200/joint_states", "-n", "2", "--timeout", "20", "--domain", domain.uri
        )
        assert rc == 0, err
        assert out.count("---") == 2 and "position: [0.5]" in out

        rc, out, err = await uniros(
            "topic", "hz", "/rx200/joint_states", "--reports", "1", "--window", "2", domain=domain.uri
        )
        assert rc == 0, err
        # what hz computes from its own receive times, whatever the host's load: a rate (1 / mean interval)
        # between 1 / max and 1 / min interval, and at least (count - 1) / window (a receive the loop resumes late
        # may stretch the window: twice the window bounds it); a count no larger than the 50 Hz timer, which never
        # fires twice in a period, published in the window (with 0.5 s for the subscription to take effect). How
        # close the rate comes to 50 Hz is the host's
        rate, min_ms, max_ms, count = (float(x) for x in re.findall(r"(?:rate:|min|max|window:) ([\d.]+)", out))
        assert 2 <= count <= (2.0 + 0.5) * 50 + 1, out
        assert min_ms - 0.01 <= 1000 / rate <= max_ms + 0.01 and rate >= (count - 1) / (2 * 2.0), out

        rc, out, err = await uniros("topic", "pub", "/cmd", "Text", "{data: hello arm}", domain=domain.uri)
        assert rc == 0, err
        async with asyncio.timeout(5):
            assert (await cmd_sub.receive()).data == "hello arm"

        rc, out, err = await uniros("param", "get", "/rx200", domain=domain.uri)
        assert rc == 0 and "rate_hz: 10" in out, (out, err)
        rc, out, err = await uniros("param", "set", "/rx200/gains", "[1, 2]", domain=domain.uri)
        assert rc == 0, err
        assert await arm.get_parameter("/rx200/gains") == [1, 2]


async def test_clear_errors(tmp_path) -> None:  # type: ignore[no-untyped-def]
    rc, out, err = await uniros("node", "list")
    assert rc == 2 and "UNIROS_DOMAIN" in err
    rc, out, err = await uniros("bench", "throughput", "--quick", "--n-envs", "8")  # refused before any process starts
    assert rc == 2 and "--quick runs N <= 4 only, and n_envs (8,) has none" in err
    async with open_domain() as domain:
        rc, out, err = await uniros("param", "get", "/missing", domain=domain.uri)
        assert rc == 2 and "/missing" in err
        rc, out, err = await uniros("topic", "echo", "/nothing", "--timeout", "1", domain=domain.uri)
        assert rc == 2 and "no topic '/nothing'" in err
        rc, out, err = await uniros("topic", "pub", "/x", "NoSuchType", "{}", domain=domain.uri)
        assert rc == 2 and "unknown message type 'NoSuchType'" in err
        f = tmp_path / "p.yaml"
        f.write_text("a: 1\nb: {c: 2}\n")
        rc, out, err = await uniros("param", "load", str(f), "--namespace", "/ns", domain=domain.uri)
        assert rc == 0 and "loaded 2" in out, (out, err)


def test_every_option_and_argument_has_help_text() -> None:
    """`uniros ... --help` explains every flag (argparse prints a bare name for one without help)."""
    import argparse

    from uniros_async.cli import _build_parser

    missing = []

    def walk(parser: argparse.ArgumentParser, path: list[str]) -> None:
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, child in action.choices.items():
                    walk(child, [*path, name])
            elif not action.help:
                missing.append(f"uniros {' '.join(path)} {'/'.join(action.option_strings) or action.dest}")

    walk(_build_parser(), [])
    assert not missing, missing
