"""Four 30 Hz 84x84 sim cameras rendering beside another run (``uniros bench latency``), until interrupted.

    python benchmarks/cameras_beside.py &         # prints "rendering" once the four cameras publish
    uniros bench latency --json latency_beside_cameras.json
    kill %1                                       # prints the frames each camera rendered and skipped

Four arms (rx200, rx200, ned2, ned2, as the latency bench's envs) each get a servo sim in this process and a scene
camera rendered in a render process of its own (``open_sim_cameras(render="process")``, as a pixel env on a wall
clock renders), so the machine renders what four pixel envs would while the latency bench runs its own envs and
learner.
"""

from __future__ import annotations

import asyncio
import contextlib
import signal

import numpy as np

from uniros_async.bus import open_domain
from uniros_async.camera import SimCameraConfig, open_sim_cameras
from uniros_async.sim.node import open_servo_sim

ARMS = ("rx200", "rx200", "ned2", "ned2")


async def main() -> None:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    cams = [SimCameraConfig(camera="scene", width=84, height=84, rate_hz=30.0)]
    async with open_domain() as domain, contextlib.AsyncExitStack() as stack:
        nodes = []
        for k, arm in enumerate(ARMS):
            ns = f"/{arm}_{k}"
            await stack.enter_async_context(open_servo_sim(arm, domain=domain, namespace=ns))
            nodes.append(
                await stack.enter_async_context(
                    open_sim_cameras(arm, domain=domain, namespace=ns, cameras=cams, render="process")
                )
            )
        print("rendering", flush=True)
        await stop.wait()
        for k, node in enumerate(nodes):
            st = node.stats[0]
            med = float(np.median(st.render_ns)) / 1e6 if st.render_ns else float("nan")
            print(f"camera {k} ({ARMS[k]}): {st.frames} frames, {st.skipped} skipped, render median {med:.2f} ms")


if __name__ == "__main__":
    asyncio.run(main())
