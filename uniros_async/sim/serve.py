"""A servo sim outside the caller's process: in a child process of the same domain, or as a remote service.

- ``open_servo_sim_process(robot, domain=uri)``: spawns a process (``get_context("spawn")``, daemon) that joins
  the caller's domain by its tcp (or tls) URI and runs the ServoSimNode there; data between the processes goes over
  shm when both are on one machine (the bus picks it per connection), else the domain's tcp or tls. Leaving the
  block stops the process (a stop message, then ``join``, then ``terminate``, then ``kill``): no process outlives
  the block.
- ``serve_servo_sim(robot, host=..., port=...)``: opens its own domain on ``tcp://HOST:PORT`` (``tls=True``:
  ``tls://HOST:PORT``, mutual TLS) and runs the node in it until cancelled; ``uniros robot serve rx200 --port 0
  --emulate-real`` (``--tls``) prints that URI on stdout and serves until SIGINT/SIGTERM. With ``emulation`` it is
  the emulated real arm (sim/emulated.py), reached only over the network, tcp or tls (its node offers no shm
  endpoint), as a physical arm on the network would be.

Clocks: by default the sim follows wall time. ``clock="sim"`` makes it a SimClock source at ``time_scale`` that
publishes ``/clock``; nodes in other processes follow it with ``uniros_async.sim_clock.follow_clock``.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import multiprocessing
import multiprocessing.connection
import os
import signal
import sys
import traceback
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from typing import Any

from uniros_async._signals import cancel_on_signals
from uniros_async.bus.domain import Domain, open_domain
from uniros_async.clock import Clock
from uniros_async.errors import ConfigError, RobotError
from uniros_async.robots.spec import RobotSpec
from uniros_async.sim.emulated import EmulationConfig
from uniros_async.sim.imperfections import Imperfections, Randomization
from uniros_async.sim.servo import ServoSimConfig
from uniros_async.sim_clock import SimClock
from uniros_async.transports.base import TransportOptions, options_from_environ

__all__ = ["ServeConfig", "ServoSimProcess", "open_servo_sim_process", "print_event", "serve_servo_sim"]

logger = logging.getLogger(__name__)

CLOCKS = ("wall", "sim")


@dataclass(frozen=True, kw_only=True)
class ServeConfig:
    """Everything a servo sim process needs (picklable, for ``spawn``).

    Attributes:
        robot: a registered robot's name, or its RobotSpec (picklable plain data: the child then needs no import
            of the package that registered it).
        domain: URI of the domain to join (``tcp://`` or ``tls://``); None: open an own domain on
            ``tcp://host:port`` (``tls://host:port`` with ``tls``).
        host: bind host of an own domain and of the node's endpoints (under tls, the host's certificate must name
            it: peers verify the address they dial).
        port: port of an own domain (0: a free one).
        namespace: topic namespace; None: ``/<robot>``.
        node_name: the node's name.
        servo: servo settings.
        emulation: an emulated real arm's perturbations, or None for the nominal sim.
        imperfections: servo-level imperfections with a strength (``open_servo_sim``), or None.
        randomize: imperfections drawn afresh for every episode (``open_servo_sim``), or None.
        clock: ``"wall"`` or ``"sim"`` (a SimClock source publishing ``/clock``).
        time_scale: the SimClock's time scale (None: unbounded); only with ``clock="sim"``.
        transport: the node's transport choice; ``auto`` uses shm to peers on the same machine.
        publish_markers: publish EE and goal markers.
        auth_key: shared key of the domain; None: ``$UNIROS_AUTH_KEY`` if set, else none.
        insecure: allow a non-loopback ``host`` without ``auth_key`` (else the domain refuses to start).
        tls: open the own domain on ``tls://`` (mutual TLS; no ``auth_key`` needed beyond loopback).
        tls_cert_file: this process's certificate for ``tls://``; None: ``$UNIROS_TLS_CERT``.
        tls_key_file: its private key; None: ``$UNIROS_TLS_KEY`` (or in the certificate file).
        tls_ca_file: the CA the peers' certificates must be signed by; None: ``$UNIROS_TLS_CA``.
        max_command_age_s: drop commands older than this (``ServoSimNode.max_command_age_s``); None: keep all.
        trace: write every command's age and every watchdog hold as a JSON line on stdout (``ServoSimNode.on_event``).
    """

    robot: str | RobotSpec
    domain: str | None = None
    host: str = "127.0.0.1"
    port: int = 0
    namespace: str | None = None
    node_name: str = "servo_sim"
    servo: ServoSimConfig = dataclasses.field(default_factory=ServoSimConfig)
    emulation: EmulationConfig | None = None
    imperfections: Imperfections | None = None
    randomize: Randomization | None = None
    clock: str = "wall"
    time_scale: float | None = 1.0
    transport: str = "auto"
    publish_markers: bool = False
    auth_key: bytes | None = None
    insecure: bool = False
    tls: bool = False
    tls_cert_file: str | None = None
    tls_key_file: str | None = None
    tls_ca_file: str | None = None
    max_command_age_s: float | None = None
    trace: bool = False

    def __post_init__(self) -> None:
        if self.clock not in CLOCKS:
            raise ConfigError(f"ServeConfig.clock: expected one of {CLOCKS}, got {self.clock!r}")
        if not 0 <= self.port <= 65535:
            raise ConfigError(f"ServeConfig.port: expected 0..65535, got {self.port}")
        if self.domain is not None and not self.domain.startswith(("tcp://", "tls://")):
            raise ConfigError(
                f"ServeConfig.domain: another process joins a domain over tcp or tls; expected tcp://HOST:PORT or "
                f"tls://HOST:PORT, got {self.domain!r} (open the domain with open_domain('tcp://127.0.0.1:0'))"
            )
        if self.domain is not None and self.tls:
            raise ConfigError(
                f"ServeConfig.tls opens an own domain on tls://; to join the domain {self.domain!r} over tls, give its "
                "tls:// URI as domain instead"
            )

    @property
    def scheme(self) -> str:
        """The network scheme of the domain served or joined: ``tls`` or ``tcp``."""
        if self.domain is not None:
            return "tls" if self.domain.startswith("tls://") else "tcp"
        return "tls" if self.tls else "tcp"

    def options(self) -> TransportOptions:
        key = self.auth_key if self.auth_key is not None else options_from_environ().auth_key
        return TransportOptions(
            bind_host=self.host,
            auth_key=key,
            insecure=self.insecure,
            tls_cert_file=self.tls_cert_file,
            tls_key_file=self.tls_key_file,
            tls_ca_file=self.tls_ca_file,
        )

    def make_clock(self) -> Clock | None:
        return SimClock(time_scale=self.time_scale) if self.clock == "sim" else None


async def serve_servo_sim(config: ServeConfig, *, on_ready: Callable[[str], Any] | None = None) -> None:
    """Run a servo sim node until cancelled: in ``config.domain``, or in an own domain on ``host:port``.

    Args:
        config: what to run.
        on_ready: called with the domain URI once the node serves (the CLI prints it).

    Raises:
        ConfigError: bad robot or settings.
        SimulationError: (inside an ExceptionGroup) physics diverged.
    """
    from uniros_async.sim.node import open_servo_sim

    options = config.options()
    async with contextlib.AsyncExitStack() as stack:
        if config.domain is None:
            dom: Domain | str = await stack.enter_async_context(
                open_domain(f"{config.scheme}://{config.host}:{config.port}", options=options)
            )
            uri = dom.uri  # type: ignore[union-attr]
        else:
            dom = uri = config.domain
        # the emulated real arm is a device on the network: the domain's tcp or tls only
        transport = config.scheme if config.emulation is not None and config.transport == "auto" else config.transport
        sim_node = await stack.enter_async_context(
            open_servo_sim(
                config.robot,
                domain=dom,
                namespace=config.namespace,
                config=config.servo,
                clock=config.make_clock(),
                emulation=config.emulation,
                imperfections=config.imperfections,
                randomize=config.randomize,
                publish_markers=config.publish_markers,
                node_name=config.node_name,
                transport=transport,
                options=options,
                max_command_age_s=config.max_command_age_s,
                on_event=print_event if config.trace else None,
            )
        )
        logger.info("serving %s as %s in %s", sim_node.sim.robot.name, sim_node.node.name, uri)
        if on_ready is not None:
            on_ready(uri)
        await asyncio.Event().wait()  # until cancelled


def print_event(event: dict[str, Any]) -> None:
    """Write ``event`` as one JSON line on stdout (``--trace``)."""
    sys.stdout.write(json.dumps(event) + "\n")
    sys.stdout.flush()


# ================================================================================================ child process


def _child_main(config: ServeConfig, conn: multiprocessing.connection.Connection) -> None:
    """Entry of the spawned process: run until the parent says stop, closes the pipe, or sends SIGTERM."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the parent, which stops us in order
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s servo_sim[%(process)d] %(name)s: %(message)s")
    try:
        asyncio.run(_child_async(config, conn))
    except asyncio.CancelledError:  # the stop we were asked for
        pass
    except BaseException:  # noqa: BLE001 - report every failure to the parent before dying
        with contextlib.suppress(OSError, ValueError):
            conn.send(("error", traceback.format_exc()))
        raise
    finally:
        conn.close()


async def _child_async(config: ServeConfig, conn: multiprocessing.connection.Connection) -> None:
    loop = asyncio.get_running_loop()
    main = cancel_on_signals(signal.SIGTERM)

    def on_pipe() -> None:  # "stop", or EOF when the parent died
        loop.remove_reader(conn.fileno())
        main.cancel()

    def ready(uri: str) -> None:
        from uniros_async.priority import freeze_heap, raise_loop_priority

        freeze_heap()
        # the hardware loop of a (emulated) real arm: on time beside learners and other loops, once it serves (its
        # start-up, the MuJoCo model and the domain, at normal priority: see uniros_async.priority)
        raise_loop_priority()
        conn.send(("ready", {"pid": os.getpid(), "domain": uri}))
        loop.add_reader(conn.fileno(), on_pipe)

    await serve_servo_sim(config, on_ready=ready)


class ServoSimProcess:
    """Handle of a servo sim running in a child process (from ``open_servo_sim_process``).

    Attributes:
        process: the multiprocessing.Process.
        domain: the domain URI it joined (or serves).
        namespace: its topic namespace.
    """

    def __init__(self, process: multiprocessing.process.BaseProcess, domain: str, namespace: str) -> None:
        self.process = process
        self.domain = domain
        self.namespace = namespace

    @property
    def pid(self) -> int | None:
        return self.process.pid

    def is_alive(self) -> bool:
        return self.process.is_alive()


async def _recv(conn: multiprocessing.connection.Connection, timeout_s: float) -> Any:
    loop = asyncio.get_running_loop()
    fut: asyncio.Future[None] = loop.create_future()

    def readable() -> None:
        if not fut.done():
            fut.set_result(None)

    loop.add_reader(conn.fileno(), readable)
    try:
        async with asyncio.timeout(timeout_s):
            await fut
    finally:
        loop.remove_reader(conn.fileno())
    return conn.recv()


@contextlib.asynccontextmanager
async def open_servo_sim_process(
    robot: str | RobotSpec,
    *,
    domain: str | Domain,
    namespace: str | None = None,
    config: ServoSimConfig | None = None,
    emulation: EmulationConfig | None = None,
    imperfections: Imperfections | None = None,
    randomize: Randomization | None = None,
    clock: str = "wall",
    time_scale: float | None = 1.0,
    publish_markers: bool = False,
    transport: str = "auto",
    auth_key: bytes | None = None,
    start_timeout_s: float = 30.0,
    stop_timeout_s: float = 5.0,
) -> AsyncIterator[ServoSimProcess]:
    """Run a servo sim node in its own process, in the caller's domain, for the duration of the block.

    Args:
        robot: a registered robot's name, or its RobotSpec (a robot registered by user code: the child gets the
            spec itself, so it needs no import of the user's module).
        domain: the Domain or its ``tcp://`` or ``tls://`` URI (a ``memory://`` domain cannot be joined from another
            process; a ``tls://`` one needs the ``$UNIROS_TLS_*`` files, which the child inherits).
        namespace: topic namespace; default ``/<robot>``.
        config: servo settings.
        emulation: run the emulated real arm instead of the nominal sim.
        imperfections: servo-level imperfections with a strength (``open_servo_sim``).
        randomize: imperfections drawn afresh for every episode (``open_servo_sim``).
        clock: ``"wall"`` or ``"sim"`` (the child drives a SimClock and publishes ``/clock``).
        time_scale: with ``clock="sim"``: sim seconds per wall second (None: unbounded).
        publish_markers: publish EE and goal markers.
        transport: the child node's transport choice (``auto``: shm on this machine).
        auth_key: the domain's shared key.
        start_timeout_s: bound on the child's start (spawn, imports, joining the domain).
        stop_timeout_s: how long to wait for an orderly exit before terminate() and kill().

    Yields:
        A ServoSimProcess; its topics are live when the block starts.

    Raises:
        ConfigError: a domain neither tcp nor tls, or bad settings.
        RobotError: the child failed to start (its traceback is in the message) or did not start in time.
    """
    uri = domain.uri if isinstance(domain, Domain) else domain
    name = robot if isinstance(robot, str) else robot.name
    cfg = ServeConfig(
        robot=robot,
        domain=uri,
        namespace=namespace,
        servo=config or ServoSimConfig(),
        emulation=emulation,
        imperfections=imperfections,
        randomize=randomize,
        clock=clock,
        time_scale=time_scale,
        publish_markers=publish_markers,
        transport=transport,
        auth_key=auth_key,
    )
    ctx = multiprocessing.get_context("spawn")
    parent_conn, child_conn = ctx.Pipe()
    # daemon=True: if this process dies, the child must not be left running the arm
    proc = ctx.Process(target=_child_main, args=(cfg, child_conn), name=f"servo_sim {name}", daemon=True)
    proc.start()
    child_conn.close()
    try:
        try:
            kind, info = await _recv(parent_conn, start_timeout_s)
        except TimeoutError:
            raise RobotError(f"the {name} servo sim process did not start within {start_timeout_s} s") from None
        except EOFError:
            raise RobotError(f"the {name} servo sim process exited during start (exit code {proc.exitcode})") from None
        if kind != "ready":
            raise RobotError(f"the {name} servo sim process failed to start:\n{info}")
        yield ServoSimProcess(proc, uri, namespace if namespace is not None else f"/{name}")
    finally:
        await _stop_process(proc, parent_conn, stop_timeout_s)


async def _stop_process(
    proc: multiprocessing.process.BaseProcess, conn: multiprocessing.connection.Connection, timeout_s: float
) -> None:
    with contextlib.suppress(OSError, ValueError):
        conn.send(("stop", None))
    if proc.is_alive():
        loop = asyncio.get_running_loop()
        exited = asyncio.Event()
        loop.add_reader(proc.sentinel, exited.set)  # the sentinel becomes readable when the process ends
        try:
            async with asyncio.timeout(timeout_s):
                await exited.wait()
        except TimeoutError:
            logger.warning("servo sim process %s did not stop within %.1f s; terminating", proc.pid, timeout_s)
        finally:
            loop.remove_reader(proc.sentinel)
    if proc.is_alive():
        proc.terminate()
        proc.join(1.0)
    if proc.is_alive():  # pragma: no cover - a child that ignores SIGTERM
        proc.kill()
        proc.join(1.0)
    proc.join(0)
    if conn.poll(0):  # an error the child reported after it had started
        with contextlib.suppress(EOFError, OSError):
            kind, info = conn.recv()
            if kind == "error":
                logger.error("servo sim process %s failed:\n%s", proc.pid, info)
    with contextlib.suppress(OSError):
        conn.close()
    with contextlib.suppress(ValueError):
        proc.close()
