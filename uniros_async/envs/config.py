"""EnvConfig: how an environment runs (clock, robot placement, rates, timeouts, latency model)."""

from __future__ import annotations

import dataclasses
from typing import Any

from uniros_async.errors import ConfigError
from uniros_async.placements import placement_spec

__all__ = ["CLOCKS", "UNSAFE_ACTIONS", "EnvConfig"]

CLOCKS = ("wall", "sim")
UNSAFE_ACTIONS = ("hold", "project")


@dataclasses.dataclass(frozen=True, kw_only=True)
class EnvConfig:
    """Runtime settings shared by every task.

    Attributes:
        robot: where the arm is: ``"sim"`` (servo sim in the env's own process, memory transport),
            ``"sim-process"`` (servo sim in its own process, shm), ``"emulated-real"`` (the emulated real arm as
            a tcp service in its own process), ``"tcp://host:port"`` (the domain of an arm served elsewhere,
            e.g. by ``uniros robot serve`` or ``uniros robot bridge``), ``"ros1://host:port"`` (an arm whose
            driver is a ROS 1 node, reached through that ROS master by a bridge in the env's process:
            ``adapters/ros1_bridge.py``), or any other placement registered with
            ``uniros_async.register_placement``.
        ros1: with ``robot="ros1://..."``: settings of the bridge (``Ros1BridgeConfig`` fields ``driver``,
            ``joint_states``, ``command``, ``command_type``, ``group``, ``ros_host``, ``state_timeout_s``); None:
            the defaults of the robot's ROS 1 driver (``adapters.drivers``).
        clock: ``"wall"`` (real time) or ``"sim"`` (SimClock, as fast as the CPU allows; only with ``robot="sim"``,
            or ``robot="emulated-real"``, which then runs the same emulation model (perturbed dynamics, sensor
            noise, command and state latency in sim time) in the env's process instead of behind tcp).
        env_loop_rate_hz: env loop rate; None: the robot's hardware rate.
        action_cycle_s: time between agent steps (an absolute deadline from the previous step).
        turn_based: the baseline, without an env loop's real-time guarantees. With the sim clock (the default
            when ``turn_based`` is set) the world is paused while the agent thinks and ``step`` advances the sim in
            lockstep for one action cycle, returning a fresh observation. With ``clock="wall"`` given explicitly it
            is the turn-based env of a real arm (openai_ros style): no env loop; ``step`` sends the command once,
            waits one action cycle and builds the returns from the newest joint state received, however old.
        agent_latency_s: with ``clock="sim"``: sim time between the returns the agent was given and its action
            reaching the loop. A number (fixed), ``"measured"`` (the agent's measured wall time), or 0.
        agent_latency_jitter_s: standard deviation of a Gaussian added to a fixed latency (clipped at 0).
        robot_timeout_s: joint states older than this make ``step`` raise RobotError and the arm hold.
        step_timeout_s: bound on any one ``step`` call (beyond the action cycle itself).
        reset_timeout_s: bound on ``reset`` (moving home and settling).
        reset_move_s: time to move home on an arm that cannot be teleported (emulated or real).
        settle_tol_rad: an arm that moves home (emulated or real) is settled when every joint is within this of
            home and slower than 10x it per s (0.02: the servos' steady-state error under gravity is ~0.011 rad).
        emulation_seed: seed of the emulated real arm's perturbations and noise.
        unsafe_action: what the loop does with an action whose target fails a safety check: ``"hold"`` (UniROS:
            nothing of it is sent, the arm holds) or ``"project"`` (the safe part of it is sent: joint by joint,
            from the base, each joint takes its target value if the configuration stays safe, so the arm slides
            along the table or a joint limit instead of freezing; ``SafetyChecker.project``). Either way
            ``info["not_executable"]`` is set (the reach task's -5 applies); projected actions also set
            ``info["action_projected"]``.
    """

    robot: str = "sim"
    clock: str | None = None  # None: "sim" when turn_based, else "wall"
    env_loop_rate_hz: float | None = None
    action_cycle_s: float = 0.8
    turn_based: bool = False
    agent_latency_s: float | str = 0.0
    agent_latency_jitter_s: float = 0.0
    robot_timeout_s: float = 2.0
    step_timeout_s: float = 10.0
    reset_timeout_s: float = 20.0
    reset_move_s: float = 1.5
    settle_tol_rad: float = 0.02
    emulation_seed: int = 0
    unsafe_action: str = "hold"
    ros1: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        placement = placement_spec(self.robot)  # ConfigError: the registered placements and the closest one
        placement.check_config(self)  # its URI and settings
        if self.ros1 is not None and placement.name != "ros1://":
            raise ConfigError(f"ros1 settings apply only to robot='ros1://HOST:PORT', got robot={self.robot!r}")
        if self.clock is None:
            object.__setattr__(self, "clock", "sim" if self.turn_based else "wall")
        if self.clock not in CLOCKS:
            raise ConfigError(f"clock must be one of {CLOCKS}, got {self.clock!r}")
        if self.clock == "sim" and not placement.sim_clock:
            raise ConfigError(
                f"clock='sim' needs robot='sim' or 'emulated-real' (or another placement with sim_clock=True: one "
                f"that runs the arm in this process), got robot={self.robot!r}"
            )
        if self.env_loop_rate_hz is not None and not 0 < self.env_loop_rate_hz <= 1000:
            raise ConfigError(f"env_loop_rate_hz must be in (0, 1000], got {self.env_loop_rate_hz}")
        if not 0 < self.action_cycle_s <= 60:
            raise ConfigError(f"action_cycle_s must be in (0, 60], got {self.action_cycle_s}")
        if isinstance(self.agent_latency_s, str):
            if self.agent_latency_s != "measured":
                raise ConfigError(f"agent_latency_s must be a number or 'measured', got {self.agent_latency_s!r}")
        elif self.agent_latency_s < 0:
            raise ConfigError(f"agent_latency_s must be >= 0, got {self.agent_latency_s}")
        if self.unsafe_action not in UNSAFE_ACTIONS:
            raise ConfigError(f"unsafe_action must be one of {UNSAFE_ACTIONS}, got {self.unsafe_action!r}")
        for name in ("robot_timeout_s", "step_timeout_s", "reset_timeout_s", "reset_move_s", "settle_tol_rad"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"{name} must be > 0, got {getattr(self, name)}")

    @classmethod
    def split(cls, kwargs: dict[str, Any]) -> tuple[EnvConfig, dict[str, Any]]:
        """Take the EnvConfig fields out of ``kwargs``; return the config and what is left (task settings)."""
        names = {f.name for f in dataclasses.fields(cls)}
        mine = {k: v for k, v in kwargs.items() if k in names}
        rest = {k: v for k, v in kwargs.items() if k not in names}
        return cls(**mine), rest
