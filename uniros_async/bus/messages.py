"""Message types: frozen dataclasses in the code, msgpack on the wire (only codec.py knows msgpack).

Every message class is declared with ``@message``, which registers it by name for the codec and compiles a schema
from its fields: numpy array fields carry ``array_field(dtype, ndim)`` metadata, nested messages are fields whose
type is another message class, and everything else is plain msgpack data (int, float, str, bool, bytes, None,
tuples/lists and dicts of those). Stamps are integer nanoseconds of the publishing domain's clock. A field added to
a message goes last, with a default: frames of publishers that do not know it yet decode with that default.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

from uniros_async.errors import CodecError

__all__ = [
    "Blob",
    "ClockTick",
    "Data",
    "Empty",
    "FieldSpec",
    "Header",
    "Image",
    "JointCommand",
    "JointState",
    "Marker",
    "Pose",
    "Text",
    "Trigger",
    "array_field",
    "from_dict",
    "to_dict",
    "message",
    "message_type",
    "registered_types",
]

M = TypeVar("M")

_REGISTRY: dict[str, type] = {}


@dataclass(frozen=True, slots=True)
class FieldSpec:
    """How one field is checked and carried: kind is "array", "message" or "data"."""

    name: str
    kind: str
    dtype: np.dtype[Any] | None = None
    ndim: int | None = None
    message_cls: type | None = None
    optional: bool = False


def array_field(dtype: Any, ndim: int, *, optional: bool = False, default: Any = dataclasses.MISSING) -> Any:
    """Declare an ndarray field of ``dtype`` and ``ndim`` (checked on construction and on decode)."""
    meta = {"uniros_array": (np.dtype(dtype), ndim, optional)}
    if default is dataclasses.MISSING and optional:
        default = None
    if default is dataclasses.MISSING:
        return field(metadata=meta)
    return field(default=default, metadata=meta)


@typing.dataclass_transform(
    kw_only_default=True, frozen_default=True, field_specifiers=(dataclasses.field, array_field)
)
def message(cls: type[M]) -> type[M]:
    """Make ``cls`` a frozen, slotted, keyword-only message dataclass and register it for the codec.

    Array fields are converted with ``np.asarray`` to the declared dtype (a list of floats is fine) and checked
    for ndim; a wrong one raises CodecError naming the field.
    """
    user_post_init = cls.__dict__.get("__post_init__")

    def __post_init__(self: Any) -> None:
        for spec in self.__uniros_arrays__:
            value = getattr(self, spec.name)
            if value is None:
                if not spec.optional:
                    raise CodecError(f"{type(self).__name__}.{spec.name}: required array is None")
                continue
            if not isinstance(value, np.ndarray) or value.dtype != spec.dtype:
                try:
                    value = np.asarray(value, dtype=spec.dtype)
                except (TypeError, ValueError) as exc:
                    raise CodecError(
                        f"{type(self).__name__}.{spec.name}: expected {spec.dtype} array, got {value!r:.80}"
                    ) from exc
                object.__setattr__(self, spec.name, value)
            if value.ndim != spec.ndim:
                raise CodecError(
                    f"{type(self).__name__}.{spec.name}: expected ndim {spec.ndim}, got shape {value.shape}"
                )
        if user_post_init is not None:
            user_post_init(self)

    cls.__post_init__ = __post_init__  # type: ignore[attr-defined]
    new_cls = dataclass(frozen=True, slots=True, kw_only=True, eq=False)(cls)
    hints = typing.get_type_hints(new_cls)
    schema = []
    for f in dataclasses.fields(new_cls):  # type: ignore[arg-type]
        if "uniros_array" in f.metadata:
            dtype, ndim, optional = f.metadata["uniros_array"]
            schema.append(FieldSpec(f.name, "array", dtype=dtype, ndim=ndim, optional=optional))
            continue
        hint = hints[f.name]
        target, optional = _unwrap_optional(hint)
        if isinstance(target, type) and target.__name__ in _REGISTRY and _REGISTRY[target.__name__] is target:
            schema.append(FieldSpec(f.name, "message", message_cls=target, optional=optional))
        else:
            schema.append(FieldSpec(f.name, "data"))
    new_cls.__uniros_schema__ = tuple(schema)  # type: ignore[attr-defined]
    # fields after the last one without a default may be missing on the wire (a frame of an older publisher)
    required = [
        i
        for i, f in enumerate(dataclasses.fields(new_cls))  # type: ignore[arg-type]
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
    ]
    new_cls.__uniros_required__ = required[-1] + 1 if required else 0  # type: ignore[attr-defined]
    new_cls.__uniros_arrays__ = tuple(s for s in schema if s.kind == "array")  # type: ignore[attr-defined]
    name = new_cls.__name__
    if name in _REGISTRY:
        raise CodecError(f"message type {name!r} is already registered")
    _REGISTRY[name] = new_cls
    return new_cls


def _unwrap_optional(hint: Any) -> tuple[Any, bool]:
    args = typing.get_args(hint)
    if args and type(None) in args and len(args) == 2:
        return next(a for a in args if a is not type(None)), True
    return hint, False


def message_type(name: str) -> type:
    """The registered message class called ``name``.

    Raises:
        CodecError: no such type (the registered names are listed).
    """
    try:
        return _REGISTRY[name]
    except KeyError:
        raise CodecError(f"unknown message type {name!r}; registered: {sorted(_REGISTRY)}") from None


def registered_types() -> dict[str, type]:
    """A copy of the name -> class table."""
    return dict(_REGISTRY)


# ------------------------------------------------------------------------------------------------- the messages


@message
class Header:
    """Stamp (ns of the publisher's clock), sequence number, and the frame the data is expressed in."""

    stamp_ns: int = 0
    seq: int = 0
    frame_id: str = ""


@message
class JointState:
    """Positions (rad or m), velocities and efforts of named joints, as sensor_msgs/JointState.

    The last two fields are the arm's echo of the link's round trip (``uniros_async.envs.transit``): the env can
    then tell a delay on the link from an offset between the arm's clock and its own. A publisher that does not echo
    leaves both None (and frames of an older publisher, without them, decode with None: trailing fields with a
    default may be missing on the wire).
    """

    header: Header
    name: tuple[str, ...]
    position: np.ndarray = array_field(np.float64, 1)
    velocity: np.ndarray = array_field(np.float64, 1)
    effort: np.ndarray = array_field(np.float64, 1)
    command_stamp_ns: int | None = None
    """The ``header.stamp_ns`` of the newest command the arm had received when it stamped this state, verbatim (the
    commanding node's clock); None when it has received none, or does not echo."""
    command_age_ns: int | None = None
    """How long before this state's stamp that command arrived, on the arm's monotonic clock; -1 when the arm echoes
    but has received no command yet; None when it does not echo."""

    def __post_init__(self) -> None:
        if not isinstance(self.name, tuple):
            object.__setattr__(self, "name", tuple(self.name))
        n = len(self.name)
        for f in ("position", "velocity", "effort"):
            if getattr(self, f).shape != (n,):
                raise CodecError(f"JointState.{f}: expected shape ({n},) for {n} names, got {getattr(self, f).shape}")


@message
class JointCommand:
    """Target positions of the arm joints (in the robot's joint order), reached over ``duration_s``
    (0: as fast as the servo profile allows); optional target velocities for velocity control."""

    header: Header
    position: np.ndarray = array_field(np.float64, 1)
    velocity: np.ndarray | None = array_field(np.float64, 1, optional=True, default=None)
    duration_s: float = 0.0

    def __post_init__(self) -> None:
        if self.velocity is not None and self.velocity.shape != self.position.shape:
            raise CodecError(
                f"JointCommand.velocity: expected shape {self.position.shape} like position, got {self.velocity.shape}"
            )


@message
class Pose:
    """Position (m) and orientation (unit quaternion w, x, y, z) in ``header.frame_id``."""

    header: Header
    position: np.ndarray = array_field(np.float64, 1)
    orientation: np.ndarray = array_field(np.float64, 1, optional=True, default=None)  # None: identity

    def __post_init__(self) -> None:
        if self.orientation is None:
            object.__setattr__(self, "orientation", np.array([1.0, 0.0, 0.0, 0.0]))
        if self.position.shape != (3,) or self.orientation.shape != (4,):
            raise CodecError(
                f"Pose: expected position (3,) and orientation (4,), got {self.position.shape} and "
                f"{self.orientation.shape}"
            )


MARKER_KINDS = ("sphere", "cube", "arrow", "cylinder", "line_strip", "points", "text")


@message
class Marker:
    """A shape to draw (goal, EE, workspace), as visualization_msgs/Marker.

    ``header.frame_id`` is the frame of ``position`` and ``points`` (m); ``color`` is rgba in [0, 1]. ``points``
    (N, 3) are the vertices of a ``line_strip`` or the dots of ``points``; a ``text`` marker shows ``text`` at
    ``position``. ``lifetime_s`` > 0: a viewer removes the marker that long after its stamp (0: until replaced).
    """

    header: Header
    ns: str = ""
    id: int = 0
    kind: str = "sphere"
    action: str = "add"
    # optional on the wire, filled with defaults in __post_init__ (a marker needs only its position)
    position: np.ndarray = array_field(np.float64, 1, optional=True, default=None)
    scale: np.ndarray = array_field(np.float64, 1, optional=True, default=None)
    color: np.ndarray = array_field(np.float64, 1, optional=True, default=None)
    points: np.ndarray | None = array_field(np.float64, 2, optional=True, default=None)
    text: str = ""
    lifetime_s: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in MARKER_KINDS:
            raise CodecError(f"Marker.kind: expected one of {MARKER_KINDS}, got {self.kind!r}")
        if self.action not in ("add", "delete"):
            raise CodecError(f"Marker.action: expected 'add' or 'delete', got {self.action!r}")
        for name, default in (("position", (0.0, 0.0, 0.0)), ("scale", (0.02, 0.02, 0.02)), ("color", (1, 0, 0, 1))):
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.array(default, dtype=np.float64))
        if self.position.shape != (3,) or self.scale.shape != (3,) or self.color.shape != (4,):
            raise CodecError("Marker: expected position (3,), scale (3,), color (4,) rgba")
        if self.points is not None and self.points.shape[1:] != (3,):
            raise CodecError(f"Marker.points: expected shape (N, 3), got {self.points.shape}")
        if not self.lifetime_s >= 0.0:
            raise CodecError(f"Marker.lifetime_s: expected >= 0 s, got {self.lifetime_s!r}")


@message
class Image:
    """An image, ``data`` of shape (height, width, channels), uint8; ``encoding`` as in sensor_msgs ("rgb8")."""

    header: Header
    encoding: str = "rgb8"
    data: np.ndarray = array_field(np.uint8, 3)


@message
class Blob:
    """Opaque bytes as a uint8 array (benchmarks, files)."""

    header: Header
    data: np.ndarray = array_field(np.uint8, 1)


@message
class ClockTick:
    """The simulation's time, published by a SimClock source on ``/clock``."""

    sim_time_ns: int


@message
class Empty:
    """No content (service requests that need none)."""


@message
class Trigger:
    """A service response: did it work, and a message for a person."""

    success: bool
    message: str = ""


@message
class Text:
    """A string."""

    data: str


@message
class Data:
    """Any msgpack-able value: dicts, lists, numbers, strings (parameters, generic service payloads)."""

    value: Any = None


def to_dict(msg: Any) -> dict[str, Any]:
    """A message as plain data (arrays as lists), for printing and YAML."""
    out: dict[str, Any] = {}
    for spec in msg.__uniros_schema__:
        v = getattr(msg, spec.name)
        if v is None:
            out[spec.name] = None
        elif spec.kind == "array":
            out[spec.name] = v.tolist()
        elif spec.kind == "message":
            out[spec.name] = to_dict(v)
        else:
            out[spec.name] = list(v) if isinstance(v, tuple) else v
    return out


def from_dict(cls: type[M], data: Any) -> M:
    """Build message ``cls`` from plain data (the inverse of to_dict; nested messages may be omitted).

    Raises:
        CodecError: not a mapping, unknown or missing fields (the valid ones are listed), or bad values.
    """
    if not isinstance(data, dict):
        raise CodecError(f"{cls.__name__}: expected a mapping of fields, got {type(data).__name__}")
    schema = {s.name: s for s in cls.__uniros_schema__}  # type: ignore[attr-defined]
    unknown = sorted(set(data) - set(schema))
    if unknown:
        raise CodecError(f"{cls.__name__}: unknown field(s) {unknown}; fields are {sorted(schema)}")
    kwargs: dict[str, Any] = {}
    for name, spec in schema.items():
        if name in data:
            v = data[name]
            if spec.kind == "message" and v is not None:
                assert spec.message_cls is not None
                v = from_dict(spec.message_cls, v)
            kwargs[name] = v
        elif spec.kind == "message" and not spec.optional:
            assert spec.message_cls is not None
            kwargs[name] = spec.message_cls()
    try:
        return cls(**kwargs)
    except TypeError as exc:
        raise CodecError(f"{cls.__name__}: {exc}") from exc
