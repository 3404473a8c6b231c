"""The rx200 reaching for its goal, in the live view, photographed by headless Chromium (the docs' picture and the
view's test): ``python -m uniros_async.view.demo -o view.png``.

A domain of this process holds an rx200 servo sim; a real ``uniros/Rx200Reach-v0`` env on that arm (in a thread)
steps toward its goal with joint deltas toward an IK solution, at most ``step_rad`` per joint and step, and its task
publishes the goal, the end effector and the bounds on ``/rx200/markers``; ``uniros view --domain`` runs as a child
process; Chromium opens the URL it prints and takes the screenshots.
"""

from __future__ import annotations

import argparse
import asyncio
import socket
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np

from uniros_async.view import ViewError

__all__ = ["free_port", "reach_and_photograph"]


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def _reach(uri: str, stop: threading.Event, step_rad: float, seed: int, result: dict[str, Any]) -> None:
    """Step an Rx200Reach-v0 env on the arm at ``uri`` toward its goal until it is reached or ``stop`` is set."""
    import gymnasium as gym

    import uniros_async  # noqa: F401  (registers the envs)

    env = gym.make("uniros/Rx200Reach-v0", robot=uri, goal_space="workspace")
    try:
        env.reset(seed=seed)
        task: Any = env.unwrapped
        q_goal, ok = task.kin.ik(task.goal, rng=seed)
        result.update(goal=task.goal.copy(), ik=ok, steps=0, success=False)
        per_action = task.delta_coeff * task._half_range * round(0.8 * task.env_loop_rate_hz)
        while not stop.is_set():
            js = task._js.latest()
            q = js.position[task._arm_idx]
            action = np.clip(np.clip(q_goal - q, -step_rad, step_rad) / per_action, -1, 1).astype(np.float32)
            _, _, terminated, truncated, info = env.step(action)
            result["steps"] += 1
            if terminated or truncated:
                result["success"] = bool(info.get("is_success"))
                break
    finally:
        env.close()


async def reach_and_photograph(
    outputs: list[Path], *, step_rad: float = 0.05, first_after_s: float = 14.0, every_s: float = 4.0, seed: int = 3
) -> tuple[str, dict[str, Any]]:
    """Run the scene and write one screenshot per path of ``outputs``; returns the view's output and the reach's
    result (``goal``, ``steps``, ``success``).

    Raises:
        ViewError: the view or the browser did not start (with the view's output).
    """
    from uniros_async.bus import open_domain
    from uniros_async.sim.node import open_servo_sim
    from uniros_async.view.screenshot import headless_chromium

    grpc, web = free_port(), free_port()
    result: dict[str, Any] = {}
    stop = threading.Event()
    async with open_domain() as domain, open_servo_sim("rx200", domain=domain.uri):
        view = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "uniros_async.cli", "view", "--domain", domain.uri, "--port", str(grpc),
            "--web-port", str(web), "--arm-wait", "30", stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.STDOUT,
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

            async def photograph() -> None:
                with headless_chromium() as browser:
                    await asyncio.to_thread(browser.open, url)
                    await asyncio.sleep(first_after_s)
                    for i, path in enumerate(outputs):
                        if i:
                            await asyncio.sleep(every_s)
                        path.write_bytes(await asyncio.to_thread(browser.screenshot))

            async with asyncio.TaskGroup() as tg:
                drainer = tg.create_task(drain())
                reacher = tg.create_task(asyncio.to_thread(_reach, domain.uri, stop, step_rad, seed, result))
                try:
                    await photograph()
                finally:
                    stop.set()
                    await reacher
                    drainer.cancel()
        finally:
            if view.returncode is None:
                view.terminate()
                try:
                    async with asyncio.timeout(15):
                        await view.wait()
                except TimeoutError:
                    view.kill()
                    await view.wait()
    return "".join(out), result


def main(argv: list[str] | None = None) -> int:
    """Write the screenshots named by ``-o`` (repeat it for a sequence)."""
    p = argparse.ArgumentParser(prog="python -m uniros_async.view.demo", description=__doc__)
    p.add_argument("-o", "--output", action="append", required=True, help="a PNG to write (repeat for more)")
    p.add_argument("--first-after", type=float, default=14.0, help="seconds before the first screenshot")
    p.add_argument("--every", type=float, default=4.0, help="seconds between screenshots")
    args = p.parse_args(argv)
    out, result = asyncio.run(
        reach_and_photograph([Path(o) for o in args.output], first_after_s=args.first_after, every_s=args.every)
    )
    print(out, end="")
    print(f"# the reach: {result}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
