"""A domain registry in a process of its own, and a new process that looks at a domain, for the rejoin tests.

``python -m rig.domain_peer registry --uri tcp://HOST:PORT``: serves a domain registry at that URI (the key from
``$UNIROS_AUTH_KEY``), prints ``ready`` once it listens, and serves until SIGTERM or SIGINT. Killed and started
again at the same URI, it is a restarted registry: a new process, a new domain id, an empty graph until the nodes
rejoin.

``python -m rig.domain_peer arm --domain URI --host IP [--command-timeout S] [--max-command-age S]``: the rx200's
servo sim, as ``uniros robot serve --trace`` serves it, but joined to the domain at URI instead of an own one (so
its registry can be killed and restarted without it): prints ``export UNIROS_DOMAIN=URI`` once it serves, then its
trace events, and serves until SIGTERM.

``python -m rig.domain_peer probe --domain URI [--topic T] [--service S] [--param P]``: joins the domain as a new
node (over tcp, as from another machine, unless ``--transport``) and prints one JSON line: the topics (with their
publishers), services, nodes, and, for each ``--topic``, the first message's seconds to arrive (None: none within
``--timeout``); for each ``--service``, whether it is listed; for each ``--param``, its value. It is what a user's
``uniros topic list`` in a new shell would see.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import signal
import sys
import time
from collections.abc import Sequence
from typing import Any

__all__ = ["main"]


async def _registry(uri: str) -> None:
    from uniros_async.bus import open_domain

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    async with open_domain(uri):
        sys.stdout.write("ready\n")
        sys.stdout.flush()
        await stop.wait()


async def _arm(domain: str, host: str, command_timeout_s: float, max_command_age_s: float) -> None:
    from uniros_async._signals import cancel_on_signals
    from uniros_async.priority import raise_loop_priority
    from uniros_async.sim.serve import ServeConfig, serve_servo_sim
    from uniros_async.sim.servo import ServoSimConfig

    cancel_on_signals(signal.SIGTERM, signal.SIGINT)
    config = ServeConfig(
        robot="rx200",
        domain=domain,
        host=host,
        servo=ServoSimConfig(command_timeout_s=command_timeout_s),
        max_command_age_s=max_command_age_s,
        trace=True,
    )

    def ready(uri: str) -> None:
        raise_loop_priority()  # the hardware loop's class, as ``uniros robot serve`` gives it
        sys.stdout.write(f"export UNIROS_DOMAIN={uri}\n")
        sys.stdout.flush()

    with contextlib.suppress(asyncio.CancelledError):
        await serve_servo_sim(config, on_ready=ready)


async def _probe(
    domain: str, topics: list[str], services: list[str], params: list[str], timeout_s: float, transport: str
) -> dict[str, Any]:
    from uniros_async.bus import open_node
    from uniros_async.bus.messages import message_type

    out: dict[str, Any] = {"first_message_s": {}, "params": {}}
    async with open_node(f"probe_{time.monotonic_ns()}", domain=domain, transport=transport) as node:
        listed = {t["topic"]: t for t in await node.list_topics()}
        out["topics"] = {n: t["publishers"] for n, t in listed.items()}
        out["services"] = sorted(s["service"] for s in await node.list_services())
        out["nodes"] = await node.list_nodes()
        for topic in topics:
            if topic not in listed:
                out["first_message_s"][topic] = None
                continue
            t0 = time.monotonic()
            sub = await node.create_subscription(message_type(listed[topic]["type"]), topic)
            try:
                async with asyncio.timeout(timeout_s):
                    await sub.receive()
                out["first_message_s"][topic] = round(time.monotonic() - t0, 3)
            except TimeoutError:
                out["first_message_s"][topic] = None
        out["services_listed"] = {s: s in out["services"] for s in services}
        for name in params:
            out["params"][name] = await node.get_parameter(name, None)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rig.domain_peer")
    sub = parser.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("registry", help="serve a domain registry until SIGTERM")
    r.add_argument("--uri", required=True)
    a = sub.add_parser("arm", help="serve the rx200's servo sim in the domain at --domain until SIGTERM")
    a.add_argument("--domain", required=True)
    a.add_argument("--host", required=True)
    a.add_argument("--command-timeout", type=float, default=0.5)
    a.add_argument("--max-command-age", type=float, default=0.5)
    p = sub.add_parser("probe", help="join a domain as a new node and print what it sees as JSON")
    p.add_argument("--domain", required=True)
    p.add_argument("--topic", action="append", default=[])
    p.add_argument("--service", action="append", default=[])
    p.add_argument("--param", action="append", default=[])
    p.add_argument("--timeout", type=float, default=5.0)
    p.add_argument("--transport", default="tcp", help="as from another machine (default); auto: shm on this one")
    args = parser.parse_args(argv)
    if args.cmd == "registry":
        asyncio.run(_registry(args.uri))
        return 0
    if args.cmd == "arm":
        with contextlib.suppress(asyncio.CancelledError):
            asyncio.run(_arm(args.domain, args.host, args.command_timeout, args.max_command_age))
        return 0
    seen = asyncio.run(_probe(args.domain, args.topic, args.service, args.param, args.timeout, args.transport))
    print(json.dumps(seen))
    return 0


if __name__ == "__main__":
    sys.exit(main())
