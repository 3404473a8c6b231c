"""Offscreen rendering (EGL or OSMesa on a headless machine; see sim/render.py for the Debian packages)."""

from __future__ import annotations

import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from uniros_async.errors import ConfigError
from uniros_async.sim.render import RenderError, render_png, render_rgb, view


def png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


@pytest.mark.slow  # the first GL context of a process takes ~1 s
def test_render_png_shows_the_arm_and_the_goal(tmp_path: Path) -> None:
    out = render_png("rx200", goal=(0.3, 0.15, 0.15), out=tmp_path / "rx200.png", width=320, height=240)
    assert png_size(out) == (320, 240)
    assert 3_000 < out.stat().st_size < 1_000_000, "a plausible PNG of a rendered scene"
    plain = render_rgb("rx200", width=320, height=240)
    marked = render_rgb("rx200", goal=(0.3, 0.15, 0.15), width=320, height=240)
    red = (marked[..., 0] > 150) & (marked[..., 1] < 80) & (marked[..., 2] < 80)
    assert red.sum() > 20 and ((plain[..., 0] > 150) & (plain[..., 1] < 80) & (plain[..., 2] < 80)).sum() == 0
    dark = plain.max(axis=-1) < 70
    assert dark.sum() > 500, "the (dark grey) arm is in the picture"


@pytest.mark.slow
def test_the_picture_says_which_marker_is_which() -> None:
    def coloured(img: np.ndarray) -> tuple[int, int]:
        corner = img[:60, :160].astype(int)  # the legend's corner, above the table
        red = (corner[..., 0] > 150) & (corner[..., 1] < 80) & (corner[..., 2] < 80)
        green = (corner[..., 1] > 150) & (corner[..., 0] < 80) & (corner[..., 2] < 80)
        return int(green.sum()), int(red.sum())

    green, red = coloured(render_rgb("rx200", goal=(0.3, 0.15, 0.15), width=320, height=240))
    assert green > 20 and red > 20, "'end effector' in green and 'goal' in red"
    green, red = coloured(render_rgb("rx200", width=320, height=240))
    assert green > 20 and red == 0, "no goal, no goal in the legend"
    assert coloured(render_rgb("rx200", goal=(0.3, 0.15, 0.15), width=320, height=240, legend=False)) == (0, 0)


def test_render_ned2_at_a_pose_and_bad_input(tmp_path: Path) -> None:
    out = render_png("ned2", q=[0.5, -0.3, 0.4, 0.0, 0.5, 0.0], out=tmp_path / "ned2.png", width=160, height=120)
    assert png_size(out) == (160, 120)
    with pytest.raises(ConfigError, match="expected 6"):
        render_rgb("ned2", q=[0.0])
    with pytest.raises(ConfigError, match="goal"):
        render_rgb("ned2", goal=(0.0, np.nan, 0.0))


@pytest.mark.slow
def test_cli_render_and_view_without_display(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "cli.png"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "uniros_async.sim.cli",
            "render",
            "rx200",
            "--out",
            str(out),
            "--goal",
            "0.3",
            "0.1",
            "0.25",
            "--width",
            "200",
            "--height",
            "150",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    assert png_size(out) == (200, 150)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(RenderError, match="needs a display"):
        view("rx200")
