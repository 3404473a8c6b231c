"""Sim camera frames through loans: rendered in a child process, copied once from its memfd into the subscriber's
shm ring, and read there in place by a subscriber in another process; the copies are counted by the transport."""

from __future__ import annotations

import asyncio
from typing import Any

import numpy as np
import pytest
from rig.bus_peers import BusPeer

from uniros_async.bus import open_domain, open_node, reliable
from uniros_async.bus.messages import Data
from uniros_async.camera import SimCameraConfig, open_sim_cameras
from uniros_async.sim.node import open_servo_sim

pytestmark = pytest.mark.slow


async def test_a_rendered_frame_is_copied_once_into_the_remote_subscribers_ring() -> None:
    cams = [SimCameraConfig(camera="scene", width=160, height=120, rate_hz=20)]
    topic = "/rx200/camera/color/image_raw"
    async with (
        open_domain() as domain,
        open_servo_sim("rx200", domain=domain),
        open_node("checker", domain=domain) as checker,
        open_sim_cameras("rx200", domain=domain, cameras=cams, render="process") as cam,
    ):
        assert cam.topic(0) == topic
        seen = await checker.create_subscription(Data, "/frames_seen", qos=reliable(1000))
        async with BusPeer(domain.uri, f"frames:{topic}", "shm"):
            pub = cam.publishers[0]._pub
            await pub.wait_for_subscribers(1, timeout_s=20)
            await seen.wait_for_publishers(1, timeout_s=20)
            conn: Any = pub._sinks[0].conn
            sent0, loaned0, in_place0 = conn.stats.frames_sent, conn.frames_loaned, pub.loaned_in_place
            got: list[list[Any]] = []
            async with asyncio.timeout(30):
                while len(got) < 5:
                    got.append((await seen.receive()).value)
            # the subscriber read each frame in place (a read-only view), the camera's whole picture, end to end
            for _seq, total, read_only, shape, encoding, frame_id in got:
                assert read_only and shape == [120, 160, 3] and encoding == "rgb8" and frame_id == "camera"
                assert total > 0
            assert [g[0] for g in got] == sorted({g[0] for g in got})
            # per frame: the render's copy out of GL (in the child), then one copy, memfd -> ring; none after
            sent = conn.stats.frames_sent - sent0
            assert sent >= 5
            assert conn.frames_loaned - loaned0 == sent, "every frame sent to the subscriber was written in place"
            assert pub.loaned_in_place - in_place0 == sent
            assert np.isfinite(cam.stats[0].render_ns).all()
