"""RobotEnv: one arm on the bus, the real-time env loop, safety checks, and where the arm runs.

The env loop is a bus timer at ``env_loop_rate_hz`` (default: the arm's hardware rate). Each tick it reads the
newest joint state (never waits for one), builds observation, reward, terminated and info through the task's
hooks and caches them with the tick's stamp, and sends the current action's joint target to the arm again
(action repeat), limited to ``max_joint_step_rad`` per tick. A task whose actions are relative to where the arm is
(``_relative_action``: joint deltas) gets its action applied again on every tick from where the arm was last told
to be, as UniROS's env loop does, so a delta acts as a joint velocity for the whole action cycle. An action whose
target fails a safety check (joint limits, a link near the table, the EE outside the workspace box,
self-collision) is never sent: the arm is told to hold and ``info["unsafe_reason"]`` says why (or, with
``unsafe_action="project"``, the safe part of it is sent and ``info["action_projected"]`` says so). ``step`` hands
the action over at once and returns the cached returns at the end of the action cycle, an absolute deadline from the
previous step.

Termination is checked at the loop's rate: once an action came, the first tick whose returns say ``terminated``
(the goal reached mid-cycle, say) ends the episode there, as on UniROS's real-time envs: the arm is told to hold,
and the returns of that tick are kept and handed to the agent at the end of the cycle. (Turn-based mode, the
baseline, judges and applies everything once per step instead.)

The arm is reached only through its topics (``joint_states``, ``command``) and services (``hold``, ``reset``)
in namespace ``/<robot>``, so the same code drives the sim in this process, a sim in another process, the
emulated real arm over tcp, or a real arm behind an adapter. Where the arm runs is the placement that
``config.robot`` names in ``uniros_async.placements``: it yields the domain the env's node joins, and says whether
``reset`` may teleport the arm home (``can_teleport``) or must drive it there and wait for it to settle. A link's
``info`` (``ArmLink.info``: the ``dxl://`` placement's servo readings) adds what it returns to the ``info`` of
every step and reset, taken when they return.
"""

from __future__ import annotations

import abc
import asyncio
import contextlib
import dataclasses
import logging
import socket
import time
from collections.abc import Callable
from typing import Any
from urllib.parse import urlsplit

import numpy as np

from uniros_async.bus import open_node
from uniros_async.bus.messages import Data, Header, JointCommand, JointState, Trigger
from uniros_async.bus.timer import Timer
from uniros_async.clock import Clock, grid_after, wall_clock
from uniros_async.envs.base import BaseEnv
from uniros_async.envs.config import EnvConfig
from uniros_async.envs.safety import SafetyChecker, SafetyConfig
from uniros_async.envs.timing import Timing
from uniros_async.envs.transit import StateTransit
from uniros_async.errors import ConfigError, RobotError
from uniros_async.kinematics import Kinematics
from uniros_async.placements import PlacementRequest, placement_spec
from uniros_async.robots import get_robot_spec
from uniros_async.sim_clock import SimClock
from uniros_async.transports.base import TransportOptions, options_from_environ

__all__ = ["RobotEnv"]

logger = logging.getLogger(__name__)

Returns = tuple[Any, float, bool, dict[str, Any]]
TICK_ALIGN_NS = 1_000_000
"""Step deadlines fall this long after an env-loop tick: time for the tick's own work."""
TICK_OFFSET_NS = 5_000_000
"""Env-loop ticks fall this long after the points of the clock's grid of their period (``clock.grid_after``), where
the servo sims publish their joint states: the tick sees the state of the same instant, this offset old, not one
a period old (the offset leaves room for an in-process sim's physics for the period, which runs at the grid
point in the same loop and must be done first, also on a loaded machine). Every env starts on the same grid, so
arms in one vector env (and action cycles that are multiples of their periods) keep one phase, give or take
each member's ``RobotEnv.loop_phase_ns``: the agent gets every member's returns about equally fresh."""
LOOP_PHASE_MAX_FRACTION = 4
"""``RobotEnv.loop_phase_ns`` is capped at a quarter of the loop's period, so a tick still sees the state its servo
published at the period's start."""
_SIM_WALL_BACKSTOP_S = 60.0
"""On a sim clock, how long in wall time a wait for the arm's first joint state lasts at most (the wait's own
timeout counts sim time)."""


def _local_host_toward(uri: str) -> str:
    """This machine's address on the interface that reaches the host of ``tcp://HOST:PORT`` or ``tls://HOST:PORT``
    (no packet is sent: a UDP socket's ``connect`` only picks the route), so that a node's listener is bound there
    and nowhere else.

    Raises:
        ConfigError: HOST has no route from here (the message names it).
    """
    parts = urlsplit(uri)
    host, port = parts.hostname or "127.0.0.1", parts.port or 1
    try:
        family = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0]
        with socket.socket(family[0], socket.SOCK_DGRAM) as s:
            s.connect(family[4])
            return str(s.getsockname()[0])
    except OSError as exc:
        raise ConfigError(f"robot={uri!r}: no route to {host} from this machine ({exc})") from exc


async def _settle() -> None:
    """Let the callbacks that are already runnable on this loop run first (one yield: this task goes to the back of
    the ready queue).

    A step's coroutine returns at its deadline before the other sleepers the same sim event woke (the servo's tick,
    the env loop's tick: their wake-ups are queued, each runs its whole callback when woken); a caller on the same
    loop (a worker) can start the next step at once, and that step must see the world after them, as it does when
    the step comes through a loop thread. Deterministic trajectories in sim time depend on it. (Not the SimClock's
    own settle, which yields until the queue is empty: two such loops would keep each other busy.)"""
    await asyncio.sleep(0)


class RobotEnv(BaseEnv):
    """A BaseEnv with one robot arm. Subclasses (TaskEnv) supply the task hooks and call ``_start()`` last."""

    def __init__(self, arm: str, config: EnvConfig, safety: SafetyConfig | None = None) -> None:
        super().__init__(config)
        self.robot_spec = get_robot_spec(arm)
        self.placement = placement_spec(config.robot)
        """Where the arm runs (``config.robot``'s entry in ``uniros_async.placements``)."""
        spec = self.robot_spec
        self.kin = Kinematics.from_spec(spec)
        self.safety = SafetyChecker(spec, self.kin, safety)
        self.env_loop_rate_hz = config.env_loop_rate_hz or spec.hardware_rate_hz
        self.timing = Timing()
        self._arm_idx = np.array([spec.joint_state_names.index(n) for n in spec.arm_joint_names])
        self.home_q = np.asarray(spec.home_q_rad, dtype=np.float64)
        self._clock: Clock = wall_clock()
        self._target: np.ndarray | None = None
        self._target_unsafe: str | None = None
        self._action: np.ndarray | None = None  # the episode's current action (None: none yet, or reset/hold)
        self._projected = False  # the current action's target was unsafe; its safe part is sent (unsafe_action)
        self._ended = False  # a tick found the episode terminated: returns kept, arm holding, until reset
        self._action_t_ns: int | None = None
        self._cache: tuple[int, Returns] | None = None
        self._deadline_ns = 0
        self._loop_timer: Timer | None = None
        self._first_step = True  # the next step is the first after a reset (see _step_deadline)
        self.loop_phase_ns = 0
        """How much later than ``TICK_OFFSET_NS`` this env's loop ticks and its steps return, on the same grids (at
        most a quarter of the loop period). Set before the env starts; a vector env's worker sets it by rank
        (``runtime.worker.LOOP_PHASE_STEP_NS``) so that its members do not all tick and return at one instant."""
        self.step_reference_ns: int | None = None
        """Set by a vector env's worker before each step: when the agent sent the step (the machine's monotonic
        clock), the same instant for every member; used once, then cleared (see ``_step_deadline``)."""
        self._last_return_wall_ns: int | None = None
        self._cmd_seq = 0
        self.last_command: JointCommand | None = None
        """The newest command the env loop sent (``bag.episodes.RecordEpisodes`` records it)."""
        self._transit = StateTransit(stall_s=config.robot_timeout_s)
        self.unsafe_actions = 0
        self.robot_process: Any = None  # a process the placement runs the arm in (ArmLink.process), or None
        self._link_info: Callable[[], dict[str, Any]] | None = None  # ArmLink.info: what the placement adds

    @property
    def _period_ns(self) -> int:
        return round(1e9 / self.env_loop_rate_hz)

    @property
    def _phase_ns(self) -> int:
        return min(max(int(self.loop_phase_ns), 0), self._period_ns // LOOP_PHASE_MAX_FRACTION)

    @property
    def _cycle_offset_ns(self) -> int:
        """``action_cycle_phase`` in ns, rounded down to a whole number of loop periods."""
        period = self._period_ns
        return round(self.config.action_cycle_phase * self.config.action_cycle_s * 1e9) // period * period

    @property
    def _wall_turn_based(self) -> bool:
        return self.config.turn_based and self.config.clock == "wall"

    def timing_snapshot(self, clear: bool = False) -> dict[str, list[int] | int]:
        """The env's timing records as plain lists (see ``Timing.snapshot``); ``clear=True`` starts afresh after."""
        snap = self.timing.snapshot()
        if clear:
            self.timing.clear()
        return snap

    # ------------------------------------------------------------------------------------------ task hooks

    @abc.abstractmethod
    def _compute_returns(self, state: JointState, q_arm: np.ndarray) -> Returns:
        """Observation, reward, terminated and info for the newest joint state (called every tick)."""

    @abc.abstractmethod
    def _action_to_target(self, action: np.ndarray, q_arm: np.ndarray) -> tuple[np.ndarray, bool]:
        """The joint target of ``action`` and whether it hit a joint limit. ``q_arm``: the arm's joint positions;
        for a relative action (``_relative_action``), where the arm was last told to be (the loop's target, kept
        within ``max_joint_step_rad`` of the measured positions)."""

    @abc.abstractmethod
    def _on_reset(self, q_arm: np.ndarray) -> None:
        """Sample the episode's goal and clear per-episode state (``self.np_random`` is seeded)."""

    # ------------------------------------------------------------------------------------------ the loop

    def _start(self) -> None:
        timeout = self.placement.start_timeout_s
        self._start_runtime(self._main, name=f"{self.robot_spec.name} env loop", timeout_s=timeout)

    async def _main(self, started: Any) -> None:
        spec, cfg = self.robot_spec, self.config
        try:
            async with contextlib.AsyncExitStack() as stack:
                clock: Clock = SimClock(time_scale=None) if cfg.clock == "sim" else wall_clock()
                self._clock = clock
                request = PlacementRequest(robot=spec, config=cfg, clock=clock)
                link = await stack.enter_async_context(self.placement.open(request))
                self.robot_process = link.process
                self._link_info = link.info
                domain, transport = link.domain, link.transport
                options = None
                if isinstance(domain, str) and domain.startswith(("tcp://", "tls://")):
                    # the arm subscribes to our commands: listen where it can reach us (loopback for an arm on loopback;
                    # beyond it, the domain's key from $UNIROS_AUTH_KEY is required, as for every listener, or tls://,
                    # whose certificates authenticate: then this host's certificate must name that address)
                    options = dataclasses.replace(options_from_environ(), bind_host=_local_host_toward(domain))
                await self._join(domain, transport, options)
                stack.push_async_callback(self._leave)
                await self._js.wait_for_publishers(1, timeout_s=30.0)
                await self._wait_for_state(after_ns=None)
                if isinstance(clock, SimClock):
                    clock.pause()
                self._start_timer()
                started(None)
                # until close() cancels main. The node rejoins the domain by itself after an outage (its registry
                # client), and its subscriptions reconnect: ``_transit_delay_ns`` notices a restarted registry
                await asyncio.Event().wait()
        except BaseException as exc:
            started(exc)
            raise

    async def _join(self, domain: Any, transport: str, options: TransportOptions | None) -> None:
        """Join the arm's domain as node ``env``: its joint-state subscription, command publisher and reset client.
        The node lives in ``self._node_stack``."""
        stack = contextlib.AsyncExitStack()
        try:
            node = await stack.enter_async_context(
                open_node(
                    "env",
                    domain=domain,
                    namespace=f"/{self.robot_spec.name}",
                    clock=self._clock,
                    transport=transport,
                    options=options,
                )
            )
            self._js = await node.create_subscription(JointState, "joint_states")
            self._cmd = await node.create_publisher(JointCommand, "command")
            self._reset_cli = node.create_client(Data, Trigger, "reset")
            self._episode_cli = node.create_client(Data, Data, "new_episode") if self.config.randomize else None
        except BaseException:
            await stack.aclose()
            raise
        self._node = node
        self._node_stack = stack

    async def _leave(self) -> None:
        await self._node_stack.aclose()

    def _start_timer(self) -> None:
        if not self._wall_turn_based:  # a real arm's turn-based env has no loop: step commands once
            start = grid_after(self._clock.now_ns(), self._period_ns, TICK_OFFSET_NS + self._phase_ns)
            self._loop_timer = self._node.create_timer(self._period_ns / 1e9, self._tick, start_ns=start)

    @property
    def _relative_action(self) -> bool:
        """Hook: True when ``_action_to_target`` depends on where the arm is (joint deltas): the loop then applies
        the action again on every tick, from where the arm was last told to be. Absolute targets are computed once
        per step."""
        return False

    def _tick(self) -> None:
        now = self._clock.now_ns()
        self.timing.tick_ns.append(now)
        if self._loop_timer is not None:
            self.timing.tick_deadline_ns.append(self._loop_timer.deadlines_ns[-1])
        js = self._js.latest()
        if js is None or self._ended:
            return
        if self._state_age_s() > self.config.robot_timeout_s:
            # where the arm is is unknown: no returns are built and no command is sent (a target computed from an
            # old state could be seconds out of date by the time it arrives); the arm's watchdog holds it
            self.timing.stale_ticks += 1
            return
        q_arm = js.position[self._arm_idx]
        returns = self._compute_returns(js, q_arm)
        self._cache = (now, returns)
        # the episode ends at this tick, the arm holds. Only once an action came: while reset walks the arm home
        # (no action yet) the old goal may still be passed
        if returns[2] and self._action is not None and not self.config.turn_based:
            self._ended = True
            hold = self._hold_target(q_arm)
            self._target, self._target_unsafe, self._action_t_ns = hold, None, None
            self._send(hold, now)
            return
        if self._relative_action and self._action is not None and not self.config.turn_based:
            self._apply_action(self._action, q_arm, now, first=False)
        target = self._target
        if target is None or self._target_unsafe is not None:
            return
        self._send(self.safety.limit_step(q_arm, target), now)
        if self._action_t_ns is not None:
            self.timing.action_latency_ns.append(now - self._action_t_ns)
            self._action_t_ns = None

    def _hold_target(self, q_arm: np.ndarray) -> np.ndarray:
        """Where to hold the arm: where it measures itself, inside the joint limits. Sensor noise or overshoot can put
        a joint a hair past a limit it sits at, and a real driver may refuse a command out there (the sims clip)."""
        return np.asarray(np.clip(q_arm, self.safety.lower, self.safety.upper))

    def _send(self, q: np.ndarray, now: int) -> None:
        self._cmd_seq += 1
        self.last_command = JointCommand(header=Header(stamp_ns=now, seq=self._cmd_seq), position=q, duration_s=0.0)
        self._cmd.publish(self.last_command)
        self._transit.sent(now)  # an arm that echoes this stamp gives the link's round trip
        self.timing.command_ns.append(now)

    def _state_age_s(self) -> float:
        """How old the newest joint state is. On a sim clock: since its stamp (the sim in this process stamps it on
        the same clock). On a wall clock: since it arrived, plus its transit (``_transit_delay_ns``): how much longer
        than the quickest recent state it took to arrive (a state that waited in a starved link or a socket buffer
        counts as old as it is), and at least half the link's round trip when the arm echoes our commands (a fixed
        delay counts too), while the arm's clock need not be ours."""
        js = self._js.latest()
        if js is None:
            return float("inf")
        if isinstance(self._clock, SimClock):
            return (self._clock.now_ns() - js.header.stamp_ns) / 1e9
        now = time.monotonic_ns()
        return (now - self._js.latest_recv_ns + self._transit_delay_ns(js, now)) / 1e9

    def _transit_delay_ns(self, js: JointState, now: int) -> int:
        """How long the newest state spent on its way from the arm (``envs.transit``: against the quickest state
        of the last minute, and half a round trip of the link when the arm echoes our commands). A restarted registry
        (a new domain id, seen when the env's node rejoins it by itself: the arm's process may be new, with another
        clock) starts the estimate afresh."""
        sub = self._js
        self._transit.follow(sub, self._node.domain_id)
        return self._transit.transit_ns(js, sub.latest_recv_ns)

    def _stale_at_ns(self) -> int:
        """When, on the env's clock, the newest joint state turns older than ``robot_timeout_s``."""
        age_s = self._state_age_s()
        if age_s == float("inf"):
            return self._clock.now_ns()
        return self._clock.now_ns() + round((self.config.robot_timeout_s - age_s) * 1e9)

    def _stale_error(self, what: str) -> RobotError:
        """Stop commanding the arm (its watchdog holds it) and say how old its newest joint state is."""
        self._stop_commanding()
        age_s = self._state_age_s()
        newest = (
            f"the newest joint state on {self._js.topic} is {age_s:.2f} s old"
            if self._js.latest() is not None
            else f"no joint state on {self._js.topic} yet"
        )
        round_trip = self._transit.describe(time.monotonic_ns())
        round_trip = f"; {round_trip}" if round_trip else ""
        return RobotError(
            f"{self.robot_spec.name}: {what}: {newest} (robot_timeout_s={self.config.robot_timeout_s}"
            f"{round_trip}); no command is sent until joint states arrive again, and the arm's watchdog"
            " holds it"
        )

    async def _wait_for_fresh_state(self, what: str) -> JointState:
        """The newest joint state if it is at most ``robot_timeout_s`` old, else the first that arrives within
        ``robot_timeout_s``.

        Raises:
            RobotError: none arrived in that time (names the robot and the newest state's age).
        """
        timeout_s = self.config.robot_timeout_s
        js = self._js.latest()
        if js is not None and self._state_age_s() <= timeout_s:
            return js
        seen = self._js.received
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            await asyncio.sleep(min(0.2 / self.robot_spec.hardware_rate_hz, max(deadline - time.monotonic(), 0.0)))
            js = self._js.latest()
            if self._js.received != seen and js is not None and self._state_age_s() <= timeout_s:
                return js
        raise self._stale_error(what)

    async def _wait_for_state(self, after_ns: int | None, timeout_s: float | None = None) -> JointState:
        """The first joint state stamped after ``after_ns`` (any, when None), waiting on the env's clock.

        On a sim clock the arm runs in this process on the same clock, so its states are due within ``timeout_s``
        of sim time, however slowly a loaded host runs the sim; ``_SIM_WALL_BACKSTOP_S`` of wall time catches a
        sim clock that stopped."""
        timeout_s = timeout_s or self.config.robot_timeout_s * 5
        deadline = time.monotonic() + timeout_s
        sim_deadline_ns: int | None = None
        if isinstance(self._clock, SimClock):
            self._clock.resume()
            sim_deadline_ns = self._clock.now_ns() + int(timeout_s * 1e9)
            deadline = time.monotonic() + max(timeout_s, _SIM_WALL_BACKSTOP_S)
        while True:
            js = self._js.latest()
            if js is not None and (after_ns is None or js.header.stamp_ns > after_ns):
                return js
            if time.monotonic() > deadline or (sim_deadline_ns is not None and self._clock.now_ns() > sim_deadline_ns):
                raise RobotError(
                    f"{self.robot_spec.name}: no joint state on {self._js.topic} within {timeout_s} s;"
                    " is the arm running?"
                )
            await self._clock.sleep(0.2 / self.robot_spec.hardware_rate_hz)

    # ------------------------------------------------------------------------------------------ step / reset

    def _set_action(self, action: np.ndarray) -> None:
        js = self._js.latest()
        assert js is not None
        now = self._clock.now_ns()
        self.timing.action_ns.append(now)
        if self._ended:  # the episode already ended at a tick: the arm keeps holding
            return
        self._action = action
        self._action_t_ns = now
        self._apply_action(action, js.position[self._arm_idx], now, first=True)

    def _apply_action(self, action: np.ndarray, q_arm: np.ndarray, now: int, *, first: bool) -> None:
        """Make ``action`` the loop's target from ``q_arm``. An unsafe target is not sent: with
        ``unsafe_action="project"`` its safe part is (``SafetyChecker.project``), otherwise (or when no joint can
        move safely) the arm holds (once per step for absolute actions, on every tick where a relative action's
        target is unsafe)."""
        ref = q_arm
        if self._relative_action and self._target is not None:
            # deltas add up from where the arm was told to be, not from where the lagging servos are yet, so a
            # delta per tick is a joint velocity; never more than max_joint_step_rad ahead of the arm
            lag = self.safety.config.max_joint_step_rad
            ref = np.clip(self._target, q_arm - lag, q_arm + lag)
        target, limit_hit = self._action_to_target(action, ref)
        why = self.safety.check(target)
        self._limit_hit = limit_hit
        self._projected = False
        if why is not None and self.config.unsafe_action == "project":
            safe = self.safety.project(ref if self.safety.check(ref) is None else q_arm, target)
            if safe is not None:  # send the safe part; the action still counts as not executable as given
                self._projected, self._target, self._target_unsafe = True, safe, None
                if first:
                    self.unsafe_actions += 1
                return
        self._target_unsafe = why
        self._target = target
        if why is not None:
            if first:
                self.unsafe_actions += 1
            hold = self._hold_target(q_arm)
            if self._relative_action:
                self._target = hold  # the next delta starts from where the arm holds
            self._send(hold, now)  # hold where it is
            self._action_t_ns = None

    async def _astep(self, action: np.ndarray) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        clock, cfg = self._clock, self.config
        if isinstance(clock, SimClock):
            await _settle()  # what the last step's sim event woke (the servo tick, the env tick) runs first
            clock.resume()
            latency = self._agent_latency_s()
            if latency > 0:
                await clock.sleep(latency)
        if self._state_age_s() > cfg.robot_timeout_s:  # no action is applied to a state that old
            raise self._stale_error("step")
        self._set_action(action)
        self._on_action(action)
        now = clock.now_ns()
        if self._wall_turn_based and self._target_unsafe is None:  # one command, no action repeat
            assert self._target is not None
            self._send(self._target, now)
            self.timing.action_latency_ns.append(clock.now_ns() - now)
            self._action_t_ns = None
        deadline = self._step_deadline(now)
        # no spin: the returns were built by the tick just before, and a few tens of microseconds later matter
        # less than a core held: ranked workers spinning for their deadlines kept lower-ranked ones from their
        # ticks (more workers than cores made the lower-ranked ticks before a deadline start late)
        while True:  # until the deadline, or until the newest joint state turns older than robot_timeout_s
            await clock.sleep_until(min(deadline, self._stale_at_ns()), spin=False)
            if self._state_age_s() > cfg.robot_timeout_s:
                self._deadline_ns = deadline
                if isinstance(clock, SimClock):
                    clock.pause()
                raise self._stale_error("step")
            if clock.now_ns() >= deadline:
                break
        self._deadline_ns = deadline
        if cfg.turn_based:  # the baseline: returns built now, from the newest joint state received
            js = self._js.latest()
            assert js is not None
            stamp = clock.now_ns()
            if self._wall_turn_based:  # as old as that state is: no loop keeps it fresh
                stamp = js.header.stamp_ns if self.placement.stamps_on_env_clock else self._js.latest_recv_ns
            self._cache = (stamp, self._compute_returns(js, js.position[self._arm_idx]))
        assert self._cache is not None
        stamp, (obs, reward, terminated, info) = self._cache
        end = clock.now_ns()
        self.timing.step_ns.append(end)
        self.timing.step_deadline_ns.append(deadline)
        self.timing.observation_age_ns.append(end - stamp)
        if isinstance(clock, SimClock):
            clock.pause()
        self._last_return_wall_ns = time.monotonic_ns()
        info = dict(info)
        if self._target_unsafe is not None:
            info["unsafe_reason"] = self._target_unsafe
        if self._projected:
            info["action_projected"] = True
        if self._link_info is not None:
            info.update(self._link_info())
        return obs, float(reward), bool(terminated), False, info

    def _on_action(self, action: np.ndarray) -> None:
        """Hook: the task records the action (e.g. for the previous-action observation)."""

    def _agent_latency_s(self) -> float:
        cfg = self.config
        if cfg.turn_based:
            return 0.0
        if cfg.agent_latency_s == "measured":
            if self._last_return_wall_ns is None:
                return 0.0
            return (time.monotonic_ns() - self._last_return_wall_ns) / 1e9
        base = float(cfg.agent_latency_s)
        if cfg.agent_latency_jitter_s > 0:
            base += float(self.np_random.normal(0.0, cfg.agent_latency_jitter_s))
        return max(0.0, base)

    async def _areset(self, options: dict[str, Any]) -> tuple[Any, dict[str, Any]]:
        clock, cfg = self._clock, self.config
        if isinstance(clock, SimClock):
            await _settle()
            clock.resume()
        self._target, self._target_unsafe, self._action_t_ns = None, None, None
        self._action, self._ended, self._projected = None, False, False
        t0 = clock.now_ns()
        # no reset on a state older than robot_timeout_s: an arm that went silent is reported, not settled on its
        # last known pose (RobotError within robot_timeout_s, or at once when the state is already that old)
        await self._wait_for_fresh_state("reset")
        drawn: dict[str, Any] = {}
        if self._episode_cli is not None:  # this episode's imperfections, drawn by the sim before the arm moves home
            from uniros_async.envs.randomize import draw_episode

            seed = int(self.np_random.spawn(1)[0].integers(2**31))  # follows the reset seed; goals' draws untouched
            drawn = await draw_episode(self._episode_cli, seed, min(cfg.reset_timeout_s, cfg.robot_timeout_s))
        if self.placement.can_teleport:  # a nominal sim can be teleported home: exact and fast
            # a teleport answers within a tick: an arm that does not answer within robot_timeout_s is not there
            timeout_s = min(cfg.reset_timeout_s, cfg.robot_timeout_s)
            try:
                reply = await self._reset_cli.call(Data(value={"q": self.home_q.tolist()}), timeout_s=timeout_s)
            except TimeoutError:
                raise self._stale_error(f"reset: no reply from {self._reset_cli.name} within {timeout_s} s") from None
            if not reply.success:
                raise RobotError(f"{self.robot_spec.name}: reset refused: {reply.message}")
            js = await self._wait_for_state(after_ns=t0, timeout_s=cfg.robot_timeout_s)
        else:
            self._target = self.home_q.copy()  # the loop re-sends it every tick until settled
            if self._wall_turn_based:  # no loop: one command home
                self._send(self._target, clock.now_ns())
            js = await self._settle(cfg.reset_timeout_s)
        self._target = self.home_q.copy()  # hold home until the first action
        q_arm = js.position[self._arm_idx]
        self._on_reset(q_arm)
        now = clock.now_ns()
        obs, _, _, info = self._compute_returns(js, q_arm)
        self._cache = (now, (obs, 0.0, False, info))
        self._deadline_ns = self._aligned_start(now)
        self._first_step = True
        if isinstance(clock, SimClock):
            clock.pause()
        self._last_return_wall_ns = time.monotonic_ns()
        link_info = self._link_info() if self._link_info is not None else {}
        return obs, {**info, **drawn, **link_info}

    def _step_deadline(self, now: int) -> int:
        """When the step whose action arrived at ``now`` returns: one action cycle after the previous deadline.

        When the agent took longer than that (an overrun, counted), a new cycle starts: turn-based, a cycle from
        ``now``; otherwise at a point of the action-cycle grid (``_next_deadline``), and the first step after a
        reset ends on that grid too (``_aligned_start``).

        On a wall clock the members of a vector env must return together, also when one of them has just
        reset while the others waited for it. So there the first step after a reset and every late step take
        the same rule, from the instant the agent sent the step (``step_reference_ns``, set by the worker; else
        when the action arrived): the first grid point at least ``cycle / 8`` after it (an action acts about that
        long, e.g. 100 ms of 800, before its returns). A step whose regular deadline is nearer than that is late
        too. Every member of a vector env on one machine decides from the same instant, so none can fall on the
        other side of a cut-off from the rest. (Were a reset that ended half a cycle or more before the next grid
        point to align its first step one cycle later than the members that kept their deadline, those would return
        a cycle early and the agent would get their returns 800 ms old.)
        """
        cfg = self.config
        cycle_ns = round(cfg.action_cycle_s * 1e9)
        first, self._first_step = self._first_step, False
        deadline = self._deadline_ns + cycle_ns
        if cfg.turn_based or isinstance(self._clock, SimClock):  # each sim env has its own clock: no peers to meet
            if deadline <= now:
                self.timing.step_overruns += 1
                deadline = now + cycle_ns if cfg.turn_based else self._next_deadline(now)
            return deadline
        # the vector env's reference instant when there is one, so members that get their actions a millisecond
        # apart cannot fall on either side of a grid point's cut-off
        ref, self.step_reference_ns = self.step_reference_ns, None
        if ref is None or not 0 <= now - ref < cycle_ns:  # none, or not this machine's clock
            ref = now
        lead = cycle_ns // 8
        # the grid point itself, not this member's phase after it, decides: members of different phases agree
        if first or deadline - self._phase_ns - ref < lead:
            if not first:
                self.timing.step_overruns += 1
            deadline = self._next_deadline(ref, lead)
            if deadline <= now:  # this worker got to the step more than cycle / 8 after the agent sent it
                deadline = self._next_deadline(now, lead)
        return deadline

    def _aligned_start(self, now: int) -> int:
        """Where the first action cycle starts: ``_next_deadline(now)`` minus one cycle (turn-based: ``now``)."""
        if self.config.turn_based:
            return now
        return self._next_deadline(now) - round(self.config.action_cycle_s * 1e9)

    def _next_deadline(self, now: int, lead_ns: int | None = None) -> int:
        """The first point, at least ``lead_ns`` (None: half an action cycle) after ``now``, of the grid of action
        cycles that starts ``TICK_ALIGN_NS`` after a scheduled env-loop tick (``TICK_OFFSET_NS`` after the clock's
        grid) and this env's ``action_cycle_phase`` of a cycle after that (whole loop periods), plus its
        ``loop_phase_ns``.

        When the action cycle is a multiple of the loop period, every step returns just after a tick, so its
        returns are about ``TICK_ALIGN_NS`` old instead of up to a period; and every env on the same clock (the
        members of a vector env, at 10 or 25 Hz) returns at the same instant, so the agent gets all of them that
        fresh.
        """
        cycle = round(self.config.action_cycle_s * 1e9)
        offset = TICK_OFFSET_NS + TICK_ALIGN_NS + self._cycle_offset_ns
        point = grid_after(now + (cycle // 2 if lead_ns is None else lead_ns), cycle, offset)
        return point + self._phase_ns  # every member picks the same grid point, then returns at its own phase

    async def _settle(self, timeout_s: float) -> JointState:
        tol = self.config.settle_tol_rad
        deadline = time.monotonic() + timeout_s
        while True:
            await self._clock.sleep(1.0 / self.robot_spec.hardware_rate_hz)
            if self._state_age_s() > self.config.robot_timeout_s:  # settling is judged on fresh states only
                raise self._stale_error("reset")
            js = self._js.latest()
            # an arm that echoes our commands must have echoed one: until then a fixed delay on the link is invisible
            # to the state's age, and an arm already at home would settle at once on a state of any age
            echo_due = self._transit.awaiting_round_trip and not isinstance(self._clock, SimClock)
            if js is not None and not echo_due:
                q = js.position[self._arm_idx]
                v = js.velocity[self._arm_idx]
                if np.max(np.abs(q - self.home_q)) < tol and np.max(np.abs(v)) < 10 * tol:
                    return js
            if time.monotonic() > deadline:
                err = (
                    "no state"
                    if js is None
                    else "the arm echoed none of our commands: no round trip measured"
                    if echo_due
                    else f"{np.max(np.abs(js.position[self._arm_idx] - self.home_q)):.3f} rad away"
                )
                raise RobotError(f"{self.robot_spec.name}: did not settle at home within {timeout_s} s ({err})")

    def _stop_commanding(self) -> None:
        """Send nothing more until a new target is set (the arm's watchdog holds it)."""
        self._target, self._target_unsafe, self._action_t_ns = None, None, None
        self._action, self._projected = None, False

    async def _ahold(self) -> None:
        js = self._js.latest()
        self._stop_commanding()
        # hold = keep commanding where it is (action repeat of the current position); never where a stale state
        # says it was
        if js is not None and self._state_age_s() <= self.config.robot_timeout_s:
            self._target = js.position[self._arm_idx].copy()
            self._send(self._target, self._clock.now_ns())
