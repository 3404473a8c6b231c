"""Placements: where an env's arm runs and how the env reaches it on the bus, as a registry open to user code.

An env's ``robot=`` setting names a placement: an exact name (``"sim"``, ``"sim-process"``, ``"emulated-real"``)
or a URI whose scheme is registered (``"tcp://127.0.0.1:7000"``, ``"tls://robot-pc:7000"``,
``"ros1://robot-pc:11311"``). A placement is a factory: given a ``PlacementRequest`` (the robot's spec, the env's
config, its clock) it returns an async context manager that starts, or connects to, the arm and yields an
``ArmLink``, the domain the env's node joins and the transport it uses there. The env then reaches the arm only
through its topics and services, whatever the placement.

Like gymnasium's ``register``, one registry (a ``uniros_async.registry.Registry``) holds every placement behind
``register_placement``; entry points are ``"module:function"`` strings, imported only when a placement is opened,
so neither this module nor ``uniros_async.envs`` imports a sim or an adapter: ``sim``, ``sim-process`` and
``emulated-real`` are registered here by name and built in ``uniros_async.sim.placement``, ``ros1://`` in
``uniros_async.adapters.ros1_bridge``.
A package of your own registers its placements at import::

    import contextlib
    from uniros_async.placements import ArmLink, PlacementRequest, open_placement, register_placement

    @contextlib.asynccontextmanager
    async def open_my_sim(request: PlacementRequest):
        async with open_placement("sim", request) as link:  # the in-process sim, plus whatever you add
            yield link

    register_placement("my-sim", open_my_sim, can_teleport=True, sim_clock=True)

A lookup that misses raises ``ConfigError`` naming the registered placements and the closest one.
"""

from __future__ import annotations

import contextlib
import dataclasses
import re
from collections.abc import AsyncIterator, Callable
from contextlib import AbstractAsyncContextManager
from typing import TYPE_CHECKING, Any, Generic, Protocol, TypeVar

from uniros_async.errors import ConfigError
from uniros_async.registry import Registry, load_entry_point

if TYPE_CHECKING:
    from uniros_async.clock import Clock
    from uniros_async.robots.spec import RobotSpec

__all__ = [
    "ArmLink",
    "PlacementFactory",
    "PlacementRequest",
    "PlacementSpec",
    "open_placement",
    "placement_names",
    "placement_spec",
    "register_placement",
]

_SCHEME = re.compile(r"[a-z][a-z0-9+.-]*")


class PlacedConfig(Protocol):
    """What this module reads of an env's config: its ``robot=`` string. An env passes its whole
    ``uniros_async.envs.config.EnvConfig``; this registry sits below the envs and needs nothing more of it."""

    @property
    def robot(self) -> str: ...


ConfigT = TypeVar("ConfigT", bound=PlacedConfig, covariant=True)


@dataclasses.dataclass(frozen=True, kw_only=True)
class PlacementRequest(Generic[ConfigT]):
    """What a placement factory gets: which arm, for which env.

    A factory annotates the config it reads: ``request: PlacementRequest[EnvConfig]``.

    Attributes:
        robot: the arm's spec (its name is also the topic namespace, ``/<name>``).
        config: the env's config (an ``EnvConfig``); ``config.robot`` is the placement string (with its URI, for
            a scheme).
        clock: the env's clock (a ``SimClock`` with ``clock="sim"``); an in-process sim must run on it.
    """

    robot: RobotSpec
    config: ConfigT
    clock: Clock

    @property
    def uri(self) -> str:
        """The env's ``robot=`` string, e.g. ``"tcp://127.0.0.1:7000"`` or ``"sim"``."""
        return self.config.robot


@dataclasses.dataclass(frozen=True, kw_only=True)
class ArmLink:
    """What an env needs to reach its arm: the domain its node joins and how.

    Attributes:
        domain: an open ``Domain`` or a domain URI (``"tcp://HOST:PORT"``, ``"tls://HOST:PORT"``) where the arm's
            node serves ``/<robot>/joint_states``, ``/<robot>/command`` and the ``hold`` and ``reset`` services.
        transport: the env node's transport choice there (``"auto"``, ``"memory"``, ``"shm"``, ``"tcp"``,
            ``"tls"``).
        process: a process that runs the arm for this env (a ``ServoSimProcess``), or None; the env keeps it as
            ``robot_process`` (tests kill it to see the env fail cleanly).
        info: what the placement adds to the ``info`` of every step and reset (called as they return, on the env
            loop's thread; the ``dxl://`` placement's servo readings), or None: nothing.
    """

    domain: Any
    transport: str = "auto"
    process: Any = None
    info: Callable[[], dict[str, Any]] | None = None


PlacementFactory = Callable[[PlacementRequest[Any]], AbstractAsyncContextManager[ArmLink]]
"""A placement: called with the request, returns an async context manager that yields the ``ArmLink`` while the
arm is reachable and releases everything it started on exit (``contextlib.asynccontextmanager`` makes one)."""

ConfigCheck = Callable[[str, Any], None]
"""A placement's own check of an env config (its URI, and the ``EnvConfig`` for its settings); raises
ConfigError."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class PlacementSpec:
    """One registered placement.

    Attributes:
        name: the registry key: an exact ``robot=`` value (``"sim"``) or a URI scheme with ``://`` (``"tcp://"``).
        entry_point: the factory, or ``"module:function"`` naming it (imported when the placement is opened).
        can_teleport: the arm can be put at its home pose at once through its ``reset`` service (a nominal sim);
            otherwise ``reset()`` drives it home and waits for it to settle, as on a real arm.
        sim_clock: the arm can run on the env's ``SimClock`` (``clock="sim"``): it runs in the env's process.
        stamps_on_env_clock: the arm's joint states are stamped with the env's own clock (an in-process sim),
            so a state's age is read from its stamp; otherwise from when it arrived.
        start_timeout_s: how long the env waits for the placement to open and the arm's first joint state.
        check: the placement's own check of an env config, or ``"module:function"`` naming it, or None.
        description: one line for error messages and docs.
    """

    name: str
    entry_point: str | PlacementFactory
    can_teleport: bool = False
    sim_clock: bool = False
    stamps_on_env_clock: bool = False
    start_timeout_s: float = 60.0
    check: str | ConfigCheck | None = None
    description: str = ""

    @property
    def is_scheme(self) -> bool:
        """True for a URI scheme (``"tcp://"``): every ``robot="tcp://..."`` is this placement."""
        return self.name.endswith("://")

    def factory(self) -> PlacementFactory:
        """The factory, imported on first use when registered by entry point.

        Raises:
            ConfigError: the entry point cannot be imported or is not callable.
        """
        factory = self.entry_point
        if isinstance(factory, str):
            factory = load_entry_point(factory, f"placement {self.name!r}")
        if not callable(factory):
            what = type(factory).__name__
            raise ConfigError(f"placement {self.name!r}: {self.entry_point!r} is {what}, not callable")
        return factory

    def check_config(self, config: PlacedConfig) -> None:
        """Run the placement's own check of ``config`` (its URI, its settings); a no-op without one.

        Raises:
            ConfigError: the placement rejects the config.
        """
        check = self.check
        if check is None:
            return
        if isinstance(check, str):
            check = load_entry_point(check, f"placement {self.name!r} check")
        check(config.robot, config)

    def open(self, request: PlacementRequest[Any]) -> AbstractAsyncContextManager[ArmLink]:
        """Open the placement for ``request``: ``async with spec.open(request) as link:``."""
        return self.factory()(request)


_PLACEMENTS = Registry[PlacementSpec](
    "placement", note="a URI scheme takes the rest of the URI; register_placement adds one"
)


def _key(robot: str) -> str:
    """The registry key of a ``robot=`` value: ``"tcp://"`` for ``"tcp://host:port"``, else the value itself."""
    scheme, sep, _ = robot.partition("://")
    return f"{scheme}://" if sep else robot


def register_placement(
    name: str,
    entry_point: str | PlacementFactory,
    *,
    can_teleport: bool = False,
    sim_clock: bool = False,
    stamps_on_env_clock: bool = False,
    start_timeout_s: float = 60.0,
    check: str | ConfigCheck | None = None,
    description: str = "",
    override: bool = False,
) -> PlacementSpec:
    """Register a placement under ``name`` so that ``robot=name`` (or ``robot="name..."`` for a scheme) uses it.

    Registering the same spec again is a no-op, so a module may register at import however often it is imported.

    Args:
        name: an exact name (``"my-sim"``) or a URI scheme ending in ``://`` (``"ros2://"``).
        entry_point: the factory (see ``PlacementFactory``), or ``"module:function"`` naming it.
        can_teleport: see ``PlacementSpec``.
        sim_clock: see ``PlacementSpec``.
        stamps_on_env_clock: see ``PlacementSpec``.
        start_timeout_s: see ``PlacementSpec``.
        check: see ``PlacementSpec``.
        description: see ``PlacementSpec``.
        override: replace a different placement already registered under ``name``.

    Returns:
        The registered PlacementSpec.

    Raises:
        ConfigError: a malformed name, or ``name`` is taken by another placement and ``override`` is False.
    """
    if not isinstance(name, str) or not name:
        raise ConfigError(f"placement name: expected a non-empty string, got {name!r}")
    if name.endswith("://"):
        if not _SCHEME.fullmatch(name[:-3]):
            raise ConfigError(f"placement scheme {name!r}: expected a URI scheme like 'ros2://' ([a-z][a-z0-9+.-]*)")
    elif "://" in name or not name.strip() == name:
        raise ConfigError(f"placement name {name!r}: expected a plain name ('my-sim') or a scheme ending in '://'")
    if not (isinstance(entry_point, str) or callable(entry_point)):
        raise ConfigError(f"placement {name!r}: expected a factory or 'module:function', got {entry_point!r}")
    if not start_timeout_s > 0:
        raise ConfigError(f"placement {name!r}: start_timeout_s must be > 0, got {start_timeout_s}")
    spec = PlacementSpec(
        name=name,
        entry_point=entry_point,
        can_teleport=can_teleport,
        sim_clock=sim_clock,
        stamps_on_env_clock=stamps_on_env_clock,
        start_timeout_s=start_timeout_s,
        check=check,
        description=description,
    )
    return _PLACEMENTS.register(name, spec, override=override)  # type: ignore[return-value]  # no entry points


def placement_names() -> list[str]:
    """The registered placements, sorted: names and schemes (``"tcp://"``)."""
    return list(_PLACEMENTS.names())


def placement_spec(robot: str) -> PlacementSpec:
    """The placement of an env's ``robot=`` value: the exact name, or the scheme of a URI.

    Args:
        robot: e.g. ``"sim"``, ``"tcp://127.0.0.1:7000"``.

    Raises:
        ConfigError: nothing is registered for it; the message lists the placements and the closest one.
    """
    if not isinstance(robot, str):
        raise ConfigError(f"robot: expected a placement name or URI string, got {type(robot).__name__} {robot!r}")
    key = _key(robot)
    if key not in _PLACEMENTS:
        raise _PLACEMENTS.unknown(key, message=f"robot={robot!r}: no placement {key!r} is registered")
    return _PLACEMENTS.get(key)


def open_placement(robot: str, request: PlacementRequest[Any]) -> AbstractAsyncContextManager[ArmLink]:
    """Open the placement registered for ``robot`` (e.g. ``"sim"``) for ``request``; a placement of your own can
    wrap a built-in one this way.

    Raises:
        ConfigError: ``robot`` names no registered placement.
    """
    return placement_spec(robot).open(request)


# ------------------------------------------------------------------------- built-ins (the sim ones: sim/placement.py)


@contextlib.asynccontextmanager
async def open_tcp(request: PlacementRequest[Any]) -> AsyncIterator[ArmLink]:
    """``robot="tcp://HOST:PORT"``: the domain of an arm served elsewhere (``uniros robot serve``/``bridge``)."""
    yield ArmLink(domain=request.uri, transport="tcp")


@contextlib.asynccontextmanager
async def open_tls(request: PlacementRequest[Any]) -> AsyncIterator[ArmLink]:
    """``robot="tls://HOST:PORT"``: the domain of an arm served elsewhere on tls (``uniros robot serve --tls``); the
    env's node needs a certificate signed by the domain's CA (``$UNIROS_TLS_CERT``, ``KEY``, ``CA``)."""
    yield ArmLink(domain=request.uri, transport="tls")


def _check_host_port(robot: str, scheme: str) -> None:
    host, sep, port = robot.removeprefix(f"{scheme}://").rstrip("/").rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigError(
            f"robot: expected a domain URI {scheme}://HOST:PORT (e.g. {scheme}://127.0.0.1:7000), got {robot!r}"
        )


def check_tcp(robot: str, config: PlacedConfig) -> None:
    """A ``tcp://HOST:PORT`` URI with a port.

    Raises:
        ConfigError: malformed.
    """
    _check_host_port(robot, "tcp")


def check_tls(robot: str, config: PlacedConfig) -> None:
    """A ``tls://HOST:PORT`` URI with a port.

    Raises:
        ConfigError: malformed.
    """
    _check_host_port(robot, "tls")


def _register_builtins() -> None:
    here, sim = __name__, "uniros_async.sim.placement"
    register_placement(
        "sim",
        f"{sim}:open_sim",
        can_teleport=True,
        sim_clock=True,
        stamps_on_env_clock=True,
        start_timeout_s=30.0,
        description="the servo sim in the env's process",
    )
    register_placement(
        "sim-process", f"{sim}:open_sim_process", can_teleport=True, description="the servo sim in its own process"
    )
    register_placement(
        "emulated-real",
        f"{sim}:open_emulated_real",
        sim_clock=True,
        description="the emulated real arm over tcp (in sim time in the env's process with clock='sim')",
    )
    register_placement(
        "tcp://", f"{here}:open_tcp", check=f"{here}:check_tcp", description="the domain of an arm served elsewhere"
    )
    register_placement(
        "tls://",
        f"{here}:open_tls",
        check=f"{here}:check_tls",
        description="the domain of an arm served elsewhere on tls (mutual TLS, encrypted)",
    )
    register_placement(
        "ros1://",
        "uniros_async.adapters.ros1_bridge:open_ros1_placement",
        check="uniros_async.adapters.ros1_bridge:check_ros1_placement",
        description="an arm whose driver is a ROS 1 node, through a bridge in the env's process",
    )
    register_placement(
        "ros2://",
        "uniros_async.adapters.ros2_bridge:open_ros2_placement",
        check="uniros_async.adapters.ros2_bridge:check_ros2_placement",
        description="an arm whose driver is a ROS 2 node, through a bridge in the env's process",
    )
    register_placement(
        "dxl://",
        "uniros_async.hardware.dxl.placement:open_dxl_placement",
        check="uniros_async.hardware.dxl.placement:check_dxl_placement",
        description="an arm of Dynamixel servos on its serial bus, driven from the env's process (no ROS)",
    )


_register_builtins()
