"""The rx200 reaching for a goal, in the live view, photographed by headless Chromium (the docs' picture and the
view's test): ``python -m uniros_async.view.demo -o view.png``.

A domain of this process holds an rx200 servo sim publishing its markers (the goal, the end effector); a node of
it commands the arm from home toward a goal pose over a few seconds and publishes the task's safety box as a marker;
``uniros view --domain`` runs as a child process; Chromium opens the printed URL and takes the screenshots.
"""

from __future__ import annotations

import argparse
import asyncio
import socket
import sys
from pathlib import Path

import numpy as np

from uniros_async.view import ViewError

__all__ = ["free_port", "reach_and_photograph"]

GOAL_Q = (0.6, 0.35, 0.1, 0.5, 0.0)
"""The goal's joint positions (rad); the goal marker sits where they put the end effector."""


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def _box_edges(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    c = [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    order = [0, 1, 3, 2, 0, 4, 5, 7, 6, 4, 5, 1, 3, 7, 6, 2]
    return np.array([c[i] for i in order], dtype=np.float64)


async def reach_and_photograph(
    outputs: list[Path], *, reach_s: float = 12.0, first_after_s: float = 14.0, every_s: float = 4.0
) -> str:
    """Run the scene and write one screenshot per path of ``outputs``; returns the view's output.

    Raises:
        ViewError: the view or the browser did not start (with the view's output).
    """
    from uniros_async.bus import open_domain, open_node
    from uniros_async.bus.messages import Header, JointCommand, Marker
    from uniros_async.robots import get_robot_spec
    from uniros_async.sim.node import open_servo_sim
    from uniros_async.view.scene import ArmGeoms
    from uniros_async.view.screenshot import headless_chromium

    spec = get_robot_spec("rx200")
    geoms = ArmGeoms("rx200")
    geoms.pose(spec.arm_joint_names, np.array(GOAL_Q))
    goal = geoms.ee_position.copy()
    home = np.asarray(spec.home_q_rad, dtype=np.float64)
    grpc, web = free_port(), free_port()
    async with (
        open_domain() as domain,
        open_servo_sim("rx200", domain=domain.uri, publish_markers=True) as sim,
        open_node("reach_demo", domain=domain.uri) as node,
    ):
        sim.set_goal_marker(goal)
        cmd = await node.create_publisher(JointCommand, "/rx200/command")
        markers = await node.create_publisher(Marker, "/rx200/task_markers")
        view = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "uniros_async.cli", "view", "--domain", domain.uri, "--port", str(grpc),
            "--web-port", str(web), stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT,
        )  # fmt: skip
        out: list[str] = []
        try:
            assert view.stdout is not None
            async with asyncio.timeout(60):
                while True:
                    line = (await view.stdout.readline()).decode()
                    out.append(line)
                    if not line:
                        raise ViewError(f"uniros view ended: {''.join(out)}")
                    if line.startswith("# the view: "):
                        url = line.removeprefix("# the view: ").strip()
                        break

            async def drain() -> None:
                assert view.stdout is not None
                while line := (await view.stdout.readline()).decode():
                    out.append(line)

            async def move() -> None:
                t0 = node.now_ns()
                while True:
                    s = min(1.0, (node.now_ns() - t0) / 1e9 / reach_s)
                    q = home + (np.array(GOAL_Q) - home) * s
                    cmd.publish(JointCommand(header=Header(stamp_ns=node.now_ns()), position=q))
                    lo, hi = np.array([0.1, -0.3, 0.02]), np.array([0.45, 0.3, 0.4])
                    h = Header(stamp_ns=node.now_ns(), frame_id="world")
                    markers.publish(Marker(header=h, ns="bounds", kind="line_strip", points=_box_edges(lo, hi),
                                           scale=np.full(3, 0.004), color=np.array([0.3, 0.5, 1.0, 1.0])))  # fmt: skip
                    markers.publish(Marker(header=h, ns="goal", kind="sphere", position=goal, scale=np.full(3, 0.04),
                                           color=np.array([0.9, 0.1, 0.1, 0.9])))  # fmt: skip
                    markers.publish(Marker(header=h, ns="goal_label", kind="text", position=goal + [0, 0, 0.04],
                                           text="goal", color=np.ones(4)))  # fmt: skip
                    await asyncio.sleep(spec.hardware_period_s)

            async def photograph() -> None:
                with headless_chromium() as browser:
                    await asyncio.to_thread(browser.open, url)
                    await asyncio.sleep(first_after_s)
                    for i, path in enumerate(outputs):
                        if i:
                            await asyncio.sleep(every_s)
                        path.write_bytes(await asyncio.to_thread(browser.screenshot))

            async with asyncio.TaskGroup() as tg:
                movers = [tg.create_task(move()), tg.create_task(drain())]
                await photograph()
                for t in movers:
                    t.cancel()
        finally:
            if view.returncode is None:
                view.terminate()
                try:
                    async with asyncio.timeout(15):
                        await view.wait()
                except TimeoutError:
                    view.kill()
                    await view.wait()
    return "".join(out)


def main(argv: list[str] | None = None) -> int:
    """Write the screenshots named by ``-o`` (repeat it for a sequence)."""
    p = argparse.ArgumentParser(prog="python -m uniros_async.view.demo", description=__doc__)
    p.add_argument("-o", "--output", action="append", required=True, help="a PNG to write (repeat for more)")
    p.add_argument("--first-after", type=float, default=14.0, help="seconds before the first screenshot")
    p.add_argument("--every", type=float, default=4.0, help="seconds between screenshots")
    args = p.parse_args(argv)
    out = asyncio.run(
        reach_and_photograph([Path(o) for o in args.output], first_after_s=args.first_after, every_s=args.every)
    )
    print(out, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
