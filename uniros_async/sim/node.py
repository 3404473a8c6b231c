"""ServoSimNode: the bus face of a ServoSim, the "hardware interface" of a simulated arm.

In namespace ``/<robot name>`` (configurable) the node

- subscribes ``command`` (JointCommand, QoS latest: no buffering, the newest command wins, as on ros_control);
- publishes ``joint_states`` (JointState) at the hardware rate (rx200 10 Hz, ned2 25 Hz) from a node timer, so
  it follows the domain's clock (a WallClock, or a SimClock that this node then drives);
- serves ``hold`` and ``stop`` (Empty -> Trigger), ``set_mode`` (Text -> Trigger), ``reset`` (Data -> Trigger:
  ``Data()`` teleports home, ``Data(value={"q": [...]})`` to a pose), ``new_episode`` (Data -> Data: with
  ``randomize``, draw the next episode's imperfections, from ``Data(value={"seed": N})`` when given; the reply holds
  ``{"strengths": {knob: strength}, "seed": N}``, ``{}`` without ``randomize``, ``{"error": ...}`` on bad input)
  and ``stats`` (Empty -> Data);
- publishes Marker messages on ``markers`` when asked (``publish_markers=True``): the goal marker given by
  ``set_goal_marker(pos)`` or received on ``markers_in``, and the EE marker at every tick.

Every joint state echoes the stamp of the newest command received (``command_stamp_ns``, verbatim, whether applied or
not) and how long before the state's stamp it arrived (``command_age_ns``, on this process's monotonic clock; an
emulated arm's command latency counts as the link's): the commanding env gets a round trip of the link on its own
clock, and with it the age of a state whatever the offset between the two clocks (``uniros_async.envs.transit``).

Commands carry the sender's stamp (``header.stamp_ns``, the domain's clock). With ``max_command_age_s`` the node
drops a command older than that when it arrives at a tick (``stale_commands``), so a command that sat in a buffer
of a broken or frozen link never moves the arm when the link comes back; the sender must share the node's clock (a
process on the same machine: CLOCK_MONOTONIC is one across network namespaces, or a SimClock follower). ``on_event``
gets a dict for every command taken at a tick (``{"ev": "cmd", "t_ns", "tick", "age_ns", "applied"}``) and every
watchdog hold (``{"ev": "hold", "t_ns", "tick"}``), ``tick`` counting the sim's ticks (``stats.ticks``, one hardware
period of sim time each): the fault tests measure with it.

Placements (docs/architecture.md): ``open_servo_sim`` runs it in the caller's process; ``open_servo_sim_process``
(sim/serve.py) in its own process joining the same domain; ``serve_servo_sim`` (sim/serve.py, and
``uniros robot serve``) as a remote service with its own tcp domain.

When the node's clock is a SimClock (not a follower) that no one drives yet, this node drives it (the
simulation is the time source) and publishes its time as ClockTick on ``/clock``.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import time
from collections.abc import AsyncIterator, Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from uniros_async.bus import Node, open_node
from uniros_async.bus.domain import Domain
from uniros_async.bus.messages import (
    ClockTick,
    Data,
    Empty,
    Header,
    JointCommand,
    JointState,
    Marker,
    Text,
    Trigger,
)
from uniros_async.bus.qos import latest
from uniros_async.bus.tasks import unwrap_task_group
from uniros_async.clock import Clock, grid_after
from uniros_async.errors import ConfigError
from uniros_async.robots import RobotSpec, get_robot_spec
from uniros_async.sim.emulated import DelayLine, EmulationConfig, add_sensor_noise, perturb_model
from uniros_async.sim.imperfections import Imperfections, Randomization
from uniros_async.sim.servo import ServoSim, ServoSimConfig, ServoStats, load_model
from uniros_async.sim_clock import SimClock
from uniros_async.transports.base import TransportOptions

__all__ = ["ServoSimNode", "open_servo_sim"]

logger = logging.getLogger(__name__)

GOAL_MARKER_ID = 0
EE_MARKER_ID = 1


class ServoSimNode:
    """A ServoSim on the bus. Create with ``async with open_servo_sim(robot, domain=...) as sim_node:``.

    Attributes:
        node: the bus node (namespace ``/<robot>`` unless told otherwise).
        sim: the ServoSim it drives (``sim.stats`` has the counters).
        emulation: the EmulationConfig of an emulated real arm, or None.
        perturbation: the factors drawn for an emulated arm (``perturb_model``), or {}.
        goal_marker: the goal marker position, or None.
        last_state: the last published JointState (after noise), or None.
        max_command_age_s: commands older than this when taken at a tick are dropped (None: none are).
        stale_commands: commands dropped for their age.
        repeated_states: ticks that sent the previous state again (``EmulationConfig.state_repeat``).
        randomize: the ranges of imperfection strengths drawn at every reset, or None.
        imperfections: this episode's drawn imperfections (with ``randomize``), or None.
        on_event: called with each command and watchdog event (see the module docstring), or None.
    """

    def __init__(
        self,
        node: Node,
        sim: ServoSim,
        *,
        emulation: EmulationConfig | None = None,
        perturbation: dict[str, np.ndarray] | None = None,
        publish_markers: bool = False,
        max_command_age_s: float | None = None,
        on_event: Callable[[dict[str, Any]], None] | None = None,
        randomize: Randomization | None = None,
    ) -> None:
        if max_command_age_s is not None and not max_command_age_s > 0:
            raise ConfigError(f"max_command_age_s: expected a value > 0 or None, got {max_command_age_s}")
        self.max_command_age_s = max_command_age_s
        self.stale_commands = 0
        self.repeated_states = 0
        self.on_event = on_event
        self.node = node
        self.sim = sim
        self.emulation = emulation
        self.perturbation = perturbation or {}
        self.publish_markers = publish_markers
        self.goal_marker: np.ndarray | None = None
        self.last_state: JointState | None = None
        self._rng = np.random.default_rng(None if emulation is None else emulation.seed + 1)
        self._pending: JointCommand | None = None
        self._seen = 0
        self._delayed_echo: tuple[int, int] | None = None  # behind a command delay line: (stamp, arrival) of the newest
        self._state_line: DelayLine[JointState] | None = None
        self._cmd_line: DelayLine[JointCommand] | None = None
        self.timer: Any = None
        self._tasks: list[asyncio.Task[Any]] = []
        self._clock_listener: Any = None
        self.randomize = randomize
        self.imperfections: Imperfections | None = None
        self._draws = np.random.default_rng([0 if randomize is None else randomize.seed, 41])
        self._episode_drawn = False  # new_episode drew the next episode's imperfections: reset keeps them
        if randomize is not None:
            self.new_episode()
            self.sim.reset()  # the arm at home as the first episode's servos read it
            self.sim.stats.resets = 0
            self._episode_drawn = False

    @property
    def robot(self) -> RobotSpec:
        return self.sim.robot

    @property
    def stats(self) -> ServoStats:
        return self.sim.stats

    def topic(self, name: str) -> str:
        """The absolute name of one of this node's topics or services (``"joint_states"`` -> ``/rx200/...``)."""
        return self.node.resolve(name)

    # ------------------------------------------------------------------------------------------- setup

    async def _start(self, tg: asyncio.TaskGroup) -> None:
        node, emu = self.node, self.emulation
        self.joint_states = await node.create_publisher(JointState, "joint_states", qos=latest())
        self.markers = await node.create_publisher(Marker, "markers", qos=latest())
        if emu is not None and (not emu.command_latency.is_zero or self.randomize is not None):
            self._cmd_line = DelayLine(emu.command_latency, self._rng, node.clock)
            self._tasks.append(tg.create_task(self._cmd_line.run(self._on_delayed_command), name="command delay"))
            self.commands = await node.create_subscription(JointCommand, "command", self._cmd_line.push, qos=latest())
        else:
            self.commands = await node.create_subscription(JointCommand, "command", qos=latest())
        if emu is not None and (not emu.state_latency.is_zero or self.randomize is not None):
            self._state_line = DelayLine(emu.state_latency, self._rng, node.clock)
            self._tasks.append(tg.create_task(self._state_line.run(self.joint_states.publish), name="state delay"))
        await node.create_subscription(Marker, "markers_in", self._on_marker_in, qos=latest())
        await node.create_service(Empty, Trigger, "hold", self._srv_hold)
        await node.create_service(Empty, Trigger, "stop", self._srv_stop)
        await node.create_service(Text, Trigger, "set_mode", self._srv_set_mode)
        await node.create_service(Data, Trigger, "reset", self._srv_reset)
        await node.create_service(Data, Data, "new_episode", self._srv_new_episode)
        await node.create_service(Empty, Data, "stats", self._srv_stats)
        clock = node.clock
        if isinstance(clock, SimClock) and not clock.follower and not clock.running:
            clock_pub = await node.create_publisher(ClockTick, "/clock", qos=latest())
            self._clock_listener = lambda t: clock_pub.publish(ClockTick(sim_time_ns=t))
            clock.add_listener(self._clock_listener)
            self._tasks.append(tg.create_task(clock.run(), name="SimClock driver"))
        # on the clock's common grid (multiples of the period), so that env loops can tick just after it
        start = grid_after(node.now_ns(), self.sim.period_ns)
        self.timer = node.create_timer(self.sim.period_ns / 1e9, self._on_tick, start_ns=start)

    # ------------------------------------------------------------------------------------------- the loop

    def _shutdown(self) -> None:
        if self.timer is not None:
            self.timer.cancel()
        if self._clock_listener is not None and isinstance(self.node.clock, SimClock):
            self.node.clock.remove_listener(self._clock_listener)
        for task in self._tasks:
            task.cancel()

    def _on_delayed_command(self, cmd: JointCommand) -> None:
        self._pending = cmd
        self._delayed_echo = (cmd.header.stamp_ns, time.monotonic_ns())

    def _echo(self) -> tuple[int | None, int | None]:
        """A state's ``command_stamp_ns`` and ``command_age_ns``: the newest command received, and how long ago it
        arrived (``JointState``); taken when the state is stamped."""
        if self._cmd_line is not None:
            echo = self._delayed_echo
            if echo is None:
                return None, -1
            return echo[0], time.monotonic_ns() - echo[1]
        sub = self.commands
        cmd = sub.latest()
        if cmd is None:
            return None, -1
        return cmd.header.stamp_ns, time.monotonic_ns() - sub.latest_recv_ns

    def _take_command(self) -> JointCommand | None:
        if self._cmd_line is not None:
            cmd, self._pending = self._pending, None
        else:
            sub = self.commands
            if sub.received == self._seen:
                return None
            self._seen = sub.received
            cmd = sub.latest()
        if cmd is None or (self.max_command_age_s is None and self.on_event is None):
            return cmd
        now = self.node.now_ns()
        age_ns = now - cmd.header.stamp_ns
        applied = self.max_command_age_s is None or age_ns <= self.max_command_age_s * 1e9
        if not applied:
            self.stale_commands += 1
            if self.stale_commands <= 10 or self.stale_commands % 1000 == 0:
                logger.warning(
                    "%s: dropped a command %.3f s old (max_command_age_s=%s; %d dropped)",
                    self.robot.name,
                    age_ns / 1e9,
                    self.max_command_age_s,
                    self.stale_commands,
                )
        if self.on_event is not None:
            tick = self.sim.stats.ticks + 1  # the tick that takes it
            self.on_event({"ev": "cmd", "t_ns": now, "tick": tick, "age_ns": age_ns, "applied": applied})
        return cmd if applied else None

    def _on_tick(self) -> None:
        cmd = self._take_command()
        holds = self.sim.stats.watchdog_holds
        # SimulationError ends the node: not hidden
        state = self.sim.tick(cmd, stamp_ns=self.node.now_ns(), echo=self._echo())
        if self.on_event is not None and self.sim.stats.watchdog_holds != holds:
            self.on_event({"ev": "hold", "t_ns": self.node.now_ns(), "tick": self.sim.stats.ticks})
        if self.emulation is not None and (self.emulation.position_noise_std or self.emulation.velocity_noise_std):
            state = add_sensor_noise(state, self.emulation, self._rng)
        if self.emulation is not None and self.emulation.state_repeat and self.last_state is not None:
            if self._rng.random() < self.emulation.state_repeat:
                self.repeated_states += 1
                prev, h = self.last_state, state.header
                state = dataclasses.replace(prev, header=Header(stamp_ns=h.stamp_ns, seq=h.seq, frame_id=h.frame_id))
        self.last_state = state
        if self._state_line is not None:
            self._state_line.push(state)
        else:
            self.joint_states.publish(state)
        if self.publish_markers:
            self.markers.publish(self._marker("ee", EE_MARKER_ID, self.sim.ee_position(), (0.1, 0.8, 0.1, 1.0)))

    # ------------------------------------------------------------------------------------------- markers

    def _marker(self, ns: str, mid: int, pos: ArrayLike, rgba: Sequence[float], action: str = "add") -> Marker:
        return Marker(
            header=Header(stamp_ns=self.node.now_ns(), frame_id="world"),
            ns=ns,
            id=mid,
            kind="sphere",
            action=action,
            position=np.asarray(pos, dtype=np.float64),
            scale=np.full(3, 0.03),
            color=np.asarray(rgba, dtype=np.float64),
        )

    def set_goal_marker(self, pos: ArrayLike | None) -> None:
        """Show (and publish, when ``publish_markers``) a goal marker at ``pos`` (m, world); None removes it.

        Raises:
            ConfigError: ``pos`` is not three finite numbers.
        """
        if pos is None:
            self.goal_marker = None
            if self.publish_markers:
                self.markers.publish(self._marker("goal", GOAL_MARKER_ID, (0, 0, 0), (1, 0, 0, 1), action="delete"))
            return
        p = np.asarray(pos, dtype=np.float64)
        if p.shape != (3,) or not np.isfinite(p).all():
            raise ConfigError(f"goal marker: expected 3 finite coordinates, got {pos!r}")
        self.goal_marker = p
        if self.publish_markers:
            self.markers.publish(self._marker("goal", GOAL_MARKER_ID, p, (0.9, 0.1, 0.1, 0.8)))

    def _on_marker_in(self, msg: Marker) -> None:
        self.set_goal_marker(None if msg.action == "delete" else msg.position)

    # ------------------------------------------------------------------------------------------- control API

    def _drop_pending(self) -> None:
        self._pending = None
        self._seen = self.commands.received
        if self._cmd_line is not None:
            self._cmd_line.clear()

    def set_mode(self, mode: str) -> None:
        """Switch the controller mode (``position``, ``velocity``, ``hold``, ``stop``).

        Raises:
            ConfigError: unknown mode.
        """
        self.sim.set_mode(mode)
        if mode in ("hold", "stop"):
            self._drop_pending()

    def hold(self) -> None:
        self.set_mode("hold")

    def stop(self) -> None:
        self.set_mode("stop")

    def new_episode(self, seed: int | None = None) -> None:
        """Draw the next episode's imperfections (``randomize``) and apply them to the sim and the emulated link;
        the next ``reset`` keeps them. Without ``randomize``, nothing.

        Args:
            seed: draw from this seed (with ``randomize.seed``): the same seed, the same draw; None: the next draw
                of the node's own sequence.
        """
        if self.randomize is None:
            return
        rng = self._draws if seed is None else np.random.default_rng([self.randomize.seed, seed, 41])
        imp = self.randomize.draw(rng)
        emu = imp.emulation()
        ids = self.sim._act_ids
        factors: dict[str, np.ndarray] = {}

        def perturb(model: Any) -> None:
            factors.update(perturb_model(model, emu, np.random.default_rng(emu.seed), actuator_ids=ids))

        self.sim.set_effects(imp.servo_effects(self.robot), perturb)
        self.imperfections, self.emulation, self.perturbation = imp, emu, factors
        if self._state_line is not None:
            self._state_line.latency = emu.state_latency
        if self._cmd_line is not None:
            self._cmd_line.latency = emu.command_latency
        self._episode_drawn = True

    def reset(self, q: ArrayLike | None = None) -> JointState:
        """Teleport to ``q`` (default: home) at rest; commands in flight are dropped. With ``randomize``, a new
        episode's imperfections are drawn first, unless ``new_episode`` drew them since the last reset.

        Raises:
            ConfigError: bad ``q``.
        """
        if not self._episode_drawn:
            self.new_episode()
        self._episode_drawn = False
        state = self.sim.reset(q)
        self._drop_pending()
        return state

    # ------------------------------------------------------------------------------------------- services

    def _q_text(self) -> str:
        return np.array2string(self.sim.qpos, precision=4, separator=", ")

    def _srv_hold(self, req: Empty) -> Trigger:
        self.hold()
        return Trigger(success=True, message=f"holding at {self._q_text()}")

    def _srv_stop(self, req: Empty) -> Trigger:
        self.stop()
        return Trigger(success=True, message=f"stopping near {self._q_text()}")

    def _srv_set_mode(self, req: Text) -> Trigger:
        try:
            self.set_mode(req.data)
        except ConfigError as exc:
            return Trigger(success=False, message=str(exc))
        return Trigger(success=True, message=f"mode {req.data}")

    def _srv_reset(self, req: Data) -> Trigger:
        value = req.value
        q = None
        if isinstance(value, dict):
            unknown = set(value) - {"q"}
            if unknown:
                return Trigger(success=False, message=f"reset: unknown key(s) {sorted(unknown)}; expected 'q'")
            q = value.get("q")
        elif value is not None:
            return Trigger(success=False, message=f"reset: expected None or {{'q': [...]}}, got {value!r:.80}")
        try:
            self.reset(q)
        except (ConfigError, TypeError, ValueError) as exc:
            return Trigger(success=False, message=str(exc))
        return Trigger(success=True, message=f"reset to {self._q_text()}")

    def _srv_new_episode(self, req: Data) -> Data:
        value = req.value
        seed = value.get("seed") if isinstance(value, dict) else None
        if value is not None and (
            not isinstance(value, dict)
            or set(value) - {"seed"}
            or (seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or seed < 0))
        ):
            return Data(value={"error": f"new_episode: expected None or {{'seed': int >= 0}}, got {value!r:.80}"})
        self.new_episode(seed)
        if self.imperfections is None:
            return Data(value={})
        return Data(value=self.imperfections.as_dict())

    def drawn(self) -> dict[str, Any]:
        """This episode's drawn imperfections (strengths, seed, the servo effects' values), or {}."""
        if self.imperfections is None:
            return {}
        out = self.imperfections.as_dict()
        if self.sim.effects is not None:
            out["servo"] = self.sim.effects.drawn()
        return out

    def _srv_stats(self, req: Empty) -> Data:
        out: dict[str, Any] = dataclasses.asdict(self.sim.stats)
        out["mode"] = self.sim.mode
        out["published"] = self.joint_states.published
        if self._state_line is not None:
            out["state_lost"] = self._state_line.lost
        if self._cmd_line is not None:
            out["command_lost"] = self._cmd_line.lost
        out["stale_commands"] = self.stale_commands
        out["repeated_states"] = self.repeated_states
        if self.imperfections is not None:
            out["imperfections"] = self.drawn()
        return Data(value=out)


def build_sim(
    robot: RobotSpec | str,
    config: ServoSimConfig | None = None,
    emulation: EmulationConfig | None = None,
    imperfections: Imperfections | None = None,
) -> tuple[ServoSim, dict[str, np.ndarray]]:
    """A ServoSim of ``robot``; for an emulated real arm its model is perturbed first (seeded).

    ``imperfections`` adds its servo-side knobs to the sim (``Imperfections.servo_effects``); its bus-side knobs
    are ``imperfections.emulation()``, which the caller passes as ``emulation``.

    Returns:
        The sim and the perturbation factors drawn ({} without emulation).
    """
    spec = get_robot_spec(robot) if isinstance(robot, str) else robot
    config = config or ServoSimConfig()
    effects = None if imperfections is None else imperfections.servo_effects(spec)
    if emulation is None:
        return ServoSim(spec, config, effects=effects), {}
    model = load_model(spec, config.physics_dt_s)
    act_ids = [model.actuator(n).id for n in spec.arm_joint_names]
    factors = perturb_model(model, emulation, np.random.default_rng(emulation.seed), actuator_ids=act_ids)
    return ServoSim(spec, config, model=model, effects=effects), factors


@contextlib.asynccontextmanager
async def open_servo_sim(
    robot: RobotSpec | str,
    *,
    domain: str | Domain | None = None,
    namespace: str | None = None,
    config: ServoSimConfig | None = None,
    clock: Clock | None = None,
    emulation: EmulationConfig | None = None,
    imperfections: Imperfections | None = None,
    randomize: Randomization | None = None,
    publish_markers: bool = False,
    node_name: str = "servo_sim",
    transport: str = "auto",
    options: TransportOptions | None = None,
    max_command_age_s: float | None = None,
    on_event: Callable[[dict[str, Any]], None] | None = None,
) -> AsyncIterator[ServoSimNode]:
    """Run a servo sim node in this process for the duration of the block.

    Args:
        robot: a RobotSpec or robot name.
        domain: the Domain (or its URI) to join; None: ``$UNIROS_DOMAIN``.
        namespace: topic namespace; default ``/<robot name>``.
        config: servo settings.
        clock: the domain's clock; a SimClock (not a follower) without a driver is driven by this node.
        emulation: make it an emulated real arm (perturbed, noisy, delayed).
        imperfections: servo-level imperfections with a strength (``uniros_async.sim.imperfections``); without
            ``emulation``, its bus-side knobs give the emulation.
        randomize: draw the imperfections afresh at every reset from these ranges (seeded); replaces
            ``emulation`` and ``imperfections``.
        publish_markers: publish the EE marker every tick and goal markers on ``markers``.
        node_name: the node's name within the namespace.
        transport: the node's transport choice (``auto``, ``memory``, ``shm``, ``tcp``).
        options: transport options.
        max_command_age_s: drop commands older than this (``ServoSimNode.max_command_age_s``); None: keep all.
        on_event: called with every command and watchdog event (see the module docstring).

    Yields:
        The running ServoSimNode; leaving the block stops it (tasks cancelled, names unregistered). If this node
        drove a SimClock, time stops with it: nodes still sleeping on that clock wait until another driver runs.

    Raises:
        ConfigError: bad robot, config or namespace.
        SimulationError: (inside an ExceptionGroup, from the node's tasks) physics diverged.
    """
    spec = get_robot_spec(robot) if isinstance(robot, str) else robot
    if randomize is not None:  # the nominal model, perturbed afresh at every reset
        emulation, imperfections = Imperfections().emulation(), None
        sim, factors = build_sim(spec, config)
    else:
        if imperfections is not None and emulation is None:
            emulation = imperfections.emulation()
        sim, factors = build_sim(spec, config, emulation, imperfections)
    ns = namespace if namespace is not None else f"/{spec.name}"
    async with open_node(
        node_name, domain=domain, namespace=ns, clock=clock, transport=transport, options=options
    ) as node:
        sim_node = ServoSimNode(
            node,
            sim,
            emulation=emulation,
            perturbation=factors,
            publish_markers=publish_markers,
            max_command_age_s=max_command_age_s,
            on_event=on_event,
            randomize=randomize,
        )
        async with unwrap_task_group() as tg:
            await sim_node._start(tg)
            try:
                yield sim_node
            finally:
                sim_node._shutdown()
