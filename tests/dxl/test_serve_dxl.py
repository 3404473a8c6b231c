"""``uniros robot serve rx200 --dxl PATH``: the arm on its (virtual) bus served over tcp for an env elsewhere."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import gymnasium as gym
import numpy as np
import pytest

import uniros_async  # noqa: F401  (registers the env ids)

from ._vbus import MARGIN_MS, read, running_vbus, sdk_port

pytestmark = pytest.mark.slow


def test_serve_dxl_serves_the_bus_arm_over_tcp_until_sigint() -> None:
    with running_vbus() as vbus:
        argv = [
            sys.executable,
            "-m",
            "uniros_async.cli",
            "robot",
            "serve",
            "rx200",
            "--dxl",
            vbus.path,
            "--port",
            "0",
            "--dxl-margin-ms",
            str(MARGIN_MS),
            "--dxl-profile-ms",
            "0",
        ]
        server = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert server.stdout is not None
            first = server.stdout.readline().strip()
            assert first.startswith("export UNIROS_DOMAIN=tcp://"), first
            uri = first.split("=", 1)[1]
            env = gym.make("uniros/Rx200Reach-v0", robot=uri, action_cycle_s=0.2)
            try:
                obs, _ = env.reset(seed=0)
                q0 = obs[7:12].copy()
                action = np.zeros(env.action_space.shape, dtype=np.float32)
                action[0] = env.action_space.high[0]
                for _ in range(8):
                    obs, *_ = env.step(action)
                assert obs[7] - q0[0] > 0.02, (q0[0], obs[7])
            finally:
                env.close()
            server.send_signal(signal.SIGINT)
            assert server.wait(15) == 0
        finally:
            if server.poll() is None:
                server.kill()
                server.wait()
            for stream in (server.stdout, server.stderr):
                if stream is not None:
                    stream.close()
        with sdk_port(vbus.path) as (port, ph):
            # the server's shutdown held the arm: torque on, and the servo settles on the goal it was left (at full
            # speed, with no profile, a moving arm stops a little past it and comes back); the goal stays put
            assert read(ph, port, 1, 64, 1) == 1
            goal = read(ph, port, 1, 116, 4)
            deadline = time.monotonic() + 5.0
            while abs(goal - read(ph, port, 1, 132, 4)) > 10 and time.monotonic() < deadline:
                time.sleep(0.05)
            assert abs(goal - read(ph, port, 1, 132, 4)) <= 10
            assert read(ph, port, 1, 116, 4) == goal
            assert read(ph, port, 1, 112, 4) == 0  # --dxl-profile-ms 0: no profile (the map's is 2000 ms)
