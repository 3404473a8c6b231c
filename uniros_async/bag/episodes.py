"""RecordEpisodes: a gymnasium wrapper that writes every step of an env to MCAP bags.

Per step it writes, on topics under ``/<name>`` (``name`` defaults to ``episodes``):

- ``step`` (``EpisodeStep``): episode and step index, observation, action, reward, terminated, truncated, success
  (``info["is_success"]``), the goal (a goal env's ``desired_goal`` and ``achieved_goal``), how long ``step`` took
  on the wall clock, and the env loop's timings of the step (its ticks and commands since the last step, the
  observation's age, the action's latency: ``envs.timing.Timing``);
- ``joint_states`` (JointState) and ``command`` (JointCommand): the newest joint state the env loop had and the
  newest command it sent, when the env is a RobotEnv in this process (an env in a worker process has none here);
- ``camera`` (Image): the frame of a pixel observation (``obs_mode="pixels"`` or ``"pixels+state"``).

Log times are the machine's monotonic clock when ``step`` returned; the messages' stamps are the env's clock. The
writing is a BagWriter's thread, so a step costs the wrapper a few copies of small arrays. One file per run, or
with ``episodes_per_file=N`` a new file every N episodes (``run-00000.mcap``, ``run-00001.mcap``, ...).
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from uniros_async.bag.step import EpisodeStep
from uniros_async.bag.writer import BagWriter, WriterStats
from uniros_async.bus.messages import Header, Image, JointCommand, JointState
from uniros_async.errors import ConfigError

__all__ = ["EpisodeStep", "RecordEpisodes"]


def _vector(x: Any) -> np.ndarray | None:
    if x is None:
        return None
    a = np.asarray(x, dtype=np.float64)
    return a.reshape(-1).copy()


def _robot_env(env: gym.Env[Any, Any]) -> Any:
    """The RobotEnv behind ``env`` in this process (through a TaskSamplerEnv's current member), or None."""
    inner: Any = env.unwrapped
    for _ in range(4):
        if hasattr(inner, "timing") and hasattr(inner, "_js"):
            return inner
        members, current = getattr(inner, "envs", None), getattr(inner, "current", None)
        if not isinstance(members, list) or not isinstance(current, int):
            return None
        inner = members[current].unwrapped
    return None


class RecordEpisodes(gym.Wrapper[Any, Any, Any, Any]):
    """Write every step of ``env`` to MCAP bags (see the module docstring).

    Args:
        env: the env.
        path: the bag (``.mcap``); with ``episodes_per_file`` the stem of the numbered files.
        episodes_per_file: a new file every this many episodes (None: one file).
        name: the topics' namespace.
        compression: the chunks' compression ("zstd" or "lz4").

    Raises:
        ConfigError: a bad setting. BagError: the file cannot be created.
    """

    def __init__(
        self,
        env: gym.Env[Any, Any],
        path: str | os.PathLike[str],
        *,
        episodes_per_file: int | None = None,
        name: str = "episodes",
        compression: str = "zstd",
    ) -> None:
        super().__init__(env)
        if episodes_per_file is not None and episodes_per_file < 1:
            raise ConfigError(f"RecordEpisodes episodes_per_file: expected >= 1 or None, got {episodes_per_file}")
        self.path = Path(path)
        self.episodes_per_file = episodes_per_file
        self.prefix = "/" + name.strip("/")
        self.compression = compression
        self.files: list[Path] = []
        self.stats: list[WriterStats] = []
        self.episode = -1
        self._step = 0
        self._writer: BagWriter | None = None
        self._episodes_in_file = 0
        self._seen_tick = 0
        self._seen_cmd = 0

    def _open(self) -> BagWriter:
        if self.episodes_per_file is None:
            path = self.path
        else:
            path = self.path.with_name(f"{self.path.stem}-{len(self.files):05d}{self.path.suffix or '.mcap'}")
        path.parent.mkdir(parents=True, exist_ok=True)
        spec = getattr(self.env, "spec", None)
        meta = {
            "env": str(getattr(spec, "id", type(self.env.unwrapped).__name__)),
            "observation_space": str(self.env.observation_space),
            "action_space": str(self.env.action_space),
        }
        self.files.append(path)
        return BagWriter(path, compression=self.compression, metadata={"uniros_episodes": meta})

    def _close_file(self) -> None:
        if self._writer is not None:
            writer, self._writer = self._writer, None
            self.stats.append(writer.close())

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(seed=seed, options=options)
        self.episode += 1
        self._step = 0
        if self._writer is None or (
            self.episodes_per_file is not None and self._episodes_in_file >= self.episodes_per_file
        ):
            self._close_file()
            self._writer = self._open()
            self._episodes_in_file = 0
        self._episodes_in_file += 1
        robot = _robot_env(self.env)
        if robot is not None:  # ticks from here on belong to this episode's steps
            self._seen_tick = robot.timing.tick_ns[-1] if robot.timing.tick_ns else 0
            self._seen_cmd = robot.timing.command_ns[-1] if robot.timing.command_ns else 0
        return obs, info

    def step(self, action: Any) -> tuple[Any, Any, bool, bool, dict[str, Any]]:
        t0 = time.monotonic_ns()
        obs, reward, terminated, truncated, info = self.env.step(action)
        t1 = time.monotonic_ns()
        writer = self._writer
        if writer is None:
            return obs, reward, terminated, truncated, info
        robot = _robot_env(self.env)
        stamp = t1
        fields: dict[str, Any] = {}
        if robot is not None:
            stamp = robot._clock.now_ns()
            timing = robot.timing
            ticks = [t for t in list(timing.tick_ns)[-256:] if t > self._seen_tick]
            cmds = [t for t in list(timing.command_ns)[-256:] if t > self._seen_cmd]
            if ticks:
                self._seen_tick = ticks[-1]
            if cmds:
                self._seen_cmd = cmds[-1]
            fields.update(tick_ns=np.array(ticks, np.int64), command_ns=np.array(cmds, np.int64))
            if timing.observation_age_ns:
                fields["observation_age_ns"] = int(timing.observation_age_ns[-1])
            if timing.action_latency_ns:
                fields["action_latency_ns"] = int(timing.action_latency_ns[-1])
            js = robot._js.latest()
            if isinstance(js, JointState):
                writer.put(self.prefix + "/joint_states", js, t1)
            cmd = getattr(robot, "last_command", None)
            if isinstance(cmd, JointCommand):
                writer.put(self.prefix + "/command", cmd, t1)
        vector, pixels = obs, None
        desired = achieved = None
        if isinstance(obs, dict):
            pixels = obs.get("pixels")
            desired, achieved = obs.get("desired_goal"), obs.get("achieved_goal")
            vector = obs.get("observation", obs.get("state"))
        if pixels is not None:
            frame = np.asarray(pixels, dtype=np.uint8)
            writer.put(self.prefix + "/camera", Image(header=Header(stamp_ns=stamp), data=frame), t1)
        success = info.get("is_success")
        writer.put(
            self.prefix + "/step",
            EpisodeStep(
                header=Header(stamp_ns=stamp, seq=self._step),
                episode=self.episode,
                step=self._step,
                observation=_vector(vector),
                action=_vector(action),
                reward=float(reward),
                terminated=bool(terminated),
                truncated=bool(truncated),
                success=None if success is None else bool(success),
                desired_goal=_vector(desired),
                achieved_goal=_vector(achieved),
                step_wall_ns=t1 - t0,
                **fields,
            ),
            t1,
        )
        self._step += 1
        return obs, reward, terminated, truncated, info

    def close(self) -> None:
        """Close the bag (its summary written) and the env.

        Raises:
            BagError: a write failed (a full disk); the file reads up to its last complete chunk.
        """
        try:
            self._close_file()
        finally:
            super().close()
