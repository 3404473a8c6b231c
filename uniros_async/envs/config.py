"""EnvConfig: how an environment runs (clock, robot placement, rates, timeouts, latency model).

These are the keyword arguments every task takes (``gym.make("uniros/Rx200Reach-v0", clock="sim", ...)``); a
task's own settings are its ``TASK_CONFIG`` (tasks/reach.py). Both are validated once, when the env is built
(``parse_kwargs`` in envs/task.py), and read as plain attributes afterwards.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import pydantic
from pydantic import Field, PlainValidator

from uniros_async.config import Bool, ConfigModel, Float, Int, Str
from uniros_async.errors import ConfigError
from uniros_async.placements import placement_spec

__all__ = ["CLOCKS", "UNSAFE_ACTIONS", "EnvConfig"]

CLOCKS = ("wall", "sim")
UNSAFE_ACTIONS = ("hold", "project")


def _latency_input(v: Any) -> float | str:
    if v == "measured":
        return "measured"
    number = v
    if isinstance(v, str):
        try:
            number = float(v)
        except ValueError:
            number = None
    if isinstance(number, bool) or not isinstance(number, int | float) or not number >= 0:
        raise ConfigError(f"expected a number >= 0 or 'measured', got {v!r}")
    return float(number)


class EnvConfig(ConfigModel):
    """Runtime settings shared by every task (each key's meaning is documented where it is declared)."""

    robot: Str = "sim"
    """Where the arm is: ``"sim"`` (servo sim in the env's own process, memory transport), ``"sim-process"``
    (servo sim in its own process, shm), ``"emulated-real"`` (the emulated real arm as a tcp service in its own
    process), ``"tcp://host:port"`` (the domain of an arm served elsewhere, e.g. by ``uniros robot serve`` or
    ``uniros robot bridge``), ``"tls://host:port"`` (the same over mutual TLS, ``uniros robot serve --tls`` or
    ``bridge --tls``; the certificate, key and CA from ``$UNIROS_TLS_CERT``, ``$UNIROS_TLS_KEY``, ``$UNIROS_TLS_CA``),
    ``"ros1://host:port"`` (an arm whose driver is a ROS 1 node, reached through that ROS master by a bridge in the
    env's process: ``adapters/ros1_bridge.py``), ``"ros2://[domain][/namespace][?...]"`` (an arm whose driver is a
    ROS 2 node, its settings in the URI's query: ``adapters/ros2_bridge.py``), ``"dxl:///dev/ttyUSB0[?...]"`` (the
    arm's Dynamixel servos on that serial port, driven from the env's own process with no middleware; the servo
    map, baud, profile and margin in the query: docs/howto/real-robots.md), or any other placement registered with
    ``uniros_async.register_placement``."""
    clock: Literal["wall", "sim"] | None = None
    """``"wall"`` (real time) or ``"sim"`` (SimClock, as fast as the CPU allows; only with ``robot="sim"``, or
    ``robot="emulated-real"``, which then runs the same emulation model (perturbed dynamics, sensor noise, command
    and state latency in sim time) in the env's process instead of behind tcp). Unset: ``"sim"`` when
    ``turn_based``, else ``"wall"``."""
    env_loop_rate_hz: Annotated[Float, Field(gt=0, le=1000)] | None = None
    """Env loop rate; unset: the robot's hardware rate."""
    action_cycle_s: Float = Field(default=0.8, gt=0, le=60)
    """Time between agent steps (an absolute deadline from the previous step)."""
    action_cycle_phase: Float = Field(default=0.0, ge=0, lt=1)
    """Where this env's action cycles fall on the clock's common grid of them, as a fraction of the cycle, rounded
    down to a whole number of env-loop periods (so a step still returns just after a tick). On a wall clock, envs of
    one phase return at the same instants; two sets of arms on one machine (the evaluation arms of
    ``eval.alongside``, which take 0.5) keep out of each other's way with different phases."""
    turn_based: Bool = False
    """The baseline, without an env loop's real-time guarantees. With the sim clock (the default when
    ``turn_based`` is set) the world is paused while the agent thinks and ``step`` advances the sim in lockstep for
    one action cycle, returning a fresh observation. With ``clock="wall"`` given explicitly it is the turn-based env
    of a real arm (openai_ros style): no env loop; ``step`` sends the command once, waits one action cycle and
    builds the returns from the newest joint state received, however old."""
    agent_latency_s: Annotated[float | Literal["measured"], PlainValidator(_latency_input)] = 0.0
    """With ``clock="sim"``: sim time between the returns the agent was given and its action reaching the loop. A
    number (fixed), ``"measured"`` (the agent's measured wall time), or 0."""
    agent_latency_jitter_s: Float = Field(default=0.0, ge=0)
    """Standard deviation of a Gaussian added to a fixed latency (clipped at 0)."""
    robot_timeout_s: Float = Field(default=2.0, gt=0)
    """Joint states older than this make ``step`` raise RobotError and the arm hold."""
    step_timeout_s: Float = Field(default=10.0, gt=0)
    """Bound on any one ``step`` call (beyond the action cycle itself)."""
    reset_timeout_s: Float = Field(default=20.0, gt=0)
    """Bound on ``reset`` (moving home and settling)."""
    reset_move_s: Float = Field(default=1.5, gt=0)
    """Time to move home on an arm that cannot be teleported (emulated or real)."""
    settle_tol_rad: Float = Field(default=0.02, gt=0)
    """An arm that moves home (emulated or real) is settled when every joint is within this of home and slower
    than 10x it per s (0.02: the servos' steady-state error under gravity is ~0.011 rad)."""
    emulation_seed: Int = 0
    """Seed of the emulated real arm's perturbations and noise."""
    imperfections: float | dict[str, float] | None = None
    """On the sim placements (``robot="sim"``, ``"sim-process"``, ``"emulated-real"``, either clock): servo-level
    imperfections (``uniros_async.sim.imperfections``): one strength in [0, 3] for every knob, or a dict knob ->
    strength (the others 0), seeded by ``emulation_seed``; on the emulated arm they replace its default emulation."""
    randomize: dict[str, tuple[float, float]] | None = None
    """On the sim placements: a range [low, high] of strengths per imperfection knob, drawn afresh by the sim at
    every reset from a seed of the env's ``np_random`` (so from the reset's seed) and ``emulation_seed``; the draw is
    in the reset's ``info["imperfections"]`` (knob -> strength) and ``info["imperfections_seed"]``. Replaces
    ``imperfections``. With ``sag``, an arm that walks home (``"emulated-real"``) can rest further from
    home than ``settle_tol_rad`` under gravity: raise that to match."""
    unsafe_action: Literal["hold", "project"] = "hold"
    """What the loop does with an action whose target fails a safety check: ``"hold"`` (UniROS: nothing of it is
    sent, the arm holds) or ``"project"`` (the safe part of it is sent: joint by joint, from the base, each joint
    takes its target value if the configuration stays safe, so the arm slides along the table or a joint limit
    instead of freezing; ``SafetyChecker.project``). Either way ``info["not_executable"]`` is set (the reach task's
    -5 applies); projected actions also set ``info["action_projected"]``."""
    ros1: dict[str, Any] | None = None
    """With ``robot="ros1://..."``: settings of the bridge (``Ros1BridgeConfig`` fields ``driver``,
    ``joint_states``, ``command``, ``command_type``, ``group``, ``ros_host``, ``state_timeout_s``,
    ``max_command_age_s``, ``insecure``); unset: the defaults of the robot's ROS 1 driver (``adapters.drivers``), and
    ``max_command_age_s`` is ``robot_timeout_s``."""

    obs_mode: Literal["state", "pixels", "pixels+state"] = "state"
    """``"state"``: the task's vector; ``"pixels"``: a Dict with the camera's newest frame (``pixels``, uint8
    height x width x 3); ``"pixels+state"``: both (``pixels``, ``state``). Frames: envs/pixels.py."""
    image_size: tuple[Annotated[Int, Field(ge=8, le=1024)], Annotated[Int, Field(ge=8, le=1024)]] = (84, 84)
    """The observation's frame size, (height, width) in pixels."""
    camera: Str = "camera"
    """The camera whose frames are observed: its topic ``/<arm>/<camera>/color/image_raw``; a sim arm has
    ``camera`` (the scene camera) and ``wrist_camera``."""
    camera_rate_hz: Annotated[Float, Field(gt=0, le=240)] | None = None
    """The rate of the sim camera the env runs; unset: 30 Hz on a wall clock, the env loop's rate on a sim clock."""
    camera_timeout_s: Float = Field(default=1.0, gt=0)
    """A frame older than this sets ``info["frame_stale"]``; ``reset`` raises RobotError without a fresh one."""
    sim_camera: Bool | None = None
    """Render the camera from the sim (True) or only subscribe to its topic (False); unset: render it on the sim
    placements (``sim``, ``sim-process``, ``emulated-real``)."""

    @pydantic.model_validator(mode="before")
    @classmethod
    def _default_clock(cls, data: Any) -> Any:
        if isinstance(data, dict) and data.get("clock") is None:
            return {**data, "clock": "sim" if data.get("turn_based") is True else "wall"}
        return data

    @pydantic.model_validator(mode="after")
    def _check(self) -> EnvConfig:
        """The checks that span keys (placement, its settings, clock)."""
        placement = placement_spec(self.robot)  # ConfigError: the registered placements and the closest one
        placement.check_config(self)  # its URI and settings
        if self.ros1 is not None and placement.name != "ros1://":
            raise ConfigError(f"ros1 settings apply only to robot='ros1://HOST:PORT', got robot={self.robot!r}")
        if self.clock == "sim" and not placement.sim_clock:
            raise ConfigError(
                f"clock='sim' needs robot='sim' or 'emulated-real' (or another placement with sim_clock=True: one "
                f"that runs the arm in this process), got robot={self.robot!r}"
            )
        return self

    @classmethod
    def split(cls, kwargs: dict[str, Any]) -> tuple[EnvConfig, dict[str, Any]]:
        """Take the EnvConfig keys out of ``kwargs``; return the config and what is left (task settings).

        Raises:
            ConfigError: an EnvConfig key has a bad value (one line per problem, naming the key).
        """
        mine = {k: v for k, v in kwargs.items() if k in cls.model_fields}
        rest = {k: v for k, v in kwargs.items() if k not in cls.model_fields}
        return cls(**mine), rest
