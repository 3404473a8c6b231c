"""How each message type is written in a bag: its MCAP schema and its bytes, both ways.

Standard types are ROS 2 messages in CDR (message encoding ``cdr``) with their ``ros2msg`` schemas, so ROS 2 tools
(``ros2 bag``, rosbags, Foxglove) read them as they are; rosbags serialises them (``adapters/ros2/msgs.py``):

==============  ===================================  ============================================================
ours            ROS 2                                 fields ROS 2 has no place for (read back as their default)
==============  ===================================  ============================================================
Header          ``std_msgs/msg/Header``               ``seq``
JointState      ``sensor_msgs/msg/JointState``        ``header.seq``, ``command_stamp_ns``, ``command_age_ns``
Image           ``sensor_msgs/msg/Image``             ``header.seq``
Pose            ``geometry_msgs/msg/PoseStamped``     ``header.seq``
ClockTick       ``rosgraph_msgs/msg/Clock``           none
Text            ``std_msgs/msg/String``               none
Empty           ``std_msgs/msg/Empty``                none
==============  ===================================  ============================================================

The stamps, names, strings and arrays all survive; what ROS 2 has no place for does not, so a recorder that needs
the link-transit echo of a JointState writes every type as our own (``BagWriter(..., ros2=False)``).

Every other type (JointCommand, Marker, Blob, Trigger, Data, and a user's ``@message`` types) is written
self-described, in a ROS 2 envelope that ROS 2 tools can read too: the schema ``uniros_msgs/msg/<Type>`` (ros2msg)
is one field, ``uint8[] msgpack``, and its comment lines describe what those bytes hold: a msgpack map of the
message's fields, each numpy array a map ``{"dtype": "<f8", "shape": [...], "data": <bytes>}``, and a JSON list of
the fields with their kind, dtype and ndim. The message is that envelope in CDR.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import struct
from collections.abc import Callable
from typing import Any

import numpy as np

from uniros_async.bus import codec
from uniros_async.bus import messages as m
from uniros_async.errors import CodecError

__all__ = ["OWN_PACKAGE", "ROS2_TYPES", "Schema", "decode", "encode", "schema_for"]

OWN_PACKAGE = "uniros_msgs/msg/"
_CDR_LE = b"\x00\x01\x00\x00"
ROS2_TYPES = {
    "Header": "std_msgs/msg/Header",
    "JointState": "sensor_msgs/msg/JointState",
    "Image": "sensor_msgs/msg/Image",
    "Pose": "geometry_msgs/msg/PoseStamped",
    "ClockTick": "rosgraph_msgs/msg/Clock",
    "Text": "std_msgs/msg/String",
    "Empty": "std_msgs/msg/Empty",
}
"""Our standard types and the ROS 2 type each is written as."""


@dataclasses.dataclass(frozen=True, slots=True)
class Schema:
    """An MCAP schema: ``name`` (a ROS 2 type; ours ``uniros_msgs/msg/<Type>``), its encoding and text, and the
    message encoding of its messages."""

    name: str
    encoding: str
    data: bytes
    message_encoding: str


def _ros2() -> Any:
    from uniros_async.adapters.ros2 import msgs

    return msgs


@functools.cache
def schema_for(type_name: str, *, standard: bool = True) -> Schema:
    """The schema our ``type_name`` is written with (``standard=False``: our own, for a standard type too).

    Raises:
        CodecError: not a registered message type.
    """
    cls = m.message_type(type_name)
    if standard and type_name in ROS2_TYPES:
        ros = ROS2_TYPES[type_name]
        text, _ = _ros2().typestore().generate_msgdef(ros, ros_version=2)
        return Schema(ros, "ros2msg", text.encode(), "cdr")
    text = (
        f"# uniros_async message {type_name}: msgpack holds a msgpack map of its fields, each numpy array a map\n"
        '# {"dtype": numpy dtype string, "shape": [int, ...], "data": raw bytes, C order}, each nested message a map.\n'
        f"# fields: {json.dumps(_fields(cls))}\n"
        "uint8[] msgpack\n"
    )
    return Schema(OWN_PACKAGE + type_name, "ros2msg", text.encode(), "cdr")


def _fields(cls: type) -> list[dict[str, Any]]:
    out: list[dict[str, Any]] = []
    for spec in cls.__uniros_schema__:  # type: ignore[attr-defined]
        entry: dict[str, Any] = {"name": spec.name, "kind": spec.kind}
        if spec.kind == "array":
            entry.update(dtype=spec.dtype.str, ndim=spec.ndim, optional=spec.optional)
        elif spec.kind == "message":
            entry.update(type=spec.message_cls.__name__, fields=_fields(spec.message_cls))
        out.append(entry)
    return out


def encode(msg: Any, schema: Schema) -> bytes:
    """``msg`` as the bytes of a message of ``schema``.

    Raises:
        CodecError: a field that does not fit (named).
    """
    if schema.name.startswith(OWN_PACKAGE):
        body = codec.encode_plain(_to_plain(msg))
        return _CDR_LE + struct.pack("<I", len(body)) + body
    return bytes(_ros2().serialize(_TO_ROS[type(msg).__name__](msg), schema.name))


def decode(data: bytes | memoryview, schema: Schema, type_name: str | None = None) -> Any:
    """The message in ``data`` of ``schema``; ``type_name`` is our type (None: from the schema's name).

    Raises:
        CodecError: the bytes are not such a message (names the type).
    """
    if schema.message_encoding != "cdr":
        raise CodecError(f"{schema.name}: message encoding {schema.message_encoding!r} is not one uniros reads")
    if schema.name.startswith(OWN_PACKAGE):
        name = type_name or schema.name.removeprefix(OWN_PACKAGE)
        if len(data) < 8 or bytes(data[:4]) != _CDR_LE:
            raise CodecError(f"{schema.name}: {len(data)} bytes are not a little-endian CDR envelope")
        (n,) = struct.unpack_from("<I", data, 4)
        if 8 + n > len(data):
            raise CodecError(f"{schema.name}: envelope of {n} bytes in a message of {len(data)}")
        return _from_plain(m.message_type(name), codec.decode_plain(bytes(data[8 : 8 + n])))
    ours = type_name or _OURS.get(schema.name)
    if ours is None:
        raise CodecError(f"{schema.name}: a ROS 2 type with no uniros message type")
    return _FROM_ROS[ours](_ros2().deserialize(data, schema.name))


# ---------------------------------------------------------------------------------------------- our own types


def _to_plain(msg: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for spec in msg.__uniros_schema__:
        v = getattr(msg, spec.name)
        if v is None:
            out[spec.name] = None
        elif spec.kind == "array":
            a = np.ascontiguousarray(v)
            out[spec.name] = {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}
        elif spec.kind == "message":
            out[spec.name] = _to_plain(v)
        else:
            out[spec.name] = v
    return out


def _from_plain(cls: type, data: Any) -> Any:
    if not isinstance(data, dict):
        raise CodecError(f"{cls.__name__}: expected a map of fields, got {type(data).__name__}")
    kwargs: dict[str, Any] = {}
    for spec in cls.__uniros_schema__:  # type: ignore[attr-defined]
        if spec.name not in data:
            continue
        v = data[spec.name]
        if v is not None and spec.kind == "array":
            try:
                v = np.frombuffer(v["data"], dtype=np.dtype(v["dtype"])).reshape(v["shape"]).copy()
            except (KeyError, TypeError, ValueError) as exc:
                raise CodecError(f"{cls.__name__}.{spec.name}: not an array map: {exc}") from exc
        elif v is not None and spec.kind == "message":
            assert spec.message_cls is not None
            v = _from_plain(spec.message_cls, v)
        kwargs[spec.name] = v
    try:
        return cls(**kwargs)
    except TypeError as exc:
        raise CodecError(f"{cls.__name__}: {exc}") from exc


# ----------------------------------------------------------------------------------------- ROS 2, both ways


def _cls(name: str) -> Any:
    return _ros2().message_class(name)


def _time(stamp_ns: int) -> Any:
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    if not -(2**31) <= sec < 2**31:
        raise CodecError(f"stamp {stamp_ns} ns does not fit builtin_interfaces/Time (int32 seconds)")
    return _cls("builtin_interfaces/msg/Time")(sec=sec, nanosec=nsec)


def _ns(t: Any) -> int:
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


def _header(h: m.Header) -> Any:
    return _cls("std_msgs/msg/Header")(stamp=_time(h.stamp_ns), frame_id=h.frame_id)


def _our_header(h: Any) -> m.Header:
    return m.Header(stamp_ns=_ns(h.stamp), frame_id=h.frame_id)


def _image_to_ros(msg: m.Image) -> Any:
    h, w, c = msg.data.shape
    data = np.ascontiguousarray(msg.data).reshape(-1)
    return _cls("sensor_msgs/msg/Image")(
        header=_header(msg.header), height=h, width=w, encoding=msg.encoding, is_bigendian=0, step=w * c, data=data
    )


def _image_from_ros(r: Any) -> m.Image:
    h, w = int(r.height), int(r.width)
    c = int(r.step) // w if w else 0
    data = np.asarray(r.data, dtype=np.uint8)
    return m.Image(header=_our_header(r.header), encoding=r.encoding, data=data.reshape(h, w, c))


def _pose_to_ros(msg: m.Pose) -> Any:
    p, q = msg.position, msg.orientation
    assert q is not None
    pose = _cls("geometry_msgs/msg/Pose")(
        position=_cls("geometry_msgs/msg/Point")(x=float(p[0]), y=float(p[1]), z=float(p[2])),
        orientation=_cls("geometry_msgs/msg/Quaternion")(x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0])),
    )
    return _cls("geometry_msgs/msg/PoseStamped")(header=_header(msg.header), pose=pose)


def _pose_from_ros(r: Any) -> m.Pose:
    p, q = r.pose.position, r.pose.orientation
    return m.Pose(
        header=_our_header(r.header), position=np.array([p.x, p.y, p.z]), orientation=np.array([q.w, q.x, q.y, q.z])
    )


_TO_ROS: dict[str, Callable[[Any], Any]] = {
    "Header": _header,
    "JointState": lambda s: _cls("sensor_msgs/msg/JointState")(
        header=_header(s.header),
        name=list(s.name),
        position=np.ascontiguousarray(s.position),
        velocity=np.ascontiguousarray(s.velocity),
        effort=np.ascontiguousarray(s.effort),
    ),
    "Image": _image_to_ros,
    "Pose": _pose_to_ros,
    "ClockTick": lambda t: _cls("rosgraph_msgs/msg/Clock")(clock=_time(t.sim_time_ns)),
    "Text": lambda t: _cls("std_msgs/msg/String")(data=t.data),
    "Empty": lambda _: _cls("std_msgs/msg/Empty")(structure_needs_at_least_one_member=0),
}

_FROM_ROS: dict[str, Callable[[Any], Any]] = {
    "Header": _our_header,
    "JointState": lambda r: m.JointState(
        header=_our_header(r.header),
        name=tuple(r.name),
        position=np.asarray(r.position, dtype=np.float64),
        velocity=np.asarray(r.velocity, dtype=np.float64),
        effort=np.asarray(r.effort, dtype=np.float64),
    ),
    "Image": _image_from_ros,
    "Pose": _pose_from_ros,
    "ClockTick": lambda r: m.ClockTick(sim_time_ns=_ns(r.clock)),
    "Text": lambda r: m.Text(data=r.data),
    "Empty": lambda _: m.Empty(),
}

_OURS = {ros: ours for ours, ros in ROS2_TYPES.items()}
