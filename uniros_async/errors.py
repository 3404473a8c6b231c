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
    ├── SimulationError                      MuJoCo diverged (dm_control PhysicsError)
    ├── RobotError                           a robot stopped publishing or refused a command
    │   └── DxlError                         a Dynamixel bus transaction failed; .servo_id when one servo did
    │       ├── DxlCrcError                  a packet's CRC did not match (counted and retried within the tick)
    │       ├── DxlStatusError               a servo answered with an error byte; .error
    │       ├── DxlTimeoutError (also TimeoutError)  a servo did not answer within the packet's timeout
    │       └── DxlPortError                 the serial port could not be opened or failed; __cause__ holds the OSError
    └── WorkerError                          an env worker failed; .index, .remote_traceback
        └── StepTimeoutError (also TimeoutError)  a worker did not answer a request in time; names it, op, timeout

Timeouts are asyncio's own ``TimeoutError`` (what ``asyncio.timeout`` raises), so callers catch one type.
"""

from __future__ import annotations

__all__ = [
    "AuthenticationError",
    "BusError",
    "CodecError",
    "ConfigError",
    "DomainError",
    "DxlCrcError",
    "DxlError",
    "DxlPortError",
    "DxlStatusError",
    "DxlTimeoutError",
    "FrameTooLargeError",
    "NameConflictError",
    "RobotError",
    "ServiceError",
    "SimulationError",
    "StepTimeoutError",
    "TransportBrokenError",
    "TransportClosedError",
    "TransportError",
    "UnirosError",
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


class SimulationError(UnirosError):
    """The physics simulation diverged (NaN/inf state or MuJoCo warnings of instability)."""


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
