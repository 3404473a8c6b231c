"""Every error uniros_async raises on purpose.

The tree (as httpx/_exceptions.py draws its own)::

    UnirosError
    ├── ConfigError (also ValueError)        a config or argument was wrong; nothing was started
    ├── CodecError (also ValueError)         a frame could not be encoded or decoded; names the field
    ├── TransportError
    │   ├── TransportClosedError             our own code closed this end (trio ClosedResourceError)
    │   ├── TransportBrokenError             the peer or the medium failed; __cause__ holds the OSError
    │   └── FrameTooLargeError (also ValueError)  a frame over the transport's max_frame_bytes
    ├── AuthenticationError                  a peer failed the shared-key handshake
    ├── BusError
    │   ├── DomainError                      the domain registry is unreachable or refused a request
    │   ├── NameConflictError                a node or service name is taken in the domain
    │   └── ServiceError                     a service call failed on the server side; .remote_traceback
    ├── BagError                             a bag cannot be written or read as asked; names the file
    │   └── BagDamagedError                  a bag is truncated or corrupt at .offset; all before it was read
    ├── CameraError                          a camera source cannot be opened or read; names it
    ├── FrameError (also ValueError)         a camera frame's size or encoding differs from its topic's
    ├── SimulationError                      MuJoCo diverged (dm_control PhysicsError)
    ├── RenderError                          no GL backend could render here; names what was tried
    ├── ViewError                            the live view cannot start or show what it was given; names why
    ├── RobotError                           a robot stopped publishing or refused a command
    │   └── DxlError                         a Dynamixel bus transaction failed; .servo_id when one servo did
    │       ├── DxlCrcError                  a packet's CRC did not match (counted and retried within the tick)
    │       ├── DxlStatusError               a servo answered with an error byte; .error
    │       ├── DxlTimeoutError (also TimeoutError)  a servo did not answer within the packet's timeout
    │       └── DxlPortError                 the serial port could not be opened or failed; __cause__ holds the OSError
    ├── WorkerError                          an env worker failed; .index, .remote_traceback
    │   └── StepTimeoutError (also TimeoutError)  a worker did not answer a request in time; names it, op, timeout
    ├── InvalidActionsError (also gymnasium's InvalidAction, ValueError)  not one action per sub-env
    ├── CheckpointError                      a checkpoint is missing, incomplete, or does not fit its env
    ├── TrainingInterrupted                  a run stopped (Ctrl-C, SIGTERM) early; .checkpoint, the newest intact one
    └── EvaluationStopped                    an evaluation ended early by its stop event

``InvalidActionsError`` is built on first use (``uniros_async.errors.InvalidActionsError`` imports gymnasium for its
base), so importing this module never imports gymnasium.

Timeouts are asyncio's own ``TimeoutError`` (what ``asyncio.timeout`` raises), so callers catch one type.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from pathlib import Path

    import gymnasium

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
]


class UnirosError(Exception):
    """Base of every error uniros_async raises on purpose."""


class ConfigError(UnirosError, ValueError):
    """A config value or argument was wrong; the message names it and what was expected."""


class CodecError(UnirosError, ValueError):
    """A message could not be encoded or a frame could not be decoded; the message names the field."""


class TransportError(UnirosError):
    """Base of transport failures."""


class TransportClosedError(TransportError):
    """Our own code closed this end of the transport."""


class TransportBrokenError(TransportError):
    """The peer or the medium failed; ``__cause__`` holds the underlying error when there is one."""


class FrameTooLargeError(TransportError, ValueError):
    """A frame was larger than the transport's ``max_frame_bytes``."""


class AuthenticationError(UnirosError):
    """A peer did not prove knowledge of the shared key."""


class BusError(UnirosError):
    """Base of bus failures (domains, names, services)."""


class DomainError(BusError):
    """The domain registry is unreachable or refused a request."""


class NameConflictError(BusError):
    """A node or service name is already taken in the domain."""


class ServiceError(BusError):
    """A service handler raised; the server's traceback text is in ``remote_traceback``."""

    def __init__(self, message: str, *, remote_traceback: str = "") -> None:
        super().__init__(message)
        self.remote_traceback = remote_traceback


class BagError(UnirosError):
    """A bag cannot be written or read as asked (names the file and what was wrong)."""


class BagDamagedError(BagError):
    """A bag is truncated or corrupt at byte ``offset``: everything before it was read."""

    def __init__(self, message: str, *, path: str, offset: int) -> None:
        super().__init__(message)
        self.path = path
        self.offset = offset


class CameraError(UnirosError):
    """A camera source that cannot be opened or read (the message names it)."""


class FrameError(UnirosError, ValueError):
    """A frame whose size or encoding differs from its topic's (the message names both); nothing was published."""


class SimulationError(UnirosError):
    """The physics simulation diverged (NaN/inf state or MuJoCo warnings of instability)."""


class RenderError(UnirosError):
    """No GL backend could render here (the message lists what was tried and what to install)."""


class ViewError(UnirosError):
    """The view cannot start or show what it was given (the message names what and why)."""


class RobotError(UnirosError):
    """A robot stopped publishing, or refused a command."""


class DxlError(RobotError):
    """A Dynamixel bus transaction failed; ``servo_id`` names the servo when one did (``None`` otherwise)."""

    def __init__(self, message: str, *, servo_id: int | None = None) -> None:
        super().__init__(message)
        self.servo_id = servo_id


class DxlCrcError(DxlError):
    """A Dynamixel packet's CRC did not match its bytes."""


class DxlStatusError(DxlError):
    """A servo answered with a non-zero error byte; ``error`` holds it."""

    def __init__(self, message: str, *, servo_id: int | None = None, error: int = 0) -> None:
        super().__init__(message, servo_id=servo_id)
        self.error = error


class DxlTimeoutError(DxlError, TimeoutError):
    """A servo did not answer within its packet's timeout (derived from the baud rate and the packet length)."""


class DxlPortError(DxlError):
    """The serial port of a Dynamixel bus could not be opened, or failed; ``__cause__`` holds the OSError."""


class WorkerError(UnirosError):
    """An environment worker process failed.

    Attributes:
        index: the sub-environment index of the worker.
        remote_traceback: the worker's traceback text.
    """

    def __init__(self, index: int, message: str, *, remote_traceback: str = "") -> None:
        super().__init__(f"worker {index}: {message}")
        self.index = index
        self.remote_traceback = remote_traceback


class StepTimeoutError(WorkerError, TimeoutError):
    """An env worker did not answer a request (a step, a reset, ...) within its timeout; the message names the
    worker's index, the operation and the timeout. A TimeoutError too, so ``except TimeoutError`` catches it."""


class CheckpointError(UnirosError):
    """A checkpoint is missing, incomplete, or does not fit the env it is used with."""


class TrainingInterrupted(UnirosError):
    """The run was stopped (Ctrl-C, SIGTERM) before ``total_steps``; ``checkpoint`` is the newest intact one."""

    def __init__(self, message: str, checkpoint: Path | None) -> None:
        super().__init__(message)
        self.checkpoint = checkpoint


class EvaluationStopped(UnirosError):
    """An evaluation ended early by its ``stop`` event (``evaluate_vec_policy``)."""


if TYPE_CHECKING:

    class InvalidActionsError(gymnasium.error.InvalidAction, UnirosError, ValueError):
        """Actions that are not one per sub-env (a ValueError too, as gymnasium's vector envs raise)."""


@functools.cache
def _invalid_actions_error() -> type[Exception]:
    from gymnasium.error import InvalidAction

    cls = type(
        "InvalidActionsError",
        (InvalidAction, UnirosError, ValueError),
        {
            "__doc__": "Actions that are not one per sub-env (a ValueError too, as gymnasium's vector envs raise).",
            "__module__": __name__,
        },
    )
    globals()["InvalidActionsError"] = cls  # later lookups find the class itself
    return cls


def __getattr__(name: str) -> Any:
    # InvalidActionsError derives from gymnasium's InvalidAction: it is made when first asked for, so that a
    # process that never steps a vector env (a transport, a sim server) does not import gymnasium
    if name == "InvalidActionsError":
        return _invalid_actions_error()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
