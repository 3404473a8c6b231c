"""``uniros view`` as real processes: the rx200 reaching for its goal, served by Rerun's viewer on loopback and
photographed twice by headless Chromium (Debian's chromium, SwiftShader's software GL); a bag replayed; and what
it refuses, by name."""

from __future__ import annotations

import asyncio
import io
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image as PILImage

from uniros_async.bag import BagWriter
from uniros_async.bus.messages import MARKER_KINDS as KINDS
from uniros_async.bus.messages import Header, Image, JointCommand, JointState, Marker
from uniros_async.view.demo import free_port, reach_and_photograph

pytestmark = pytest.mark.slow


async def uniros(*args: str, timeout_s: float = 60.0) -> tuple[int, str]:
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "uniros_async.cli",
        *args,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.STDOUT,
    )
    try:
        async with asyncio.timeout(timeout_s):
            out, _ = await proc.communicate()
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    assert proc.returncode is not None
    return proc.returncode, out.decode()


async def test_the_rx200_moves_toward_its_goal_in_headless_chromium(tmp_path: Path) -> None:
    """A real Rx200Reach-v0 env steps toward its goal; the 3D view is not blank and changes between two pictures."""
    shots = [tmp_path / "a.png", tmp_path / "b.png"]
    # 0.03 rad per step: the reach lasts past the second picture
    out, reach = await reach_and_photograph(shots, step_rad=0.03, first_after_s=12.0, every_s=4.0)
    assert "/rx200/joint_states" in out and "/rx200/markers" in out, out
    assert reach["ik"] and reach["steps"] >= 15, reach
    a, b = (np.asarray(PILImage.open(io.BytesIO(p.read_bytes())).convert("RGB"), dtype=np.int16) for p in shots)
    h, w, _ = a.shape
    scene_a, scene_b = a[40 : h * 2 // 3, : w * 3 // 5], b[40 : h * 2 // 3, : w * 3 // 5]  # the 3D view
    # not a blank canvas: the arm's dark links, the red goal and the viewer's light background are all there
    dark = (scene_b.max(axis=2) < 60).mean()
    assert 0.004 < dark < 0.6, f"dark (arm) pixels in the 3D view: {dark:.4f}"
    red = ((scene_b[..., 0] > 170) & (scene_b[..., 1] < 80) & (scene_b[..., 2] < 80)).sum()
    assert red > 30, f"{red} red (goal) pixels in the 3D view"
    assert len(np.unique(scene_b.reshape(-1, 3), axis=0)) > 50, "a flat canvas"
    # the arm moved between the two pictures
    changed = (np.abs(scene_a - scene_b).max(axis=2) > 40).mean()
    assert changed > 0.002, f"only {changed:.4f} of the 3D view changed in 4 s"


def write_bag(bag: Path) -> None:
    names = ("waist", "shoulder", "elbow", "wrist_angle", "wrist_rotate")
    with BagWriter(bag) as w:
        for i in range(20):
            t = 1_000_000_000 + i * 100_000_000
            q = np.full(5, i * 0.02)
            js = JointState(header=Header(stamp_ns=t), name=names, position=q, velocity=np.zeros(5), effort=np.zeros(5))
            w.put("/rx200/joint_states", js, t, t)
            w.put("/rx200/command", JointCommand(header=Header(stamp_ns=t), position=q + 0.01), t, t)
            kind = KINDS[i % len(KINDS)]
            pts = np.random.default_rng(i).normal(size=(4, 3)) * 0.1
            marker = Marker(header=Header(stamp_ns=t), ns=kind, kind=kind, position=[0.3, 0, 0.2], text=kind,
                            points=pts, lifetime_s=0.5 * (i % 2))  # fmt: skip
            w.put("/rx200/markers", marker, t, t)
            w.put("/rx200/camera", Image(header=Header(stamp_ns=t), data=np.full((24, 32, 3), i, np.uint8)), t, t)


async def test_a_bag_is_replayed_and_bad_input_is_named(tmp_path: Path) -> None:
    bag = tmp_path / "reach.mcap"
    write_bag(bag)
    rc, out = await uniros("view", "--bag", str(bag), "--port", str(free_port()), "--web-port", str(free_port()),
                           "--duration", "0.5")  # fmt: skip
    assert rc == 0, out
    assert "drew 80 messages of 4 topic(s); arms: rx200" in out, out

    not_a_bag = tmp_path / "notes.txt"
    not_a_bag.write_text("hello")
    rc, out = await uniros("view", "--bag", str(not_a_bag))
    assert rc == 2 and "is not an MCAP file" in out and str(not_a_bag) in out, out

    rc, out = await uniros("view", "--bag", str(bag), "--host", "0.0.0.0")
    assert rc == 2 and "not a loopback address" in out and "--allow-remote" in out, out

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        rc, out = await uniros("view", "--bag", str(bag), "--port", str(port), "--web-port", str(free_port()))
    assert rc == 2 and f"gRPC port {port} on 127.0.0.1 is in use" in out, out

    from uniros_async.bus import open_domain, open_node

    async with open_domain() as domain, open_node("lonely", domain=domain.uri) as node:
        from uniros_async.bus.messages import Text

        await node.create_publisher(Text, "/chatter")
        rc, out = await uniros("view", "--domain", domain.uri, "--arm-wait", "1", "--port", str(free_port()),
                               "--web-port", str(free_port()))  # fmt: skip
    assert rc == 2 and f"no arm in the domain {domain.uri}" in out and "/chatter" in out, out


def test_a_killed_view_leaves_no_viewer_server(tmp_path: Path) -> None:
    bag = tmp_path / "reach.mcap"
    write_bag(bag)
    grpc, web = free_port(), free_port()
    view = subprocess.Popen(
        [sys.executable, "-m", "uniros_async.cli", "view", "--bag", str(bag), "--port", str(grpc), "--web-port",
         str(web)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    assert view.stdout is not None
    try:
        lines = []
        while not (line := view.stdout.readline()).startswith("# drew"):
            lines.append(line)
            assert line, f"uniros view ended before drawing the bag: {''.join(lines)}"
        children = [int(c) for c in Path(f"/proc/{view.pid}/task/{view.pid}/children").read_text().split()]
        assert children, "the viewer's server is not a child of the view"
    finally:
        view.kill()
        view.wait()
        view.stdout.close()
    deadline = time.monotonic() + 10
    while any(_alive(c) for c in children):
        assert time.monotonic() < deadline, f"the viewer's server {children} outlived the killed view"
        time.sleep(0.05)
    for port in (grpc, web):
        with socket.socket() as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # connections in TIME_WAIT own no port
            s.bind(("127.0.0.1", port))  # free again: no listener left


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"
