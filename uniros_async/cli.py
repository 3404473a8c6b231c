"""The one ``uniros`` entry point.

    uniros bench latency|transport|...    benchmarks (bench/)
    uniros topic list|echo|hz|pub         topics of a domain, as rostopic
    uniros node list                      nodes of a domain, as rosnode
    uniros param get|set|load|list        parameters of a domain, as rosparam
    uniros robot ...                      simulated and emulated arms (sim/cli.py)
    uniros camera serve SOURCE            a V4L2/UVC device or a video file as a camera node (camera/cli.py)
    uniros train|eval|plot                TD3 / TD3+HER training, checkpoint evaluation, curves (training/cli.py)
    uniros bag record|info|play           MCAP bags of a domain's topics, as ros2 bag (bag/cli.py)
    uniros view --domain URI | --bag FILE the arms live or a bag in Rerun's web viewer (view/cli.py)

Every introspection command takes ``--domain URI`` or reads ``UNIROS_DOMAIN``. Errors print one line and exit 2;
nothing here starts a domain (``open_domain()`` does that from Python).
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
import time
from collections.abc import Sequence
from typing import Any

import yaml

from uniros_async.errors import UnirosError

__all__ = ["main"]


_JSON_HELP = "also write the records as JSON to PATH"
_NO_PROGRESS_HELP = "no progress bar on stderr"


def _domain_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--domain", default=None, help="domain URI (default: $UNIROS_DOMAIN)")


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="uniros", description="uniros_async: real-time RL on simulated and real robots"
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    bench = sub.add_parser("bench", help="benchmarks").add_subparsers(dest="scenario", required=True)
    bt = bench.add_parser("transport", help="round trip and throughput of every transport and installed peer")
    bt.add_argument("--quick", action="store_true", help="fewer samples: finishes within 60 s")
    bt.add_argument("--json", dest="json_path", default=None, metavar="PATH", help="write records as JSON")
    bt.add_argument("--transports", nargs="+", default=None, help="subset to run (default: all)")
    bt.add_argument("--payloads", nargs="+", default=None, help="small, 64k, image, hd (default: all)")
    bt.add_argument("--no-progress", action="store_true", help=_NO_PROGRESS_HELP)
    bti = bench.add_parser("timers", help="fire-time error of 10 Hz and 25 Hz timers vs asyncio.sleep")
    bti.add_argument("--duration", type=float, default=60.0, help="seconds per phase (default 60)")
    bti.add_argument("--json", dest="json_path", default=None, metavar="PATH", help=_JSON_HELP)
    bti.add_argument("--no-progress", action="store_true", help=_NO_PROGRESS_HELP)

    be = bench.add_parser("envloop", help="actuator cycle, action cycle, observation age of the real-time reach envs")
    be.add_argument("--duration", type=float, default=60.0, help="wall seconds per arm (default 60)")
    be.add_argument("--arms", nargs="+", default=["rx200", "ned2"], help="robots to run (default rx200 ned2)")
    be.add_argument("--action-cycle", type=float, default=0.8, help="seconds (default 0.8)")
    be.add_argument(
        "--robot",
        default="sim",
        help="sim, sim-process, emulated-real, tcp://host:port, tls://host:port, ros1://host:port or ros2://[domain]",
    )
    be.add_argument("--concurrent", action="store_true", help="run the arms at the same time")
    be.add_argument(
        "--think-ms", type=float, default=50.0, help="the agent thinks a random 0 to this many ms before each step"
    )
    be.add_argument("--json", dest="json_path", default=None, metavar="PATH", help=_JSON_HELP)
    be.add_argument("--no-progress", action="store_true", help=_NO_PROGRESS_HELP)

    bl = bench.add_parser("latency", help="the paper's timing figures (Fig 8-10): cycles, ages, latencies, learners")
    scenarios = ["single", "concurrent", "turn-based", "sweep"]
    bl.add_argument(
        "--scenario", dest="scenario_name", default="concurrent", choices=scenarios, help="default concurrent"
    )
    bl.add_argument(
        "--duration", type=float, default=None, help="wall seconds per learner/mode/sweep point (default: per scenario)"
    )
    bl.add_argument("--learner", dest="learners", nargs="+", default=None, help="sb3-td3 and/or async-td3")
    bl.add_argument("--action-cycle", type=float, default=0.8, help="seconds (default 0.8)")
    bl.add_argument("--think-ms", type=float, default=50.0, help="scripted agent's think time, 0 to this")
    bl.add_argument(
        "--learning-starts", type=int, default=10, help="env steps before a learner trains (default %(default)s)"
    )
    bl.add_argument("--seed", type=int, default=0, help="seeds the envs, the learners and the scripted agent")
    bl.add_argument("--json", dest="json_path", default=None, metavar="PATH", help=_JSON_HELP)
    bl.add_argument("--plot", dest="plot_path", default=None, metavar="PATH.png", help="draw box plots to PATH.png")
    bl.add_argument(
        "--allow-idle",
        action="store_true",
        help="let idle cores halt (default: a SCHED_IDLE busy-poll process per core keeps them awake, like cyclictest)",
    )
    bl.add_argument(
        "--load",
        dest="loads",
        nargs="+",
        default=[],
        choices=["cpu", "gil", "torch", "gc"],
        help="run the scenario under each load (spinning processes, a GIL-holding thread, torch threads = cores, "
        "heavy allocation and gc) and print the load table",
    )
    bl.add_argument(
        "--sched",
        dest="sched_classes",
        nargs="+",
        default=["rt", "off"],
        choices=["rt", "off"],
        help="with --load: scheduling classes to compare (UNIROS_LOOP_PRIORITY; default: rt off)",
    )
    bl.add_argument(
        "--backend",
        choices=("local", "ray"),
        default="local",
        help="ray: every env's worker placed by Ray (a local cluster of a head and one node per arm type unless"
        " --ray-address; on a shared host run it under unshare --net, see docs/scaling.md)",
    )
    bl.add_argument("--ray-address", default=None, metavar="HOST:PORT", help="the Ray cluster for --backend ray")
    bl.add_argument("--no-progress", action="store_true", help=_NO_PROGRESS_HELP)

    bth = bench.add_parser("throughput", help="make_vec vs gymnasium AsyncVectorEnv vs SB3 SubprocVecEnv")
    bth.add_argument("--quick", action="store_true", help="N = 1, 2, 4 and fewer steps")
    bth.add_argument("--steps", type=int, default=100, help="rx200 steps per row (default 100; --quick: 30)")
    bth.add_argument(
        "--n-envs", dest="n_envs", type=int, nargs="+", default=None, help="rx200 rows' env counts (default 1 2 4 8)"
    )
    bth.add_argument("--json", dest="json_path", default=None, metavar="PATH", help=_JSON_HELP)
    bth.add_argument("--transport", choices=("shm", "tcp"), default="shm", help="make_vec's workers over (default shm)")
    bth.add_argument(
        "--backend",
        choices=("local", "ray"),
        default="local",
        help="ray: add rows of workers placed by Ray, local tcp workers and a Ray actor call per step (a local"
        " two-node cluster unless --ray-address; on a shared host run it under unshare --net, see docs/performance.md)",
    )
    bth.add_argument("--ray-address", default=None, metavar="HOST:PORT", help="the Ray cluster for --backend ray")
    bth.add_argument(
        "--repeat",
        type=int,
        default=0,
        metavar="R",
        help="only the make_vec rows at N >= 4 (and the Ray-placed ones with --backend ray), R runs each with new"
        " workers, each run's %% of the physics bound printed",
    )
    bth.add_argument(
        "--shared-cores",
        dest="shared_cores",
        nargs="+",
        choices=("pin", "through", "off"),
        default=None,
        help="with --repeat: a row per UNIROS_SHARED_CORES mode, runs interleaved (default: the environment's)",
    )
    bth.add_argument(
        "--envs-per-worker",
        dest="envs_per_worker",
        nargs="+",
        default=None,
        metavar="K",
        help="envs per worker process in make_vec's rows: 'auto' (make_vec's default rule), a count, or 'cores' for"
        " one process per core where the envs outnumber the cores; with --repeat a row per value, runs interleaved"
        " (default: auto)",
    )
    bth.add_argument("--no-progress", action="store_true", help=_NO_PROGRESS_HELP)

    br = bench.add_parser("ros1", help="ROS 1 round trips: our asyncio client against rospy (needs ROS 1 installed)")
    br.add_argument("--blocks", type=int, default=11, help="blocks per client, in turns; the first is warm-up")
    br.add_argument("--per-block", type=int, default=500, help="round trips per block (default %(default)s)")
    br.add_argument("--json", dest="json_path", default=None, metavar="PATH", help=_JSON_HELP)
    br.add_argument("--no-progress", action="store_true", help=_NO_PROGRESS_HELP)
    b2 = bench.add_parser("ros2", help="ROS 2 round trips: our DDS participant against rclpy (needs the rclpy venv)")
    b2.add_argument("--blocks", type=int, default=11, help="blocks per client, in turns; the first is warm-up")
    b2.add_argument("--per-block", type=int, default=500, help="round trips per block (default %(default)s)")
    b2.add_argument("--domain-id", type=int, default=0, help="ROS 2 domain id (default %(default)s)")
    b2.add_argument("--no-netns", action="store_true", help="run on this host's loopback, not in a network namespace")
    b2.add_argument(
        "--rclpy-shm",
        action="store_true",
        help="let rclpy-to-rclpy use Fast DDS's shared memory (default: UDP, as ours)",
    )
    b2.add_argument("--json", dest="json_path", default=None, metavar="PATH", help=_JSON_HELP)
    b2.add_argument("--no-progress", action="store_true", help=_NO_PROGRESS_HELP)
    bd = bench.add_parser("dxl", help="a servo-bus tick (sync read + sync write): our client vs dynamixel-sdk on vbus")
    bd.add_argument("--cycles", type=int, default=2000, help="ticks per row (default %(default)s)")
    bd.add_argument("--baud", type=int, default=None, help="the virtual bus's baud rate (default: the servo map's)")
    bd.add_argument("--json", dest="json_path", default=None, metavar="PATH", help=_JSON_HELP)
    bd.add_argument("--no-rt", action="store_true", help="leave the clients and the vbus in the ordinary class")
    bd.add_argument("--allow-idle", action="store_true", help="let idle cores halt (default: kept awake)")
    bc = bench.add_parser("cameras", help="the main job's four real-time envs with and without a 30 Hz camera each")
    bc.add_argument("--duration", type=float, default=60.0, help="wall seconds per row (default 60)")
    bc.add_argument("--sizes", nargs="+", default=["none", "84x84"], help="WxH per row, or none (default none 84x84)")
    bc.add_argument("--json", dest="json_path", default=None, metavar="PATH", help=_JSON_HELP)
    bb = bench.add_parser("bag", help="four real-time envs and a 30 Hz 640x480 camera recorded to one MCAP bag")
    bb.add_argument("--duration", type=float, default=600.0, help="wall seconds (default 600)")
    bb.add_argument("--baseline", type=float, default=60.0, help="first, seconds without recording (default 60)")
    bb.add_argument("--out", default="bench_bag.mcap", metavar="FILE", help="the bag (default bench_bag.mcap)")
    bb.add_argument("--keep", action="store_true", help="keep the bag (default: removed after reading it back)")
    bb.add_argument("--json", dest="json_path", default=None, metavar="PATH", help=_JSON_HELP)
    bs = bench.add_parser("simclock", help="how many times faster than real time the accelerated sim runs")
    bs.add_argument("--sim-seconds", type=float, default=60.0, help="simulated seconds per case (default 60)")
    bs.add_argument("--episodes", type=int, default=3, help="reach episodes to time (default 3)")
    bs.add_argument("--json", dest="json_path", default=None, metavar="PATH", help=_JSON_HELP)
    brp = bench.add_parser("report", help="docs/performance.md's tables from benchmarks/results (write|check|record)")
    brp.add_argument("report_args", nargs=argparse.REMAINDER, help="see: uniros bench report -- --help")

    topic = sub.add_parser("topic", help="topics of a domain").add_subparsers(dest="action", required=True)
    tl = topic.add_parser("list", help="topics with their types, publishers and subscribers")
    _domain_arg(tl)
    te = topic.add_parser("echo", help="print messages of a topic")
    _domain_arg(te)
    te.add_argument("topic", help="topic name, e.g. /rx200/joint_states")
    te.add_argument("-n", "--count", type=int, default=0, help="stop after N messages (0: until Ctrl-C)")
    te.add_argument("--timeout", type=float, default=0.0, help="stop after this many seconds (0: never)")
    th = topic.add_parser("hz", help="measure the publishing rate of a topic")
    _domain_arg(th)
    th.add_argument("topic", help="topic name")
    th.add_argument("--window", type=float, default=1.0, help="seconds per report")
    th.add_argument("--reports", type=int, default=0, help="stop after N reports (0: until Ctrl-C)")
    tp = topic.add_parser("pub", help="publish a message given as YAML/JSON")
    _domain_arg(tp)
    tp.add_argument("topic", help="topic name")
    tp.add_argument("type", help="message type, e.g. Text, JointCommand")
    tp.add_argument("data", help="fields as YAML, e.g. '{data: hello}'")
    tp.add_argument("-r", "--rate", type=float, default=0.0, help="repeat at this rate in Hz (0: once)")
    tp.add_argument("-n", "--count", type=int, default=1, help="how many times (with --rate; 0: forever)")
    tp.add_argument("--wait", type=float, default=1.0, help="seconds to wait for subscribers before publishing")

    node = sub.add_parser("node", help="nodes of a domain").add_subparsers(dest="action", required=True)
    _domain_arg(node.add_parser("list", help="names of the nodes"))

    param = sub.add_parser("param", help="parameters of a domain").add_subparsers(dest="action", required=True)
    pg = param.add_parser("get", help="print a parameter (or a namespace as a mapping) as YAML")
    _domain_arg(pg)
    pg.add_argument("name", help="parameter or namespace, e.g. /rx200_1")
    ps = param.add_parser("set", help="set a parameter to a YAML value")
    _domain_arg(ps)
    ps.add_argument("name", help="parameter name")
    ps.add_argument("value", help="YAML value")
    pl = param.add_parser("load", help="load a YAML file of parameters")
    _domain_arg(pl)
    pl.add_argument("path", help="YAML file")
    pl.add_argument("--namespace", default="/", help="prefix of the loaded names (default /)")
    pli = param.add_parser("list", help="names of parameters")
    _domain_arg(pli)
    pli.add_argument("prefix", nargs="?", default="/", help="list only names under it (default /)")

    from uniros_async.sim import cli as robot_cli  # imports no MuJoCo until a robot command runs

    robot_cli.add_parser(sub)

    from uniros_async.camera import cli as camera_cli  # imports no OpenCV until a camera command runs

    camera_cli.add_parser(sub)

    from uniros_async.bag import cli as bag_cli  # imports no mcap until a bag command runs

    bag_cli.add_parser(sub)

    from uniros_async.view import cli as view_cli  # imports no rerun until the view runs

    view_cli.add_parser(sub)

    from uniros_async.training import cli as training_cli  # imports no torch/SB3 until a training command runs

    training_cli.add_parsers(sub)
    return parser


async def _with_node(args: argparse.Namespace, fn: Any) -> Any:
    from uniros_async.bus import open_node

    async with open_node(f"uniros_cli_{int(time.time() * 1e6) % 10**9}", domain=args.domain) as node:
        return await fn(node)


async def _topic_type(node: Any, topic: str) -> type:
    from uniros_async.bus.messages import message_type

    for t in await node.list_topics():
        if t["topic"] == topic:
            return message_type(t["type"])
    raise UnirosError(f"no topic {topic!r} in the domain (see `uniros topic list`)")


def _run_topic(args: argparse.Namespace) -> int:
    from uniros_async.bus import reliable
    from uniros_async.bus.messages import from_dict, message_type, to_dict

    if args.action == "list":

        async def go(node: Any) -> None:
            for t in await node.list_topics():
                print(
                    f"{t['topic']}  [{t['type']}]  pubs: {', '.join(t['publishers']) or '-'}  subs: "
                    f"{', '.join(s for s in t['subscribers'] if not s.startswith('/uniros_cli_')) or '-'}"
                )

    elif args.action == "echo":

        async def go(node: Any) -> None:
            cls = await _topic_type(node, args.topic)
            sub = await node.create_subscription(cls, args.topic, qos=reliable(100))
            n = 0
            deadline = time.monotonic() + args.timeout if args.timeout else None
            while not args.count or n < args.count:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    break
                try:
                    async with asyncio.timeout(left):
                        msg = await sub.receive()
                except TimeoutError:
                    break
                print(
                    yaml.safe_dump(to_dict(msg), sort_keys=False, default_flow_style=None).rstrip() + "\n---",
                    flush=True,
                )
                n += 1

    elif args.action == "hz":

        async def go(node: Any) -> None:
            cls = await _topic_type(node, args.topic)
            sub = await node.create_subscription(cls, args.topic, qos=reliable(10000))
            reports = 0
            while not args.reports or reports < args.reports:
                stamps: list[int] = []
                end = time.monotonic() + args.window
                while (left := end - time.monotonic()) > 0:
                    try:
                        async with asyncio.timeout(left):
                            await sub.receive()
                    except TimeoutError:
                        break
                    stamps.append(time.monotonic_ns())
                if len(stamps) >= 2:
                    import numpy as np

                    d = np.diff(stamps) / 1e9
                    print(
                        f"average rate: {1 / d.mean():.3f} Hz  min {d.min() * 1e3:.2f} ms  max {d.max() * 1e3:.2f} ms  "
                        f"std {d.std() * 1e3:.3f} ms  window: {len(stamps)}",
                        flush=True,
                    )
                else:
                    print("no new messages", flush=True)
                reports += 1

    else:  # pub

        async def go(node: Any) -> None:
            cls = message_type(args.type)
            msg: Any = from_dict(cls, yaml.safe_load(args.data) or {})
            pub = await node.create_publisher(cls, args.topic)
            try:
                await pub.wait_for_subscribers(1, timeout_s=args.wait)
            except TimeoutError:
                pass
            n = 0
            while True:
                pub.publish(msg)
                n += 1
                if not args.rate or (args.count and n >= args.count):
                    break
                await asyncio.sleep(1 / args.rate)
            await asyncio.sleep(0.1)  # let the frames leave before the node closes
            print(f"published {n} {cls.__name__} on {args.topic} to {pub.subscription_count} subscriber(s)")

    asyncio.run(_with_node(args, go))
    return 0


def _run_param(args: argparse.Namespace) -> int:
    async def go(node: Any) -> None:
        if args.action == "get":
            print(yaml.safe_dump(await node.get_parameter(args.name), default_flow_style=None).rstrip())
        elif args.action == "set":
            await node.set_parameter(args.name, yaml.safe_load(args.value))
        elif args.action == "load":
            n = await node.load_parameters(args.path, namespace=args.namespace)
            print(f"loaded {n} parameter(s) from {args.path}")
        else:
            for name in await node.list_parameters(args.prefix):
                print(name)

    asyncio.run(_with_node(args, go))
    return 0


def _run_node(args: argparse.Namespace) -> int:
    async def go(node: Any) -> None:
        for name in await node.list_nodes():
            if name != node.name:
                print(name)

    asyncio.run(_with_node(args, go))
    return 0


def _run_bench(args: argparse.Namespace) -> int:
    if args.scenario == "report":
        from uniros_async.bench import report

        return report.main([a for a in args.report_args if a != "--"])
    if args.scenario == "transport":
        from uniros_async.bench import transport

        cfg = transport.TransportBenchConfig(
            quick=args.quick,
            json_path=args.json_path,
            progress=not args.no_progress,
            transports=tuple(args.transports) if args.transports else transport.ALL,
            payloads=tuple(args.payloads) if args.payloads else tuple(transport.PAYLOADS),
        )
        transport.main(cfg)
    elif args.scenario == "throughput":
        from uniros_async.bench import throughput

        throughput.main(
            throughput.ThroughputBenchConfig(
                n_envs=tuple(args.n_envs) if args.n_envs else throughput.ThroughputBenchConfig.n_envs,
                quick=args.quick,
                steps=args.steps,
                json_path=args.json_path,
                transport=args.transport,
                progress=not args.no_progress,
                backend=args.backend,
                ray_address=args.ray_address,
                repeat=args.repeat,
                shared_cores=tuple(args.shared_cores or ()),
                envs_per_worker=tuple(args.envs_per_worker or ("auto",)),
            )
        )
    elif args.scenario == "ros1":
        from uniros_async.bench import ros1

        ros1.main(
            ros1.Ros1BenchConfig(
                blocks=args.blocks,
                per_block=args.per_block,
                json_path=args.json_path,
                progress=not args.no_progress,
            )
        )
    elif args.scenario == "ros2":
        from uniros_async.bench import ros2

        ros2.main(
            ros2.Ros2BenchConfig(
                blocks=args.blocks,
                per_block=args.per_block,
                domain_id=args.domain_id,
                netns=not args.no_netns,
                rclpy_shm=args.rclpy_shm,
                json_path=args.json_path,
                progress=not args.no_progress,
            )
        )
    elif args.scenario == "dxl":
        from uniros_async.bench import dxl

        dxl.main(
            dxl.DxlBenchConfig(
                cycles=args.cycles,
                baud=args.baud,
                json_path=args.json_path,
                real_time=not args.no_rt,
                keep_cores_awake=not args.allow_idle,
            )
        )
    elif args.scenario == "bag":
        from uniros_async.bench import bag as bench_bag

        bench_bag.main(
            bench_bag.BagBenchConfig(
                duration_s=args.duration,
                baseline_s=args.baseline,
                out=args.out,
                keep=args.keep,
                json_path=args.json_path,
            )
        )
    elif args.scenario == "cameras":
        from uniros_async.bench import cameras

        sizes = cameras.parse_sizes(args.sizes)
        cameras.main(cameras.CameraBenchConfig(duration_s=args.duration, sizes=sizes, json_path=args.json_path))
    elif args.scenario == "simclock":
        from uniros_async.bench import simclock

        simclock.main(
            simclock.SimClockBenchConfig(sim_seconds=args.sim_seconds, episodes=args.episodes, json_path=args.json_path)
        )
    elif args.scenario == "latency":
        from uniros_async.bench import latency

        latency.main(
            latency.LatencyBenchConfig(
                scenario=args.scenario_name,
                duration_s=args.duration,
                learners=tuple(args.learners) if args.learners else None,
                action_cycle_s=args.action_cycle,
                think_ms=args.think_ms,
                learning_starts=args.learning_starts,
                seed=args.seed,
                json_path=args.json_path,
                plot_path=args.plot_path,
                progress=not args.no_progress,
                keep_cores_awake=not args.allow_idle,
                loads=tuple(args.loads),
                sched_classes=tuple(args.sched_classes),
                backend=args.backend,
                ray_address=args.ray_address,
            )
        )
    elif args.scenario == "envloop":
        from uniros_async.bench import envloop

        envloop.main(
            envloop.EnvLoopBenchConfig(
                duration_s=args.duration,
                arms=tuple(args.arms),
                action_cycle_s=args.action_cycle,
                robot=args.robot,
                concurrent=args.concurrent,
                think_ms=args.think_ms,
                json_path=args.json_path,
                progress=not args.no_progress,
            )
        )
    else:
        from uniros_async.bench import timers

        timers.main(
            timers.TimerBenchConfig(duration_s=args.duration, json_path=args.json_path, progress=not args.no_progress)
        )
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``uniros`` command; returns the exit code."""
    args = _build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s"
    )
    try:
        if args.command == "bench":
            return _run_bench(args)
        if args.command == "topic":
            return _run_topic(args)
        if args.command == "param":
            return _run_param(args)
        if args.command == "node":
            return _run_node(args)
        if args.command in ("train", "eval", "plot"):
            from uniros_async.training import cli as training_cli

            return training_cli.run(args)
        if args.command == "robot":
            from uniros_async.sim import cli as robot_cli

            return int(robot_cli.run(args))
        if args.command == "camera":
            from uniros_async.camera import cli as camera_cli

            return camera_cli.run(args)
        if args.command == "bag":
            from uniros_async.bag import cli as bag_cli

            return bag_cli.run(args)
        if args.command == "view":
            from uniros_async.view import cli as view_cli

            return view_cli.run(args)
    except KeyboardInterrupt:
        return 130
    except (UnirosError, KeyError, TimeoutError) as exc:
        print(f"uniros: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
