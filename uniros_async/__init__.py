"""uniros_async: a middleware-free asyncio runtime for reinforcement learning on simulated and real robot arms.

The bus (``uniros_async.bus``: domains, nodes, topics, timers, services, parameters) runs over pluggable
transports (``uniros_async.transports``: memory, shm, tcp); robots, environments and training build on it.
Robots, placements (where an arm runs) and tasks are registries your own package adds to at import, without editing
this one: ``register_robot``, ``register_placement``, ``register_task`` and ``register_env_id``. Every error
raised on purpose is a ``UnirosError``, exported here; ``uniros_async.errors`` draws their tree.
"""

from typing import TYPE_CHECKING, Any

from uniros_async.errors import (
    AuthenticationError,
    BagDamagedError,
    BagError,
    BusError,
    CameraError,
    CheckpointError,
    CodecError,
    ConfigError,
    DomainError,
    DxlCrcError,
    DxlError,
    DxlPortError,
    DxlStatusError,
    DxlTimeoutError,
    EvaluationStopped,
    FrameError,
    FrameTooLargeError,
    NameConflictError,
    RenderError,
    RobotError,
    ServiceError,
    SimulationError,
    StepTimeoutError,
    TrainingInterrupted,
    TransportBrokenError,
    TransportClosedError,
    TransportError,
    UnirosError,
    ViewError,
    WorkerError,
)

if TYPE_CHECKING:
    from uniros_async.errors import InvalidActionsError
    from uniros_async.placements import register_placement
    from uniros_async.robots import register_robot
    from uniros_async.runtime import make, make_vec
    from uniros_async.tasks.registry import register_env_id, register_task

__version__ = "0.1.0"

__all__ = [
    "AuthenticationError",
    "BagDamagedError",
    "BagError",
    "BusError",
    "CameraError",
    "CheckpointError",
    "CodecError",
    "ConfigError",
    "DomainError",
    "DxlCrcError",
    "DxlError",
    "DxlPortError",
    "DxlStatusError",
    "DxlTimeoutError",
    "EvaluationStopped",
    "FrameError",
    "FrameTooLargeError",
    "InvalidActionsError",
    "NameConflictError",
    "RenderError",
    "RobotError",
    "ServiceError",
    "SimulationError",
    "StepTimeoutError",
    "TrainingInterrupted",
    "TransportBrokenError",
    "TransportClosedError",
    "TransportError",
    "UnirosError",
    "ViewError",
    "WorkerError",
    "__version__",
    "make",
    "make_vec",
    "register_env_id",
    "register_placement",
    "register_robot",
    "register_task",
]


def _register_ids(_gymnasium: object) -> None:
    from uniros_async.tasks.registry import register_envs

    register_envs()


# The gymnasium ids ("uniros/Rx200Reach-v0", ...) are registered on import, as gymnasium-robotics does, but
# without importing gymnasium here: at once if it is loaded, else right after it is (a bus-only process skips it).
from uniros_async._post_import import when_imported as _when_imported  # noqa: E402

_when_imported("gymnasium", _register_ids)


def __getattr__(name: str) -> Any:
    # The registries and the runtime load only when asked for: a transport-only process or an env worker of a
    # gymnasium env imports none of them (each registry fills with the built-in entries when first imported).
    if name == "InvalidActionsError":  # its base is gymnasium's InvalidAction: made when first asked for
        from uniros_async import errors

        return errors.InvalidActionsError
    if name in ("make", "make_vec"):
        from uniros_async import runtime

        return getattr(runtime, name)
    if name == "register_placement":
        from uniros_async import placements

        return placements.register_placement
    if name == "register_robot":
        from uniros_async import robots

        return robots.register_robot
    if name in ("register_task", "register_env_id"):  # gymnasium is imported for them (the task registry)
        from uniros_async.tasks import registry

        return getattr(registry, name)
    raise AttributeError(f"module 'uniros_async' has no attribute {name!r}")
