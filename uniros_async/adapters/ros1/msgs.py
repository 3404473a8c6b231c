"""ROS 1 messages the arm drivers speak, as dataclasses with ROS 1's own wire format (what genpy writes).

Each class carries what a TCPROS connection header names: ``_type`` ("sensor_msgs/JointState"), ``_md5sum`` and
``_full_text`` (the message definition, copied from the genpy classes of ROS Noetic / Debian, or from the
Interbotix repository for ``JointGroupCommand``). ``serialize()`` gives the message body (without TCPROS's 4-byte
length prefix) and ``deserialize(body)`` reads one back; a truncated or corrupt body raises CodecError naming the
type and the field.

Wire format: little-endian; a string is uint32 length + bytes (UTF-8); a variable-length array is uint32 count +
elements; ``time`` is uint32 secs + uint32 nsecs and ``duration`` int32 secs + int32 nsecs. Stamps are integer
nanoseconds here (``stamp_ns``); float arrays deserialize as read-only numpy views of the body (no copy).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Self

import numpy as np

from uniros_async.errors import CodecError

__all__ = [
    "MESSAGE_TYPES",
    "CompressedImage",
    "Float64MultiArray",
    "Image",
    "JointGroupCommand",
    "JointState",
    "JointTrajectory",
    "JointTrajectoryPoint",
    "Ros1Message",
    "RosHeader",
]

_U32 = struct.Struct("<I")
_HEADER = struct.Struct("<III")  # seq, stamp.secs, stamp.nsecs
_DURATION = struct.Struct("<ii")
_DIM = struct.Struct("<II")  # MultiArrayDimension size, stride
_NS = 1_000_000_000
_F64 = np.dtype("<f8")
_F32 = np.dtype("<f4")


class _Reader:
    """Reads fields from one message body; every shortfall is a CodecError naming the type, field and offset."""

    __slots__ = ("buf", "pos", "type_name")

    def __init__(self, data: bytes | bytearray | memoryview, type_name: str) -> None:
        # A memoryview may sit on a buffer that is reused; copy it once so the array views stay valid.
        self.buf = data.tobytes() if isinstance(data, memoryview) else bytes(data)
        self.pos = 0
        self.type_name = type_name

    def _take(self, n: int, what: str) -> int:
        start = self.pos
        if n > len(self.buf) - start:
            raise CodecError(
                f"{self.type_name}: truncated body reading {what} at byte {start}: "
                f"need {n} bytes, {len(self.buf) - start} left of {len(self.buf)}"
            )
        self.pos = start + n
        return start

    def u32(self, what: str) -> int:
        return int(_U32.unpack_from(self.buf, self._take(4, what))[0])

    def unpack(self, st: struct.Struct, what: str) -> tuple[Any, ...]:
        return st.unpack_from(self.buf, self._take(st.size, what))

    def string(self, what: str, index: int | None = None) -> str:
        # The field's name is formatted only on an error: a JointState has a dozen strings, and building their
        # names for every message cost more than reading them.
        buf, pos = self.buf, self.pos
        if len(buf) - pos >= 4:
            (n,) = _U32.unpack_from(buf, pos)
            end = pos + 4 + n
            if end <= len(buf):
                self.pos = end
                try:
                    return buf[pos + 4 : end].decode()
                except UnicodeDecodeError as exc:
                    name = what if index is None else f"{what}[{index}]"
                    raise CodecError(f"{self.type_name}: {name} at byte {pos + 4} is not UTF-8 ({exc.reason})") from exc
        name = what if index is None else f"{what}[{index}]"
        n = self.u32(f"{name} length")
        self._take(n, name)  # raises: this is where it runs short
        raise AssertionError("unreachable")

    def count(self, what: str, min_item_bytes: int) -> int:
        n = self.u32(f"{what} length")
        # A corrupt count must fail here, not allocate or loop over millions of items first.
        if n * min_item_bytes > len(self.buf) - self.pos:
            raise CodecError(
                f"{self.type_name}: {what} announces {n} items at byte {self.pos - 4} "
                f"but only {len(self.buf) - self.pos} bytes are left"
            )
        return n

    def strings(self, what: str) -> list[str]:
        return [self.string(what, i) for i in range(self.count(what, 4))]

    def array(self, dtype: np.dtype[Any], what: str) -> np.ndarray:
        n = self.count(what, dtype.itemsize)
        start = self._take(n * dtype.itemsize, what)
        return np.frombuffer(self.buf, dtype=dtype, count=n, offset=start)

    def done(self) -> None:
        if self.pos != len(self.buf):
            raise CodecError(
                f"{self.type_name}: {len(self.buf) - self.pos} unexpected bytes after the message "
                f"(it ends at byte {self.pos} of {len(self.buf)})"
            )


def _string(out: list[bytes], value: str, what: str) -> None:
    if not isinstance(value, str):
        raise CodecError(f"{what}: expected str, got {type(value).__name__}")
    b = value.encode()
    out.append(_U32.pack(len(b)))
    out.append(b)


def _strings(out: list[bytes], values: Sequence[str], what: str) -> None:
    if isinstance(values, str):
        raise CodecError(f"{what}: expected a sequence of str, got a str")
    out.append(_U32.pack(len(values)))
    for i, v in enumerate(values):
        _string(out, v, f"{what}[{i}]")


def _array(out: list[bytes], values: Any, dtype: np.dtype[Any], what: str) -> None:
    try:
        with np.errstate(over="raise"):  # 1e39 -> float32 would be inf: refuse, do not command a robot with it
            a = np.ascontiguousarray(values, dtype=dtype)
    except (TypeError, ValueError, FloatingPointError) as exc:
        raise CodecError(f"{what}: expected a 1-D array of {dtype.name}: {exc}") from exc
    if a.ndim != 1:
        raise CodecError(f"{what}: expected a 1-D array, got shape {a.shape}")
    out.append(_U32.pack(a.shape[0]))
    out.append(a.tobytes())


def _pack(out: list[bytes], st: struct.Struct, what: str, *values: int) -> None:
    try:
        out.append(st.pack(*values))
    except struct.error as exc:
        raise CodecError(f"{what}={values}: out of range for the ROS 1 wire type ({exc})") from exc


class Ros1Message:
    """Base of the ROS 1 message classes: subclasses define ``_encode`` / ``_decode`` for their fields."""

    __slots__ = ()
    _type: ClassVar[str]
    _md5sum: ClassVar[str]
    _full_text: ClassVar[str]

    def _encode(self, out: list[bytes]) -> None:
        raise NotImplementedError

    @classmethod
    def _decode(cls, r: _Reader) -> Self:
        raise NotImplementedError

    def serialize(self) -> bytes:
        """The message body in ROS 1 wire format (TCPROS adds the 4-byte length itself).

        Raises:
            CodecError: a field has the wrong type or a value out of its wire type's range (named).
        """
        out: list[bytes] = []
        try:
            self._encode(out)
        except CodecError as exc:
            raise CodecError(f"{self._type}: {exc}") from exc
        return b"".join(out)

    @classmethod
    def deserialize(cls, data: bytes | bytearray | memoryview) -> Self:
        """Read one message body (without the TCPROS length prefix).

        Raises:
            CodecError: the body is truncated, too long or corrupt; the message names the type, field and offset.
        """
        return cls._checked(data)

    @classmethod
    def _checked(cls, data: bytes | bytearray | memoryview) -> Self:
        """Every field read through ``_Reader``, which names the field and offset of any fault."""
        r = _Reader(data, cls._type)
        msg = cls._decode(r)
        r.done()
        return msg


_HEADER_TEXT = (
    "# Standard metadata for higher-level stamped data types.\n"
    "# This is generally used to communicate timestamped data \n"
    "# in a particular coordinate frame.\n"
    "# \n"
    "# sequence ID: consecutively increasing ID \n"
    "uint32 seq\n"
    "#Two-integer timestamp that is expressed as:\n"
    "# * stamp.sec: seconds (stamp_secs) since epoch (in Python the variable is called 'secs')\n"
    "# * stamp.nsec: nanoseconds since stamp_secs (in Python the variable is called 'nsecs')\n"
    "# time-handling sugar is provided by the client library\n"
    "time stamp\n"
    "#Frame this data is associated with\n"
    "string frame_id\n"
)
_SEPARATOR = "\n" + "=" * 80 + "\n"


@dataclass(frozen=True, slots=True)
class RosHeader(Ros1Message):
    """std_msgs/Header. ``stamp_ns`` is ROS time (wall clock since the epoch, or /clock) in nanoseconds."""

    _type: ClassVar[str] = "std_msgs/Header"
    _md5sum: ClassVar[str] = "2176decaecbce78abc3b96ef049fabed"
    _full_text: ClassVar[str] = _HEADER_TEXT

    seq: int = 0
    stamp_ns: int = 0
    frame_id: str = ""

    def _encode(self, out: list[bytes]) -> None:
        secs, nsecs = divmod(self.stamp_ns, _NS)
        _pack(out, _HEADER, "header.seq/stamp", self.seq, secs, nsecs)
        _string(out, self.frame_id, "header.frame_id")

    @classmethod
    def _decode(cls, r: _Reader) -> Self:
        seq, secs, nsecs = r.unpack(_HEADER, "header.seq/stamp")
        return cls(seq=seq, stamp_ns=secs * _NS + nsecs, frame_id=r.string("header.frame_id"))


@dataclass(frozen=True, slots=True, eq=False)  # eq=False: == on ndarray fields raises
class JointState(Ros1Message):
    """sensor_msgs/JointState: positions (rad or m), velocities and efforts of named joints; arrays may be empty."""

    _type: ClassVar[str] = "sensor_msgs/JointState"
    _md5sum: ClassVar[str] = "3066dcd76a6cfaef579bd0f34173e9fd"
    _full_text: ClassVar[str] = (
        "# This is a message that holds data to describe the state of a set of torque controlled joints. \n"
        "#\n"
        "# The state of each joint (revolute or prismatic) is defined by:\n"
        "#  * the position of the joint (rad or m),\n"
        "#  * the velocity of the joint (rad/s or m/s) and \n"
        "#  * the effort that is applied in the joint (Nm or N).\n"
        "#\n"
        "# Each joint is uniquely identified by its name\n"
        "# The header specifies the time at which the joint states were recorded. All the joint states\n"
        "# in one message have to be recorded at the same time.\n"
        "#\n"
        "# This message consists of a multiple arrays, one for each part of the joint state. \n"
        "# The goal is to make each of the fields optional. When e.g. your joints have no\n"
        "# effort associated with them, you can leave the effort array empty. \n"
        "#\n"
        "# All arrays in this message should have the same size, or be empty.\n"
        "# This is the only way to uniquely associate the joint name with the correct\n"
        "# states.\n"
        "\n"
        "\n"
        "Header header\n"
        "\n"
        "string[] name\n"
        "float64[] position\n"
        "float64[] velocity\n"
        "float64[] effort\n" + _SEPARATOR + "MSG: std_msgs/Header\n" + _HEADER_TEXT
    )

    header: RosHeader
    name: list[str]
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray

    def _encode(self, out: list[bytes]) -> None:
        self.header._encode(out)
        _strings(out, self.name, "name")
        _array(out, self.position, _F64, "position")
        _array(out, self.velocity, _F64, "velocity")
        _array(out, self.effort, _F64, "effort")

    @classmethod
    def deserialize(cls, data: bytes | bytearray | memoryview) -> Self:
        """``Ros1Message.deserialize``, with a straight read first for a well-formed body (``_joint_state_fast``)."""
        buf = data.tobytes() if isinstance(data, memoryview) else bytes(data)
        fast = _joint_state_fast(cls, buf)
        return fast if fast is not None else cls._checked(buf)

    @classmethod
    def _decode(cls, r: _Reader) -> Self:
        return cls(
            header=RosHeader._decode(r),
            name=r.strings("name"),
            position=r.array(_F64, "position"),
            velocity=r.array(_F64, "velocity"),
            effort=r.array(_F64, "effort"),
        )


def _joint_state_fast(cls: Any, buf: bytes) -> Any:
    """A well-formed JointState body read straight through (a driver's joint states arrive at the hardware rate);
    None for anything else, which the checked reader then reads again to say exactly what is wrong."""
    size = len(buf)
    if size < 20:
        return None
    u32 = _U32.unpack_from
    try:
        seq, secs, nsecs = _HEADER.unpack_from(buf, 0)
        (n,) = u32(buf, 12)
        pos = 16 + n
        if pos + 4 > size:
            return None
        frame_id = buf[16:pos].decode()
        (k,) = u32(buf, pos)
        pos += 4
        if 4 * k > size - pos:
            return None
        names = []
        for _ in range(k):
            (m,) = u32(buf, pos)
            end = pos + 4 + m
            if end > size:
                return None
            names.append(buf[pos + 4 : end].decode())
            pos = end
        arrays = []
        for _ in range(3):
            (c,) = u32(buf, pos)
            end = pos + 4 + 8 * c
            if end > size:
                return None
            arrays.append(np.frombuffer(buf, dtype=_F64, count=c, offset=pos + 4))
            pos = end
    except (struct.error, UnicodeDecodeError):
        return None
    if pos != size:
        return None
    header = RosHeader(seq=seq, stamp_ns=secs * _NS + nsecs, frame_id=frame_id)
    return cls(header=header, name=names, position=arrays[0], velocity=arrays[1], effort=arrays[2])


@dataclass(frozen=True, slots=True, eq=False)
class Float64MultiArray(Ros1Message):
    """std_msgs/Float64MultiArray: what ros_control's JointGroupPositionController reads on ``<controller>/command``.

    ``dim`` holds the layout's (label, size, stride) triples; controllers leave it empty.
    """

    _type: ClassVar[str] = "std_msgs/Float64MultiArray"
    _md5sum: ClassVar[str] = "4b7d974086d4060e7db4613a7e6c3ba4"
    _full_text: ClassVar[str] = (
        "# Please look at the MultiArrayLayout message definition for\n"
        "# documentation on all multiarrays.\n"
        "\n"
        "MultiArrayLayout  layout        # specification of data layout\n"
        "float64[]         data          # array of data\n"
        "\n" + _SEPARATOR + "MSG: std_msgs/MultiArrayLayout\n"
        "# The multiarray declares a generic multi-dimensional array of a\n"
        "# particular data type.  Dimensions are ordered from outer most\n"
        "# to inner most.\n"
        "\n"
        "MultiArrayDimension[] dim # Array of dimension properties\n"
        "uint32 data_offset        # padding elements at front of data\n"
        "\n"
        "# Accessors should ALWAYS be written in terms of dimension stride\n"
        "# and specified outer-most dimension first.\n"
        "# \n"
        "# multiarray(i,j,k) = data[data_offset + dim_stride[1]*i + dim_stride[2]*j + k]\n"
        "#\n"
        "# A standard, 3-channel 640x480 image with interleaved color channels\n"
        "# would be specified as:\n"
        "#\n"
        '# dim[0].label  = "height"\n'
        "# dim[0].size   = 480\n"
        "# dim[0].stride = 3*640*480 = 921600  (note dim[0] stride is just size of image)\n"
        '# dim[1].label  = "width"\n'
        "# dim[1].size   = 640\n"
        "# dim[1].stride = 3*640 = 1920\n"
        '# dim[2].label  = "channel"\n'
        "# dim[2].size   = 3\n"
        "# dim[2].stride = 3\n"
        "#\n"
        "# multiarray(i,j,k) refers to the ith row, jth column, and kth channel.\n"
        + _SEPARATOR
        + "MSG: std_msgs/MultiArrayDimension\n"
        "string label   # label of given dimension\n"
        "uint32 size    # size of given dimension (in type units)\n"
        "uint32 stride  # stride of given dimension"
    )

    data: np.ndarray
    dim: list[tuple[str, int, int]] = field(default_factory=list)
    data_offset: int = 0

    def _encode(self, out: list[bytes]) -> None:
        out.append(_U32.pack(len(self.dim)))
        for i, d in enumerate(self.dim):
            if len(d) != 3:
                raise CodecError(f"dim[{i}]: expected (label, size, stride), got {d!r}")
            _string(out, d[0], f"dim[{i}].label")
            _pack(out, _DIM, f"dim[{i}].size/stride", d[1], d[2])
        _pack(out, _U32, "data_offset", self.data_offset)
        _array(out, self.data, _F64, "data")

    @classmethod
    def _decode(cls, r: _Reader) -> Self:
        dims = []
        for i in range(r.count("dim", 12)):
            label = r.string(f"dim[{i}].label")
            size, stride = r.unpack(_DIM, f"dim[{i}].size/stride")
            dims.append((label, size, stride))
        offset = r.u32("data_offset")
        return cls(data=r.array(_F64, "data"), dim=dims, data_offset=offset)


_POINT_TEXT = (
    "# Each trajectory point specifies either positions[, velocities[, accelerations]]\n"
    "# or positions[, effort] for the trajectory to be executed.\n"
    "# All specified values are in the same order as the joint names in JointTrajectory.msg\n"
    "\n"
    "float64[] positions\n"
    "float64[] velocities\n"
    "float64[] accelerations\n"
    "float64[] effort\n"
    "duration time_from_start\n"
)


@dataclass(frozen=True, slots=True, eq=False)
class JointTrajectoryPoint(Ros1Message):
    """trajectory_msgs/JointTrajectoryPoint; ``time_from_start_ns`` is a duration (int32 secs + int32 nsecs)."""

    _type: ClassVar[str] = "trajectory_msgs/JointTrajectoryPoint"
    _md5sum: ClassVar[str] = "f3cd1e1c4d320c79d6985c904ae5dcd3"
    _full_text: ClassVar[str] = _POINT_TEXT

    positions: np.ndarray
    velocities: np.ndarray
    accelerations: np.ndarray
    effort: np.ndarray
    time_from_start_ns: int

    def _encode(self, out: list[bytes]) -> None:
        _array(out, self.positions, _F64, "positions")
        _array(out, self.velocities, _F64, "velocities")
        _array(out, self.accelerations, _F64, "accelerations")
        _array(out, self.effort, _F64, "effort")
        # floor division keeps nsecs in [0, 1e9), as genpy's Duration normalises it.
        _pack(out, _DURATION, "time_from_start", *divmod(self.time_from_start_ns, _NS))

    @classmethod
    def _decode(cls, r: _Reader) -> Self:
        positions = r.array(_F64, "positions")
        velocities = r.array(_F64, "velocities")
        accelerations = r.array(_F64, "accelerations")
        effort = r.array(_F64, "effort")
        secs, nsecs = r.unpack(_DURATION, "time_from_start")
        return cls(positions, velocities, accelerations, effort, time_from_start_ns=secs * _NS + nsecs)


@dataclass(frozen=True, slots=True, eq=False)
class JointTrajectory(Ros1Message):
    """trajectory_msgs/JointTrajectory: the ``command`` topic of ros_control's JointTrajectoryController."""

    _type: ClassVar[str] = "trajectory_msgs/JointTrajectory"
    _md5sum: ClassVar[str] = "65b4f94a94d1ed67169da35a02f33d3f"
    _full_text: ClassVar[str] = (
        "Header header\n"
        "string[] joint_names\n"
        "JointTrajectoryPoint[] points\n"
        + _SEPARATOR
        + "MSG: std_msgs/Header\n"
        + _HEADER_TEXT
        + _SEPARATOR
        + "MSG: trajectory_msgs/JointTrajectoryPoint\n"
        + _POINT_TEXT
    )

    header: RosHeader
    joint_names: list[str]
    points: list[JointTrajectoryPoint]

    def _encode(self, out: list[bytes]) -> None:
        self.header._encode(out)
        _strings(out, self.joint_names, "joint_names")
        out.append(_U32.pack(len(self.points)))
        for i, p in enumerate(self.points):
            if not isinstance(p, JointTrajectoryPoint):
                raise CodecError(f"points[{i}]: expected JointTrajectoryPoint, got {type(p).__name__}")
            p._encode(out)

    @classmethod
    def _decode(cls, r: _Reader) -> Self:
        header = RosHeader._decode(r)
        names = r.strings("joint_names")
        points = [JointTrajectoryPoint._decode(r) for _ in range(r.count("points", 4 * 4 + 8))]
        return cls(header=header, joint_names=names, points=points)


@dataclass(frozen=True, slots=True, eq=False)
class JointGroupCommand(Ros1Message):
    """interbotix_xs_msgs/JointGroupCommand: the Interbotix SDK's ``/<robot>/commands/joint_group`` (float32 cmd).

    Not packaged in Debian; ``_md5sum`` is genmsg's md5 of the definition without comments ("string name\\n
    float32[] cmd"), which the tests recompute with genmsg.
    """

    _type: ClassVar[str] = "interbotix_xs_msgs/JointGroupCommand"
    _md5sum: ClassVar[str] = "fa54c229b7238fc905e59a51a526f379"
    _full_text: ClassVar[str] = (
        "# Command the joints in the specified joint group. Note that the commands are processed differently based "
        "on the group's operating mode.\n"
        "# For example, if a group's operating mode is set to 'position', the commands are interpreted as positions "
        "in radians\n"
        "\n"
        "string name            # Name of joint group\n"
        "float32[] cmd          # List of joint commands; order is dictated by the index of each joint name for the "
        "given group in the 'groups' section of a 'motor_config' yaml file\n"
    )

    name: str
    cmd: np.ndarray

    def _encode(self, out: list[bytes]) -> None:
        _string(out, self.name, "name")
        _array(out, self.cmd, _F32, "cmd")

    @classmethod
    def _decode(cls, r: _Reader) -> Self:
        return cls(name=r.string("name"), cmd=r.array(_F32, "cmd"))


_IMAGE_SIZE = struct.Struct("<II")  # height, width
_IMAGE_STEP = struct.Struct("<BI")  # is_bigendian, step
_U8 = np.dtype(np.uint8)


@dataclass(frozen=True, slots=True, eq=False)
class Image(Ros1Message):
    """sensor_msgs/Image: ``height`` rows of ``step`` bytes in ``data``, pixels in ``encoding`` (e.g. ``rgb8``)."""

    _type: ClassVar[str] = "sensor_msgs/Image"
    _md5sum: ClassVar[str] = "060021388200f6f0f447d0fcd9c64743"
    _full_text: ClassVar[str] = (
        "# This message contains an uncompressed image\n"
        "# (0, 0) is at top-left corner of image\n"
        "#\n"
        "\n"
        "Header header        # Header timestamp should be acquisition time of image\n"
        "                     # Header frame_id should be optical frame of camera\n"
        "                     # origin of frame should be optical center of camera\n"
        "                     # +x should point to the right in the image\n"
        "                     # +y should point down in the image\n"
        "                     # +z should point into to plane of the image\n"
        "                     # If the frame_id here and the frame_id of the CameraInfo\n"
        "                     # message associated with the image conflict\n"
        "                     # the behavior is undefined\n"
        "\n"
        "uint32 height         # image height, that is, number of rows\n"
        "uint32 width          # image width, that is, number of columns\n"
        "\n"
        "# The legal values for encoding are in file src/image_encodings.cpp\n"
        "# If you want to standardize a new string format, join\n"
        "# ros-users@lists.sourceforge.net and send an email proposing a new encoding.\n"
        "\n"
        "string encoding       # Encoding of pixels -- channel meaning, ordering, size\n"
        "                      # taken from the list of strings in include/sensor_msgs/image_encodings.h\n"
        "\n"
        "uint8 is_bigendian    # is this data bigendian?\n"
        "uint32 step           # Full row length in bytes\n"
        "uint8[] data          # actual matrix data, size is (step * rows)\n"
        + _SEPARATOR
        + "MSG: std_msgs/Header\n"
        + _HEADER_TEXT
    )

    header: RosHeader
    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: np.ndarray

    def _encode(self, out: list[bytes]) -> None:
        self.header._encode(out)
        _pack(out, _IMAGE_SIZE, "height/width", self.height, self.width)
        _string(out, self.encoding, "encoding")
        _pack(out, _IMAGE_STEP, "is_bigendian/step", self.is_bigendian, self.step)
        _array(out, self.data, _U8, "data")

    @classmethod
    def _decode(cls, r: _Reader) -> Self:
        header = RosHeader._decode(r)
        height, width = r.unpack(_IMAGE_SIZE, "height/width")
        encoding = r.string("encoding")
        big, step = r.unpack(_IMAGE_STEP, "is_bigendian/step")
        data = r.array(_U8, "data")
        return cls(header=header, height=height, width=width, encoding=encoding, is_bigendian=big, step=step, data=data)


@dataclass(frozen=True, slots=True, eq=False)
class CompressedImage(Ros1Message):
    """sensor_msgs/CompressedImage: an image in ``format`` (``jpeg`` or ``png``, image_transport's words)."""

    _type: ClassVar[str] = "sensor_msgs/CompressedImage"
    _md5sum: ClassVar[str] = "8f7a12909da2c9d3332d540a0977563f"
    _full_text: ClassVar[str] = (
        "# This message contains a compressed image\n"
        "\n"
        "Header header        # Header timestamp should be acquisition time of image\n"
        "                     # Header frame_id should be optical frame of camera\n"
        "                     # origin of frame should be optical center of camera\n"
        "                     # +x should point to the right in the image\n"
        "                     # +y should point down in the image\n"
        "                     # +z should point into to plane of the image\n"
        "\n"
        "string format        # Specifies the format of the data\n"
        "                     #   Acceptable values:\n"
        "                     #     jpeg, png\n"
        "uint8[] data         # Compressed image buffer\n" + _SEPARATOR + "MSG: std_msgs/Header\n" + _HEADER_TEXT
    )

    header: RosHeader
    format: str
    data: np.ndarray

    def _encode(self, out: list[bytes]) -> None:
        self.header._encode(out)
        _string(out, self.format, "format")
        _array(out, self.data, _U8, "data")

    @classmethod
    def _decode(cls, r: _Reader) -> Self:
        return cls(header=RosHeader._decode(r), format=r.string("format"), data=r.array(_U8, "data"))


MESSAGE_TYPES: dict[str, type[Ros1Message]] = {
    cls._type: cls
    for cls in (
        RosHeader,
        JointState,
        Float64MultiArray,
        JointTrajectoryPoint,
        JointTrajectory,
        JointGroupCommand,
        Image,
        CompressedImage,
    )
}
