"""The codec: round trips (property-based), zero-copy views, and errors that name the field."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from uniros_async.bus import codec
from uniros_async.bus.messages import Blob, Data, Header, Image, JointCommand, JointState, Marker, Pose, Text
from uniros_async.errors import CodecError

names = st.lists(st.text(min_size=1, max_size=12), min_size=0, max_size=10)
floats = st.floats(allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=100, deadline=None)
@given(names=names, data=st.data(), stamp=st.integers(0, 2**63 - 1), seq=st.integers(0, 2**32))
def test_joint_state_round_trip(names: list[str], data: st.DataObject, stamp: int, seq: int) -> None:
    n = len(names)
    arrays = [np.array(data.draw(st.lists(floats, min_size=n, max_size=n)), dtype=np.float64) for _ in range(3)]
    msg = JointState(
        header=Header(stamp_ns=stamp, seq=seq, frame_id="base"),
        name=tuple(names),
        position=arrays[0],
        velocity=arrays[1],
        effort=arrays[2],
    )
    frame = b"".join(bytes(p) for p in codec.encode(msg))
    out = codec.decode(frame, JointState)
    assert out.header == msg.header or (out.header.stamp_ns, out.header.seq) == (stamp, seq)
    assert out.name == msg.name
    for a, b in zip((out.position, out.velocity, out.effort), arrays, strict=True):
        np.testing.assert_array_equal(a, b)


@settings(max_examples=50, deadline=None)
@given(
    value=st.recursive(
        st.none() | st.booleans() | st.integers(-(2**63), 2**63 - 1) | floats | st.text(),
        lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=5), c, max_size=4),
    )
)
def test_data_round_trip(value: object) -> None:
    assert codec.decode(b"".join(bytes(p) for p in codec.encode(Data(value=value)))).value == value


def test_large_arrays_travel_beside_the_body_and_decode_as_views() -> None:
    img = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    parts = codec.encode(Image(header=Header(seq=1), data=img))
    assert len(parts[0]) < 200, "the msgpack body does not carry the pixels"
    assert any(isinstance(p, memoryview) and p.nbytes == img.nbytes for p in parts), "the array is not copied"
    frame = bytes(b"".join(bytes(p) for p in parts))
    out = codec.decode(memoryview(frame), Image)
    np.testing.assert_array_equal(out.data, img)
    assert out.data.base is not None and not out.data.flags.writeable, "a read-only view into the frame"
    assert codec.frame_type_name(frame) == "Image"


def test_other_messages_round_trip() -> None:
    msgs = [
        JointCommand(header=Header(), position=[0.1, 0.2], velocity=[0.0, 0.5], duration_s=0.3),
        Pose(header=Header(frame_id="world"), position=[1, 2, 3]),
        Marker(header=Header(), kind="sphere", position=[0.3, 0.0, 0.2]),
        Blob(header=Header(), data=np.arange(10, dtype=np.uint8)),
        Text(data="hello"),
    ]
    for m in msgs:
        out = codec.decode(b"".join(bytes(p) for p in codec.encode(m)))
        assert type(out) is type(m)
    assert codec.decode(b"".join(bytes(p) for p in codec.encode(msgs[1]))).orientation.tolist() == [1, 0, 0, 0]


def _frame(msg: object) -> bytearray:
    return bytearray(b"".join(bytes(p) for p in codec.encode(msg)))


def test_decode_errors_name_what_was_wrong() -> None:
    js = JointState(header=Header(), name=("a", "b"), position=[1, 2], velocity=[0, 0], effort=[0, 0])
    with pytest.raises(CodecError, match="expected JointState, got Text"):
        codec.decode(_frame(Text(data="x")), JointState)
    with pytest.raises(CodecError, match="shorter than its 4-byte header"):
        codec.decode(b"\x01")
    with pytest.raises(CodecError, match="announces a"):
        codec.decode(b"\xff\xff\x00\x00abc")
    with pytest.raises(CodecError, match="malformed frame body"):
        codec.decode(b"\x03\x00\x00\x00\xc1\xc1\xc1")
    truncated = _frame(js)[:-8]
    with pytest.raises(CodecError, match=r"JointState\.effort: array of 16 bytes .* overruns the frame"):
        codec.decode(truncated)
    unknown = codec.encode_plain(["NoSuchMessage", [], []])
    with pytest.raises(CodecError, match="unknown message type 'NoSuchMessage'"):
        codec.decode(len(unknown).to_bytes(4, "little") + unknown)


def test_wrong_dtype_and_shape_are_named() -> None:
    good = JointState(header=Header(), name=("a",), position=[1.0], velocity=[0.0], effort=[0.0])
    body = codec.decode_plain(_frame(good)[4 : 4 + int.from_bytes(_frame(good)[:4], "little")])
    name, values, table = body
    table[0][0] = "<i4"  # position claims int32
    bad = codec.encode_plain([name, values, table])
    with pytest.raises(CodecError, match=r"JointState\.position: expected dtype float64, got int32"):
        codec.decode(len(bad).to_bytes(4, "little") + bad + bytes(-(4 + len(bad)) % 8) + bytes(24))
    with pytest.raises(CodecError, match=r"JointState\.velocity: expected shape \(2,\) for 2 names"):
        JointState(header=Header(), name=("a", "b"), position=[1, 2], velocity=[0], effort=[0, 0])
    with pytest.raises(CodecError, match=r"Pose: expected position \(3,\)"):
        Pose(header=Header(), position=[1, 2])
    with pytest.raises(CodecError, match="Marker.kind"):
        Marker(header=Header(), kind="blob")
    with pytest.raises(CodecError, match="expected a @message instance, got dict"):
        codec.encode({"not": "a message"})


def test_markers_of_every_kind_round_trip_with_text_and_lifetime() -> None:
    pts = np.array([[0.1, 0.0, 0.0], [0.2, 0.1, 0.3]])
    for kind in ("sphere", "cube", "arrow", "cylinder", "line_strip", "points", "text"):
        m = Marker(header=Header(stamp_ns=7, frame_id="world"), ns="goal", id=3, kind=kind, points=pts,
                   color=[0.1, 0.2, 0.3, 0.4], text=f"a {kind}", lifetime_s=1.5)  # fmt: skip
        out = codec.decode(b"".join(bytes(p) for p in codec.encode(m)), Marker)
        assert (out.kind, out.text, out.lifetime_s, out.header.frame_id) == (kind, f"a {kind}", 1.5, "world")
        np.testing.assert_array_equal(out.points, pts)
        np.testing.assert_array_equal(out.color, [0.1, 0.2, 0.3, 0.4])
    with pytest.raises(CodecError, match=r"Marker.points: expected shape \(N, 3\)"):
        Marker(header=Header(), kind="points", points=np.zeros((2, 2)))
    with pytest.raises(CodecError, match="Marker.lifetime_s: expected >= 0"):
        Marker(header=Header(), lifetime_s=-1.0)
