"""The env worker process: one environment (or several), served to the agent side over the project's own transports.

A worker is started with one frozen ``WorkerSpec``: by the supervisor as ``python -m uniros_async.runtime``
(``launch.start_worker``, ``__main__.py``), and the same way by a Ray actor on the node Ray placed it on
(``ray_host.py``). It listens on ``shm://`` (a unique name), hands the listen URI to the supervisor through the
start-up pipe, accepts one connection, builds its env with ``gymnasium.make(env_id, **kwargs)`` (or calls the env
factory it was given, ``specs.normalize_specs``) and then answers requests until told to close or until the
supervisor goes away. A spec with ``mates`` (``make_vec(envs_per_worker=...)``) makes the process do the same for
each of them too, every env with its own listener and connection, all served on the one event loop: where
accelerated envs outnumber the cores, one process per core keeps a core's caches for its envs instead of switching
between processes at every step.

One event loop per worker (docs/architecture.md): a uniros env is made inside ``envs.runtime.deferred_start()`` and
started on the worker's own loop (``await env.astart()``), so its bus, servo sim and env loop run beside the
request handler, and a step is ``await env.astep(action)`` in the handler's own task: no loop thread, no hand-over
between threads, and the reply leaves as soon as the step's coroutine returns (before the rest of what the same
sim event woke runs). The wrappers gymnasium and ``make_vec`` put around it (OrderEnforcing, TimeLimit, PadSpaces)
are applied by ``astep_through`` / ``areset_through`` (runtime/attached.py) with the same semantics; an env with any
other wrapper, or one that is not a uniros BaseEnv, runs on a loop thread and is stepped through its synchronous API,
as it would be in the agent's own process.

The requests and replies are those of runtime/protocol.py. An exception while serving a request is sent back (the
supervisor raises it as WorkerError) and the worker keeps serving; an exception while building the env is sent as
the reply to the first request, and the worker exits.

Lifetime: the worker ignores SIGINT (the agent's Ctrl-C is the supervisor's business), stops on SIGTERM
(the root task is cancelled, the env closed in ``finally``), and stops when the supervisor dies: the connection
breaks (EOF on the shm socket) and, as a backstop for a worker blocked in a long env call, a watchdog thread sees
the parent exit, cancels the root task and, if that has not ended the process within ``exit_grace_s``, calls
``os._exit``. The watchdog waits in ``poll(2)`` on a pidfd of the parent, which holds no GIL until the parent
exits. A thread that woke every 0.1 s to compare ``getppid()`` took the GIL ten times a second in the ordinary
scheduling class. The env loop's thread, in the real-time class, then had to wait for it whenever CPU load beside
kept it off a core while it held or was being handed the GIL (CPython's forced switch waits until the other thread
has taken the GIL): an inversion of priorities that no class on the loop's thread prevents (docs/reliability.md,
"Real time under load").
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import multiprocessing
import multiprocessing.connection
import os
import select
import signal
import threading
import time
from typing import Any

import gymnasium as gym

from uniros_async._signals import cancel_on_signals
from uniros_async.errors import TransportError
from uniros_async.runtime.attached import areset_through, astep_through, base_env_class, supports_async
from uniros_async.runtime.cores import cores_shared, move_off_core, on_loopback, turn_spin_ns, usable_cpus
from uniros_async.runtime.protocol import (
    AUTORESET_MODES,
    conform,
    error_reply,
    pack,
    pack_step_reply,
    reply_value,
    space_to_plain,
    unpack,
)
from uniros_async.runtime.specs import factory_of

__all__ = [
    "LOOP_PHASE_STEP_NS",
    "WorkerSpec",
    "worker_entry",
    "worker_main",
]

logger = logging.getLogger(__name__)

LOOP_PHASE_STEP_NS = 1_000_000
"""A real-time env's loop ticks and step deadlines fall ``loop_phase`` (the supervisor's choice: by default its rank)
times this much after the common grid (``RobotEnv.loop_phase_ns``), so the members of a vector env tick and return one
after the other, the highest-ranked last. On one instant, workers that outnumber the cores run in priority order anyway,
and the later ones start whenever the others' variable work lets them, so the last reply, which the agent waits for,
scatters; staggered, each runs alone and the last reply comes from the worker with the highest priority. The step is
well above a worker's tick or return, even with cold caches; the first member's returns wait up to ``n - 1`` steps
longer for the agent."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class WorkerSpec:
    """Everything a worker needs, fixed at start.

    Attributes:
        index: the sub-environment index (named in every WorkerError).
        env_id: a registered gymnasium id.
        kwargs: keyword arguments for ``gymnasium.make`` (plain, picklable data).
        parent_pid: the supervisor's pid; the worker exits when its parent changes.
        accept_timeout_s: how long the worker waits for the supervisor to connect.
        exit_grace_s: after the supervisor died, how long a clean shutdown may take before ``os._exit``.
        listen_uri: where the worker listens for the supervisor: ``shm://`` (a unique name; same machine) or
            ``tcp://127.0.0.1:0`` (a free port).
        auth_key: shared key the supervisor must prove (HMAC handshake) before the worker serves it; a worker
            placed by Ray listens with its vector env's key.
        rt_rank: for a real-time env, the rank of its SCHED_RR priority among the workers of its vector env
            (``priority.raise_loop_priority``; the supervisor gives the first worker the highest).
        loop_phase: for a real-time env, its loop's phase in ``LOOP_PHASE_STEP_NS`` (``Supervisor``'s
            ``loop_phase_base``).
        registration: ``gymnasium.register`` keyword arguments for ``env_id`` as the agent's process has it
            registered (``envargs.registration``), used when this fresh interpreter does not know the id.
        agent_pid: the agent's pid when it is not ``parent_pid`` (a worker a Ray actor started): over tcp on
            loopback the worker's poll looks where the agent runs (``TcpTransport.peer_pid``).
        environ: environment variables set in the worker before it builds its env: those the agent set after the
            worker's interpreter started (``WorkerProcess.environ_changes``), and what the agent's imports found
            already, so that the worker's imports need not search again (``launch.found_libraries``).
        mates: the other envs this process hosts (``make_vec(envs_per_worker=...)``), each with its own listener,
            connection and index; ``worker_main`` serves them all on its one event loop.
    """

    index: int
    env_id: str
    kwargs: dict[str, Any] = dataclasses.field(default_factory=dict)
    parent_pid: int = 0
    accept_timeout_s: float = 60.0
    exit_grace_s: float = 3.0
    listen_uri: str = "shm://"
    auth_key: bytes | None = None
    rt_rank: int = 0
    loop_phase: int = 0
    registration: dict[str, Any] | None = None
    agent_pid: int = 0
    environ: dict[str, str] = dataclasses.field(default_factory=dict)
    mates: tuple[WorkerSpec, ...] = ()


# ---------------------------------------------------------------- the worker


def worker_entry(spec: WorkerSpec, conn: multiprocessing.connection.Connection) -> None:
    """Process target: run ``worker_main`` and exit."""
    # The agent's Ctrl-C reaches every process of the group; the supervisor decides how workers stop.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # multiprocessing forbids children of daemon processes; an env with robot="sim-process" or "emulated-real"
    # starts its own servo process (itself daemonic, and it exits with us). Clearing the flag in this process only
    # changes what this process believes about itself; the supervisor still treats us as daemonic.
    multiprocessing.current_process()._config["daemon"] = False  # type: ignore[attr-defined]
    try:
        asyncio.run(worker_main(spec, conn))
    except (KeyboardInterrupt, asyncio.CancelledError):
        pass
    finally:
        conn.close()


def _wait_for_exit(pid: int) -> None:
    """Return once ``pid``, this process's parent, has exited (or is not our parent any more).

    Blocks in ``poll(2)`` on a pidfd, without the GIL and without waking until then; where pidfds are missing (not
    Linux, or a kernel before 5.3), polls ``getppid()`` every 0.1 s instead.
    """
    fd = None
    with contextlib.suppress(AttributeError, OSError):  # no os.pidfd_open, or the pid is gone already
        fd = os.pidfd_open(pid)
    if fd is not None:
        try:
            if os.getppid() == pid:  # the pidfd is our parent's, not a reused pid's
                poller = select.poll()
                poller.register(fd, select.POLLIN)
                poller.poll()  # readable when the process exits
            return
        finally:
            os.close(fd)
    while os.getppid() == pid:
        time.sleep(0.1)


def _start_watchdog(spec: WorkerSpec, loop: asyncio.AbstractEventLoop, task: asyncio.Task[Any]) -> None:
    parent = spec.parent_pid or os.getppid()

    def watch() -> None:
        _wait_for_exit(parent)
        logger.warning("worker %d: supervisor %d is gone; stopping", spec.index, parent)
        try:
            loop.call_soon_threadsafe(task.cancel)
        except RuntimeError:  # the loop already closed: we are exiting anyway
            return
        time.sleep(spec.exit_grace_s)
        os._exit(1)

    threading.Thread(target=watch, name=f"uniros-worker-{spec.index}-watchdog", daemon=True).start()


async def worker_main(spec: WorkerSpec, conn: multiprocessing.connection.Connection) -> None:
    """Listen (once per env this process hosts: ``spec`` and its ``mates``), hand the URIs over ``conn`` in that
    order, then accept, build and serve each env on this event loop until every one is closed."""
    from uniros_async.transports.base import TransportOptions, listen

    loop = asyncio.get_running_loop()
    task = cancel_on_signals(signal.SIGTERM)
    _start_watchdog(spec, loop, task)
    hosted = (spec, *spec.mates)
    listeners: list[Any] = []
    try:
        for s in hosted:
            listeners.append(await listen(s.listen_uri, TransportOptions(auth_key=s.auth_key)))
            conn.send(listeners[-1].uri)
        builds = asyncio.Lock()  # one env built at a time: the threads each build starts are told apart
        # every connection accepted before any env is built: a build holds this loop, and a handshake held past
        # its listener's deadline is dropped
        accepted = asyncio.Barrier(len(hosted))
        async with asyncio.TaskGroup() as tg:
            for s, listener in zip(hosted, listeners, strict=True):
                tg.create_task(_host(s, listener, builds, accepted, shared_loop=len(hosted) > 1))
    finally:
        for listener in listeners:
            await listener.aclose()


async def _host(
    spec: WorkerSpec, listener: Any, builds: asyncio.Lock, accepted: asyncio.Barrier, *, shared_loop: bool
) -> None:
    """Accept the supervisor on ``listener``, wait until every env of this process is accepted (``accepted``),
    build ``spec``'s env and serve it until it is closed or the supervisor goes away. ``shared_loop``: other envs
    are served on this loop too; no poll for the next request then (it would hold the loop that steps them)."""
    transport = None
    server = _Server(spec)
    try:
        async with asyncio.timeout(spec.accept_timeout_s):
            transport = await listener.accept()
        await listener.aclose()
        async with asyncio.timeout(spec.accept_timeout_s):
            await accepted.wait()
        from uniros_async.priority import thread_ids

        async with builds:
            before = thread_ids()
            await server.build()
            if shared_loop and server.realtime and server.build_error is None:
                from uniros_async.errors import ConfigError

                why = ConfigError(
                    f"{spec.env_id} runs on the wall clock (a real-time env loop), which needs a worker process of its"
                    " own: make_vec(envs_per_worker=1); the steps of the other envs on its event loop would hold its"
                    " ticks"
                )
                server.build_error = error_reply(why, f"could not host {spec.env_id} with other envs")
            else:
                server.raise_loop_priority(thread_ids() - before)
        if hasattr(transport, "spin_ns"):  # shm and tcp
            # a real-time env loop shares this event loop now: its ticks matter more than the wake-up a poll
            # for the next request would save, and the poll would hold the loop (up to its spin window)
            transport.spin_ns = 0 if server.realtime or shared_loop else turn_spin_ns(transport)
        if hasattr(transport, "on_shared_core") and not server.realtime:
            transport.on_shared_core = move_off_core
            if hasattr(transport, "peer_pid") and on_loopback(transport):  # tcp: TcpTransport._peer_here
                transport.peer_pid = spec.agent_pid or spec.parent_pid
        await server.serve(transport)
    except TransportError:
        logger.info("worker %d: the supervisor went away", spec.index)
    finally:
        await server.aclose()
        if transport is not None:
            await transport.aclose()


class _Server:
    """The env and the request handlers of one worker."""

    def __init__(self, spec: WorkerSpec) -> None:
        self.spec = spec
        self.env: gym.Env[Any, Any] | None = None
        self.build_error: dict[str, Any] | None = None
        self.needs_autoreset = False
        self.attached = False  # the env runs on this process's event loop and is stepped with astep_through
        self.realtime = False  # ... and its env loop follows the wall clock
        self._conform_action: Any = None  # protocol.conform for the action space, where an action needs it
        self.tag_infos = False
        self.transport: Any = None
        self.cores_shared = False  # more workers of this vector env than cores here (``_share_cores``)
        self.pinned_cpu: int | None = None

    async def build(self) -> None:
        import uniros_async  # noqa: F401  (registers the uniros ids in this fresh interpreter)
        from uniros_async.envs.runtime import deferred_start
        from uniros_async.priority import freeze_heap

        os.environ.update(self.spec.environ)
        try:
            reg = self.spec.registration
            if reg is not None and reg["id"] not in gym.registry:
                gym.register(**reg)
            factory = factory_of(self.spec.kwargs)
            with deferred_start():
                if factory is None:
                    env = gym.make(self.spec.env_id, **self.spec.kwargs)
                else:
                    env = _env_from_factory(factory)
                self.env = env
            # before the env's loop starts: the collection that starts a freeze walks the whole heap, and
            # without the freeze the first full collection would come in the loop's first seconds, on its thread
            freeze_heap()
            self._conform_action = _action_conformer(env.action_space)
            base = env.unwrapped
            realtime = getattr(getattr(base, "config", None), "clock", "sim") != "sim"
            if realtime and hasattr(base, "loop_phase_ns"):
                base.loop_phase_ns = self.spec.loop_phase * LOOP_PHASE_STEP_NS  # before its loop starts
            base_env = base_env_class()
            if base_env is not None and isinstance(base, base_env) and base.attached:
                if supports_async(env):
                    await base.astart()
                    self.attached = True
                    self.realtime = realtime
                else:
                    base.start_thread()  # unknown wrappers: the synchronous API over a loop thread, as in-process
        except gym.error.UnregisteredEnv as exc:  # registered where the caller runs, as it was checked there
            where = (
                "this worker is a fresh interpreter, where only the uniros ids, gymnasium's own and the ids that "
                "modules imported at start-up register exist: register the env when a module is imported and name it "
                "'module:Id'"
            )
            self.build_error = error_reply(exc, f"could not make {self.spec.env_id} ({where})")
        except Exception as exc:  # noqa: BLE001 - sent back to the supervisor
            self.build_error = error_reply(exc, f"could not make {self.spec.env_id}")

    def raise_loop_priority(self, started: set[int]) -> None:
        """Once a wall-clock env is built and its loop ticks: the real-time class for the threads that run it, not
        for its start-up (see ``uniros_async.priority``): this one, which also serves its steps, the env's loop
        thread where it has one, and the threads its build started (``started``: they deliver to the loop, as a
        ROS 2 arm's cyclonedds receive threads do). Threads and processes they start later begin ordinary."""
        env = self.env
        if env is None or getattr(getattr(env.unwrapped, "config", None), "clock", None) != "wall":
            return  # not built, accelerated (sim clock, computes flat out), or no uniros env: no loop to keep on time
        from uniros_async.priority import raise_loop_priority

        raise_loop_priority(self.spec.rt_rank)
        for tid in started:  # among them the env's loop thread (the synchronous API over unknown wrappers)
            raise_loop_priority(self.spec.rt_rank, thread_id=tid)

    async def serve(self, transport: Any) -> None:
        self.transport = transport
        try_send = getattr(transport, "try_send", None)  # shm, tcp: a step's reply leaves without a coroutine
        while True:
            frame = await transport.receive()
            try:
                request = unpack(frame)
            except Exception as exc:  # noqa: BLE001
                await transport.send(pack(error_reply(exc, "bad request")))
                continue
            op = request.get("op")
            if self.build_error is not None:
                await transport.send(pack(self.build_error))
                return
            try:
                if op == "step" and not self.attached:  # a synchronous env's step: no coroutine in the way
                    result = self._step_now(request["action"], request.get("autoreset"))
                else:
                    result = await self.handle(op, request)
            except Exception as exc:  # noqa: BLE001 - sent back; the env stays usable when it can
                reply = error_reply(exc, f"{op} failed")
            else:
                if op == "step":
                    frame = pack_step_reply(result)
                    if try_send is None or not try_send(frame):
                        await transport.send(frame)
                    continue
                reply = {"ok": True, "result": result}
            await transport.send(pack(reply))
            if op == "close":
                return

    async def handle(self, op: Any, request: dict[str, Any]) -> Any:
        env = self.env
        assert env is not None
        if op == "step":
            ref = request.get("t")
            if ref is not None and self.attached:
                base: Any = env.unwrapped
                base.step_reference_ns = ref  # see RobotEnv._step_deadline
            return await self._step(request["action"], request.get("autoreset"))
        if op == "spaces":
            # tag_infos: add info["env_id"] to every info (in a vector env of different envs, which one spoke);
            # otherwise the infos are the env's own
            self.tag_infos = bool(request.get("tag_infos"))
            self._share_cores(request.get("share"))
            return self._spaces()
        if op == "pad":
            from uniros_async.envs.wrappers import PadSpaces

            self.env = PadSpaces(env, int(request["obs_size"]), int(request["action_size"]))
            self._conform_action = _action_conformer(self.env.action_space)
            return self._spaces()
        if op == "reset":
            self.needs_autoreset = False
            obs, info = await self._reset(request.get("seed"), request.get("options"))
            return [obs, self._info(info)]
        if op == "call":
            attr = self._attr(request["name"])
            if callable(attr):
                attr = attr(*request.get("args", []), **request.get("kwargs", {}))
            return reply_value(attr)
        if op == "get":  # reading is harmless: private attributes too
            return reply_value(self._attr(request["name"], private=True))
        if op == "set":
            name = request["name"]
            if name.startswith("_"):
                raise AttributeError(f"refusing to set private attribute {name!r}")
            env.set_wrapper_attr(name, request["value"])
            return None
        if op == "render":
            return env.render()
        if op == "is_wrapped":
            return _is_wrapped(env, str(request["wrapper"]))
        if op == "close":
            await self.aclose()
            return None
        raise ValueError(
            f"unknown op {op!r}; expected spaces, pad, reset, step, call, get, set, render, is_wrapped or close"
        )

    def _attr(self, name: str, *, private: bool = False) -> Any:
        """Attribute ``name`` of the env, looked up through its wrappers as gymnasium's vector envs do (a private
        one only with ``private``).

        Raises:
            AttributeError: no such attribute, or a private one without ``private``.
        """
        if name.startswith("_") and not private:
            raise AttributeError(f"refusing to call private attribute {name!r}")
        env = self.env
        assert env is not None
        return env.get_wrapper_attr(name)

    def _share_cores(self, share: list[Any] | None) -> None:
        """``share``: ``[slot, count, mode]`` from the supervisor, this worker's rank among the ``count`` workers of
        its vector env on this machine and the agent's ``shared_cores_mode``. When they outnumber the cores here
        (``cores_shared``; never for a real-time env loop, which has its own priority), stop polling for the next
        request, run each step through
        (``priority.run_steps_through``) and, with ``pin``, stay on core ``slot`` modulo the cores (round robin: as
        many workers on each core as can be).

        Left to the scheduler, where a step's wake-ups put the workers decides how long the step takes (4 on 2
        cores placed 3 and 1: the core with 3 takes 3 step times while the other idles after 1, ~67 % of the
        physics bound), and a woken worker tends to land where it ran before, so a placement lasts. Pinned, each
        core gets its share in every run (docs/performance.md, "More envs than cores"). Once set up, the policy
        stays.

        As many workers as cores or more (crowded or not) have no core each apart from the agent's: they do not move
        off the agent's core (``on_shared_core`` cleared), since one that did would land on a fellow worker's and the
        two would step in turn.
        """
        if self.cores_shared or self.realtime or not share:
            return
        slot, count, mode = int(share[0]), int(share[1]), str(share[2])
        cpus = usable_cpus()
        if count >= len(cpus) and hasattr(self.transport, "on_shared_core"):
            self.transport.on_shared_core = None
        if mode == "off" or not cores_shared(count):
            return
        self.cores_shared = True
        from uniros_async.priority import run_steps_through

        if hasattr(self.transport, "spin_ns"):
            self.transport.spin_ns = 0
        how = run_steps_through()
        if mode == "pin":
            cpu = cpus[slot % len(cpus)]
            try:
                os.sched_setaffinity(0, {cpu})
                self.pinned_cpu = cpu
            except (AttributeError, OSError) as exc:  # not permitted here: the scheduler places it
                logger.debug("worker %d: could not pin to cpu %d: %s", self.spec.index, cpu, exc)
        logger.debug(
            "worker %d: %d workers share %d cores here; steps run through (%s), pinned to %s",
            self.spec.index,
            count,
            len(cpus),
            how,
            self.pinned_cpu,
        )

    def _spaces(self) -> dict[str, Any]:
        env = self.env
        assert env is not None
        return {
            "observation_space": space_to_plain(env.observation_space),
            "action_space": space_to_plain(env.action_space),
            "metadata": {
                k: v for k, v in env.metadata.items() if v is None or isinstance(v, bool | int | float | str | list)
            },
            "render_mode": env.render_mode,
            "max_episode_steps": env.spec.max_episode_steps if env.spec is not None else None,
            "pid": os.getpid(),
            "realtime": self.realtime,  # a real-time env loop shares this worker's event loop
            "cores_shared": self.cores_shared,
            "pinned_cpu": self.pinned_cpu,
            "moves_off_agent_core": getattr(self.transport, "on_shared_core", None) is not None,
        }

    def _info(self, info: dict[str, Any]) -> dict[str, Any]:
        return {**info, "env_id": self.spec.env_id} if self.tag_infos else info

    async def _reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        env = self.env
        assert env is not None
        if self.attached:
            return await areset_through(env, seed, options)
        return env.reset(seed=seed, options=options)

    async def _step(self, action: Any, autoreset: str | None) -> list[Any]:
        env = self.env
        assert env is not None
        if not self.attached:
            return self._step_now(action, autoreset)
        if self._reset_instead(autoreset):
            obs, info = await self._reset()
            return [obs, 0.0, False, False, self._info(info)]
        conform_action = self._conform_action
        if conform_action is not None:
            action = conform_action(action)
        result, reset = self._returns(*await astep_through(env, action), autoreset)
        if reset:
            final_obs = result[0]
            result[0], info = await self._reset()
            result[4] = self._same_step_info(final_obs, result[4], info)
        return result

    def _step_now(self, action: Any, autoreset: str | None) -> list[Any]:
        """``_step`` for an env stepped through its synchronous API (not attached), in the caller's frame."""
        env = self.env
        assert env is not None
        if self._reset_instead(autoreset):
            obs, info = env.reset()
            return [obs, 0.0, False, False, self._info(info)]
        conform_action = self._conform_action
        if conform_action is not None:
            action = conform_action(action)
        result, reset = self._returns(*env.step(action), autoreset)
        if reset:
            final_obs = result[0]
            result[0], info = env.reset()
            result[4] = self._same_step_info(final_obs, result[4], info)
        return result

    def _reset_instead(self, autoreset: str | None) -> bool:
        """Whether this step resets instead (gymnasium's NEXT_STEP mode: the step after an episode's end resets and
        ignores the action).

        Raises:
            ValueError: an unknown autoreset mode.
        """
        if autoreset == "next_step":
            if self.needs_autoreset:
                self.needs_autoreset = False
                return True
            return False
        if autoreset not in AUTORESET_MODES:
            raise ValueError(f"autoreset must be one of {AUTORESET_MODES}, got {autoreset!r}")
        return False

    def _returns(
        self, obs: Any, reward: Any, terminated: Any, truncated: Any, info: dict[str, Any], autoreset: str | None
    ) -> tuple[list[Any], bool]:
        """A step's reply, and whether the env must now be reset in the same step (SAME_STEP: the reply then carries
        the reset's observation, ``_same_step_info``)."""
        done = bool(terminated or truncated)
        if self.tag_infos:
            info = self._info(info)
        if autoreset == "next_step":
            self.needs_autoreset = done
        elif autoreset == "same_step" and done:
            return [obs, float(reward), bool(terminated), bool(truncated), info], True
        return [obs, float(reward), bool(terminated), bool(truncated), info], False

    def _same_step_info(self, final_obs: Any, step_info: dict[str, Any], reset_info: dict[str, Any]) -> dict[str, Any]:
        """The info of a step that ended an episode and reset at once, as gymnasium's SAME_STEP mode builds it per
        sub-env: the reset's info, with the step's observation and info as ``final_obs`` and ``final_info``."""
        return {**self._info(reset_info), "final_obs": final_obs, "final_info": step_info}

    async def aclose(self) -> None:
        env, self.env = self.env, None
        if env is None:
            return
        if self.attached:
            base: Any = env.unwrapped
            await base.aclose()  # the wrappers' close() only passes close on
        else:
            env.close()


def _env_from_factory(payload: bytes) -> gym.Env[Any, Any]:
    """The env that a pickled env factory (``specs.normalize_specs``) builds.

    Raises:
        TypeError: the factory returned something other than a gymnasium.Env.
    """
    import cloudpickle

    env = cloudpickle.loads(payload)()
    if not isinstance(env, gym.Env):
        raise TypeError(f"the env factory returned {type(env).__name__}, expected a gymnasium.Env")
    return env


def _action_conformer(space: gym.Space[Any]) -> Any:
    """``conform`` for actions of ``space`` (a Tuple's arrive as lists), or None where actions arrive as the env
    takes them (a Box's as arrays, a Discrete's as ints): a step then costs nothing more."""
    if isinstance(space, gym.spaces.Box | gym.spaces.Discrete):
        return None
    return lambda action: conform(space, action)


def _is_wrapped(env: gym.Env[Any, Any], wrapper: str) -> bool:
    """Whether a wrapper of class ``wrapper`` (``"module:QualName"``) is around the env, as SB3's
    ``env_is_wrapped`` asks; False when that class cannot be imported here (then no wrapper of it can be there)."""
    import importlib

    module, _, name = wrapper.partition(":")
    try:
        cls: Any = importlib.import_module(module)
        for part in name.split("."):
            cls = getattr(cls, part)
    except (ImportError, AttributeError):
        return False
    e: Any = env
    while isinstance(e, gym.Wrapper):
        if isinstance(e, cls):
            return True
        e = e.env
    return False
