"""ROS 1 messages: byte-identical to genpy (the Debian classes, run by the system Python), round trips, md5s, and
clear CodecErrors for bad input."""

from __future__ import annotations

import json
import subprocess
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from uniros_async.adapters.ros1 import msgs
from uniros_async.adapters.ros1.msgs import (
    MESSAGE_TYPES,
    CompressedImage,
    Float64MultiArray,
    Image,
    JointGroupCommand,
    JointState,
    JointTrajectory,
    JointTrajectoryPoint,
    Ros1Message,
    RosHeader,
)
from uniros_async.bench.ros1_peers import ros1_missing, ros1_python, ros_env
from uniros_async.errors import CodecError

NS = 1_000_000_000


def _point(positions: list[float], time_from_start_ns: int) -> JointTrajectoryPoint:
    empty = np.array([])
    return JointTrajectoryPoint(np.array(positions), np.zeros(len(positions)), empty, empty, time_from_start_ns)


# Each case is built the same way here and in GENPY_SCRIPT (by name), so the bytes must match exactly.
CASES: dict[str, Ros1Message] = {
    "header": RosHeader(seq=4_000_000_000, stamp_ns=1_700_000_000 * NS + 123_456_789, frame_id="bäse"),
    "joint_state": JointState(
        RosHeader(7, 1_700_000_000 * NS + 5, "base_link"),
        ["waist", "shoulder", "elbow"],
        np.array([0.1, -0.2, 0.3]),
        np.array([1.0, 2.0, 3.0]),
        np.array([]),
    ),
    "joint_state_empty": JointState(RosHeader(), [], np.array([]), np.array([]), np.array([])),
    "multiarray": Float64MultiArray(np.array([1.5, -2.5, 3.25]), [("x", 3, 1), ("", 0, 0)], data_offset=2),
    "multiarray_empty": Float64MultiArray(np.array([])),
    "point": _point([1.0, 2.0], 1_500_000_000),
    "trajectory": JointTrajectory(
        RosHeader(1, 5 * NS + 6, ""),
        ["a", "b"],
        [_point([1.0, 2.0], 1_500_000_000), _point([3.0, 4.0], -250_000_000)],
    ),
    "group_command": JointGroupCommand("arm", np.array([0.5, -1.25, 3.0], np.float32)),
    "image": Image(RosHeader(3, 5 * NS + 6, "cam"), 2, 3, "rgb8", 0, 10, np.arange(20, dtype=np.uint8)),
    "compressed": CompressedImage(RosHeader(3, 5 * NS + 6, "cam"), "jpeg", np.arange(7, dtype=np.uint8)),
}

GENPY_SCRIPT = r"""
import io, json, sys
import genmsg, genmsg.msg_loader, genpy, genpy.dynamic, rospy
from sensor_msgs.msg import CompressedImage, Image, JointState
from std_msgs.msg import Float64MultiArray, Header, MultiArrayDimension
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

ours = json.loads(sys.argv[1])
JGC_TEXT = ours["jgc_text"]
JointGroupCommand = genpy.dynamic.generate_dynamic("interbotix_xs_msgs/JointGroupCommand", JGC_TEXT)[
    "interbotix_xs_msgs/JointGroupCommand"]
ctx = genmsg.MsgContext.create_default()
spec = genmsg.msg_loader.load_msg_from_string(ctx, JGC_TEXT, "interbotix_xs_msgs/JointGroupCommand")

def hdr(seq, secs, nsecs, frame):
    return Header(seq=seq, stamp=rospy.Time(secs, nsecs), frame_id=frame)

def point(pos, secs, nsecs):
    return JointTrajectoryPoint(positions=pos, velocities=[0.0] * len(pos), accelerations=[], effort=[],
                                time_from_start=rospy.Duration(secs, nsecs))

cases = {
    "header": hdr(4000000000, 1700000000, 123456789, "bäse"),
    "joint_state": JointState(header=hdr(7, 1700000000, 5, "base_link"), name=["waist", "shoulder", "elbow"],
                              position=[0.1, -0.2, 0.3], velocity=[1.0, 2.0, 3.0], effort=[]),
    "joint_state_empty": JointState(),
    "multiarray": Float64MultiArray(data=[1.5, -2.5, 3.25]),
    "multiarray_empty": Float64MultiArray(),
    "point": point([1.0, 2.0], 1, 500000000),
    "trajectory": JointTrajectory(header=hdr(1, 5, 6, ""), joint_names=["a", "b"],
                                  points=[point([1.0, 2.0], 1, 500000000), point([3.0, 4.0], 0, -250000000)]),
    "group_command": JointGroupCommand(name="arm", cmd=[0.5, -1.25, 3.0]),
    "image": Image(header=hdr(3, 5, 6, "cam"), height=2, width=3, encoding="rgb8", is_bigendian=0, step=10,
                   data=bytes(range(20))),
    "compressed": CompressedImage(header=hdr(3, 5, 6, "cam"), format="jpeg", data=bytes(range(7))),
}
cases["multiarray"].layout.dim = [MultiArrayDimension("x", 3, 1), MultiArrayDimension("", 0, 0)]
cases["multiarray"].layout.data_offset = 2

out = {"bytes": {}, "classes": {}, "decoded": {}}
for name, msg in cases.items():
    buf = io.BytesIO()
    msg.serialize(buf)
    out["bytes"][name] = buf.getvalue().hex()
for cls in (Header, JointState, Float64MultiArray, JointTrajectoryPoint, JointTrajectory, JointGroupCommand, Image,
            CompressedImage):
    out["classes"][cls._type] = {"md5": cls._md5sum, "full_text": cls._full_text}
out["jgc_md5_genmsg"] = genmsg.compute_md5(ctx, spec)
# genpy reads our bytes back
for name, hexbytes in ours["bytes"].items():
    msg = type(cases[name])()
    msg.deserialize(bytes.fromhex(hexbytes))
    out["decoded"][name] = msg == cases[name]
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def genpy_ref(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    reason = ros1_missing()
    if reason is not None:
        pytest.skip(reason)
    ours = {"jgc_text": JointGroupCommand._full_text, "bytes": {k: m.serialize().hex() for k, m in CASES.items()}}
    proc = subprocess.run(
        [ros1_python(), "-c", GENPY_SCRIPT, json.dumps(ours)],
        capture_output=True,
        text=True,
        timeout=60,
        env=ros_env("http://127.0.0.1:1/", home=tmp_path_factory.mktemp("ros_home")),
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    return dict(json.loads(proc.stdout))


def as_plain(value: Any) -> Any:
    """A message as nested tuples/lists, so two messages compare with ==."""
    if isinstance(value, Ros1Message):
        return (type(value).__name__, *(as_plain(getattr(value, f)) for f in value.__dataclass_fields__))
    if isinstance(value, np.ndarray):
        return (str(value.dtype), value.tolist())
    if isinstance(value, list | tuple):
        return [as_plain(v) for v in value]
    return value


@pytest.mark.parametrize("name", list(CASES))
def test_bytes_equal_genpy(genpy_ref: dict[str, Any], name: str) -> None:
    assert CASES[name].serialize().hex() == genpy_ref["bytes"][name]


@pytest.mark.parametrize("name", list(CASES))
def test_we_read_genpy_bytes_and_genpy_reads_ours(genpy_ref: dict[str, Any], name: str) -> None:
    msg = CASES[name]
    back = type(msg).deserialize(bytes.fromhex(genpy_ref["bytes"][name]))
    assert as_plain(back) == as_plain(msg)
    assert genpy_ref["decoded"][name] is True


@pytest.mark.parametrize("type_name", sorted(MESSAGE_TYPES))
def test_md5_and_definition_equal_genpy(genpy_ref: dict[str, Any], type_name: str) -> None:
    cls = MESSAGE_TYPES[type_name]
    assert cls._type == type_name
    assert cls._md5sum == genpy_ref["classes"][type_name]["md5"]
    assert cls._full_text == genpy_ref["classes"][type_name]["full_text"]


def test_joint_group_command_md5_is_genmsgs(genpy_ref: dict[str, Any]) -> None:
    assert JointGroupCommand._md5sum == genpy_ref["jgc_md5_genmsg"] == "fa54c229b7238fc905e59a51a526f379"


def test_message_types_are_keyed_by_type() -> None:
    assert set(MESSAGE_TYPES) == {
        "std_msgs/Header",
        "sensor_msgs/JointState",
        "std_msgs/Float64MultiArray",
        "trajectory_msgs/JointTrajectoryPoint",
        "trajectory_msgs/JointTrajectory",
        "interbotix_xs_msgs/JointGroupCommand",
        "sensor_msgs/Image",
        "sensor_msgs/CompressedImage",
    }
    assert all(cls._type == key for key, cls in MESSAGE_TYPES.items())


@pytest.mark.parametrize("name", list(CASES))
def test_round_trip_every_case(name: str) -> None:
    msg = CASES[name]
    data = msg.serialize()
    assert as_plain(type(msg).deserialize(data)) == as_plain(msg)
    assert as_plain(type(msg).deserialize(memoryview(data))) == as_plain(msg)


def test_deserialized_arrays_are_float64_views_and_survive_a_reused_buffer() -> None:
    buf = bytearray(CASES["joint_state"].serialize())
    msg = JointState.deserialize(memoryview(buf))
    buf[:] = bytes(len(buf))  # the caller reuses its buffer
    assert msg.position.dtype == np.float64 and msg.position.tolist() == [0.1, -0.2, 0.3]
    assert JointGroupCommand.deserialize(CASES["group_command"].serialize()).cmd.dtype == np.float32


finite = st.floats(allow_nan=False, width=64)
names = st.lists(st.text(max_size=8), max_size=4)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seq=st.integers(0, 2**32 - 1),
    stamp_ns=st.integers(0, (2**32 - 1) * NS),
    frame=st.text(max_size=10),
    name=names,
    pos=st.lists(finite, max_size=6),
    tfs_ns=st.integers(-(2**31) * NS, (2**31 - 1) * NS),
    pos32=st.lists(st.floats(allow_nan=False, width=32), max_size=6),
)
def test_round_trip_property(
    seq: int, stamp_ns: int, frame: str, name: list[str], pos: list[float], tfs_ns: int, pos32: list[float]
) -> None:
    header = RosHeader(seq, stamp_ns, frame)
    msgs: list[Ros1Message] = [
        JointState(header, name, np.array(pos), np.array(pos[::-1]), np.array([])),
        JointTrajectory(header, name, [_point(pos, tfs_ns), _point([], 0)]),
        Float64MultiArray(np.array(pos), [(n, len(n), seq) for n in name], data_offset=seq),
        JointGroupCommand(frame, np.array(pos32, np.float32)),
    ]
    for msg in msgs:
        assert as_plain(type(msg).deserialize(msg.serialize())) == as_plain(msg)


def test_every_truncation_is_a_codec_error_naming_type_and_field() -> None:
    data = CASES["trajectory"].serialize()
    for n in range(len(data)):
        with pytest.raises(CodecError, match=r"trajectory_msgs/JointTrajectory: .*(truncated|announces)"):
            JointTrajectory.deserialize(data[:n])
    with pytest.raises(CodecError, match=r"sensor_msgs/JointState: truncated body reading header"):
        JointState.deserialize(b"\x01\x00")


def test_trailing_bytes_huge_counts_and_bad_utf8_are_codec_errors() -> None:
    data = CASES["joint_state"].serialize()
    with pytest.raises(CodecError, match=r"3 unexpected bytes after the message"):
        JointState.deserialize(data + b"abc")
    huge = JointGroupCommand.deserialize  # name "arm", then a cmd count of 2**32-1
    with pytest.raises(CodecError, match=r"interbotix_xs_msgs/JointGroupCommand: cmd announces 4294967295 items"):
        huge(b"\x03\x00\x00\x00arm\xff\xff\xff\xff")
    with pytest.raises(CodecError, match=r"name at byte 4 is not UTF-8"):
        huge(b"\x02\x00\x00\x00\xff\xfe\x00\x00\x00\x00")


@settings(max_examples=200, deadline=None)
@given(data=st.binary(max_size=200), cls=st.sampled_from(sorted(MESSAGE_TYPES.values(), key=lambda c: c._type)))
def test_random_bytes_decode_or_raise_codec_error(data: bytes, cls: type[Ros1Message]) -> None:
    try:
        msg = cls.deserialize(data)
    except CodecError as exc:
        assert cls._type in str(exc)
    else:
        assert msg.serialize() == data  # whatever decodes is exactly what we would write


@pytest.mark.parametrize(
    ("msg", "match"),
    [
        (RosHeader(seq=-1), r"std_msgs/Header: header.seq/stamp=.* out of range"),
        (RosHeader(stamp_ns=-1), r"out of range"),
        (JointState(RosHeader(), "ab", np.array([]), np.array([]), np.array([])), r"name: expected a sequence of str"),
        (JointState(RosHeader(), [], np.zeros((2, 2)), np.array([]), np.array([])), r"position: expected a 1-D array"),
        (JointGroupCommand("arm", np.array(["x"])), r"cmd: expected a 1-D array of float32"),
        (JointGroupCommand("arm", np.array([1e39])), r"cmd: expected a 1-D array of float32: overflow"),
        (JointTrajectory(RosHeader(), [], [1.0]), r"points\[0\]: expected JointTrajectoryPoint, got"),  # type: ignore
        (Float64MultiArray(np.array([]), [("x", 1)]), r"dim\[0\]: expected \(label, size, stride\)"),  # type: ignore
    ],
)
def test_unencodable_fields_are_codec_errors(msg: Ros1Message, match: str) -> None:
    with pytest.raises(CodecError, match=match):
        msg.serialize()


@settings(max_examples=200, deadline=None)
@given(
    names=st.lists(st.text(max_size=12), max_size=10),
    frame_id=st.text(max_size=20),
    seq=st.integers(0, 2**32 - 1),
    data=st.data(),
)
def test_joint_state_fast_read_matches_the_checked_one(names: list[str], frame_id: str, seq: int, data: Any) -> None:
    """JointState.deserialize reads a well-formed body straight through; it must give what the field-by-field reader
    gives, and leave every malformed body (a cut anywhere) to that reader's precise error."""
    n = len(names)
    arrays = [np.asarray(data.draw(st.lists(st.floats(allow_nan=False), min_size=k, max_size=k))) for k in (n, n, 0)]
    msg = msgs.JointState(
        header=msgs.RosHeader(seq=seq, stamp_ns=123_456_789_012, frame_id=frame_id),
        name=names,
        position=arrays[0],
        velocity=arrays[1],
        effort=arrays[2],
    )
    body = msg.serialize()
    fast, checked = msgs.JointState.deserialize(body), msgs.JointState._checked(body)
    assert fast.header == checked.header and fast.name == checked.name
    for field in ("position", "velocity", "effort"):
        np.testing.assert_array_equal(getattr(fast, field), getattr(checked, field))
    cut = data.draw(st.integers(0, len(body) - 1))
    assert msgs._joint_state_fast(msgs.JointState, body[:cut]) is None
    with pytest.raises(CodecError, match="sensor_msgs/JointState"):
        msgs.JointState.deserialize(body[:cut])
