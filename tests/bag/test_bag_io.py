"""BagWriter and BagReader on real files: every message type round trips, rosbags reads the bag as ROS 2, and a
truncated, corrupt or unwritable bag reads up to the damage and names the offset."""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from _bag_messages import assert_same, one_of_each

from uniros_async.bag import BagDamagedError, BagError, BagReader, BagWriter, schemas
from uniros_async.bus import messages as m
from uniros_async.errors import ConfigError


def write(path: Path, n: int, **kw: Any) -> list[tuple[str, int, Any]]:
    written = []
    with BagWriter(path, **kw) as w:
        for i in range(n):
            for topic, msg in one_of_each(i):
                t = 1_000_000_000 + i * 10_000_000
                assert w.put(topic, msg, t)
                written.append((topic, t, msg))
    assert w.stats.total_written == len(written) and w.stats.total_dropped == 0
    return written


def test_every_type_round_trips_with_both_compressions(tmp_path: Path) -> None:
    builtin = {n for n in m.__all__ if n in m.registered_types()}  # bus/messages.py's own types
    assert {type(x).__name__ for _, x in one_of_each(0)} == builtin
    for compression in ("zstd", "lz4"):
        path = tmp_path / f"{compression}.mcap"
        written = write(path, 20, compression=compression, chunk_bytes=64 << 10)
        got = list(BagReader(path).messages())
        assert len(got) == len(written)
        for (topic, t, msg), bm in zip(written, got, strict=True):
            assert (bm.topic, bm.log_time_ns, bm.type_name) == (topic, t, type(msg).__name__)
            assert_same(bm.message, msg)
        info = BagReader(path).info()
        assert BagReader(path)._summary_info() == info  # a complete bag's info comes from its summary
        assert info.complete and info.damage is None and info.compression == {compression}
        assert info.chunks > 1 and info.message_count == len(written)
        assert info.topics["/rx200/joint_states"].schema_name == "sensor_msgs/msg/JointState"
        assert info.topics["/rx200/command"].schema_name == "uniros_msgs/msg/JointCommand"


def test_ros2_less_fields_are_dropped_and_our_own_encoding_keeps_them(tmp_path: Path) -> None:
    h = m.Header(stamp_ns=5, seq=7, frame_id="f")
    js = m.JointState(header=h, name=("a",), position=[1.0], velocity=[2.0], effort=[3.0], command_stamp_ns=4)
    for ros2, seq, echo in ((True, 0, None), (False, 7, 4)):
        path = tmp_path / f"{ros2}.mcap"
        with BagWriter(path, ros2=ros2) as w:
            w.put("/js", js, 1)
        (bm,) = BagReader(path).messages()
        assert bm.message.header.seq == seq and bm.message.command_stamp_ns == echo
        assert bm.message.header.stamp_ns == 5 and np.array_equal(bm.message.position, [1.0])


def test_rosbags_reads_the_bag_as_ros2_and_decodes_every_standard_message_to_the_same_values(tmp_path: Path) -> None:
    from rosbags.highlevel import AnyReader

    from uniros_async.adapters.ros2 import msgs

    path = tmp_path / "b.mcap"
    written = write(path, 5)
    ours = {(t, tm): msg for t, tm, msg in written}
    seen: set[str] = set()
    with AnyReader([path], default_typestore=msgs.typestore()) as reader:
        assert {c.topic: c.msgtype for c in reader.connections}["/rx200/joint_states"] == "sensor_msgs/msg/JointState"
        for conn, t, raw in reader.messages():
            ros = reader.deserialize(raw, conn.msgtype)
            msg = ours[(conn.topic, t)]
            name = type(msg).__name__
            seen.add(name)
            if name in schemas.ROS2_TYPES:
                assert conn.msgtype == schemas.ROS2_TYPES[name]
                # rosbags' own decoding, compared field by field with what was written
                _same_as_ros(msg, ros)
            else:
                assert conn.msgtype == f"uniros_msgs/msg/{name}"
                assert_same(schemas.decode(bytes(raw), schemas.schema_for(name)), msg)
    assert seen == {type(x).__name__ for _, x in one_of_each(0)}


def _ns(t: Any) -> int:
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


def _same_as_ros(msg: Any, ros: Any) -> None:
    name = type(msg).__name__
    header = msg if name == "Header" else getattr(msg, "header", None)
    rh = ros if name == "Header" else getattr(ros, "header", None)
    if header is not None:
        assert _ns(rh.stamp) == header.stamp_ns and rh.frame_id == header.frame_id
    if name == "JointState":
        assert list(ros.name) == list(msg.name)
        for f in ("position", "velocity", "effort"):
            assert np.array_equal(getattr(ros, f), getattr(msg, f))
    elif name == "Image":
        h, w, c = msg.data.shape
        assert (ros.height, ros.width, ros.step, ros.encoding) == (h, w, w * c, msg.encoding)
        assert np.array_equal(np.asarray(ros.data).reshape(h, w, c), msg.data)
    elif name == "Pose":
        p, q = ros.pose.position, ros.pose.orientation
        assert np.array_equal([p.x, p.y, p.z], msg.position)
        assert np.array_equal([q.w, q.x, q.y, q.z], msg.orientation)
    elif name == "ClockTick":
        assert _ns(ros.clock) == msg.sim_time_ns
    elif name == "Text":
        assert ros.data == msg.data


def _chunk_offsets(path: Path) -> list[tuple[int, int]]:
    """(offset, length) of every chunk record, walking the file's records."""
    data = path.read_bytes()
    pos, out = 8, []
    while pos + 9 <= len(data):
        op, n = struct.unpack_from("<BQ", data, pos)
        if op == 0x06:
            out.append((pos, n))
        if op == 0x02:
            break
        pos += 9 + n
    return out


def test_a_truncated_bag_reads_up_to_its_last_whole_chunk_then_names_the_offset(tmp_path: Path) -> None:
    path = tmp_path / "b.mcap"
    written = write(path, 30, chunk_bytes=32 << 10)
    chunks = _chunk_offsets(path)
    assert len(chunks) >= 4
    off, n = chunks[2]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: off + n // 2])
    reader = BagReader(cut)
    got = []
    with pytest.raises(BagDamagedError, match=f"damaged at byte {off}") as exc:
        for bm in reader.messages():
            got.append(bm)
    assert exc.value.offset == off and str(cut) in str(exc.value)
    assert 0 < len(got) < len(written)
    for (topic, t, msg), bm in zip(written, got, strict=False):
        assert (bm.topic, bm.log_time_ns) == (topic, t)
        assert_same(bm.message, msg)
    # strict=False stops there quietly, and says where
    assert len(list(reader.messages(strict=False))) == len(got) and reader.damage is not None
    info = BagReader(cut).info()
    assert info.message_count == len(got) and not info.complete and f"byte {off}" in (info.damage or "")


def test_a_corrupt_chunk_is_caught_by_its_crc(tmp_path: Path) -> None:
    path = tmp_path / "b.mcap"
    write(path, 30, chunk_bytes=32 << 10, compression="none")
    off, n = _chunk_offsets(path)[1]
    data = bytearray(path.read_bytes())
    data[off + n - 50] ^= 0xFF  # a byte inside the chunk's messages
    path.write_bytes(bytes(data))
    with pytest.raises(BagDamagedError, match=f"byte {off}: a chunk's CRC"):
        list(BagReader(path).messages())


def test_bad_files_and_settings_are_named(tmp_path: Path) -> None:
    with pytest.raises(BagError, match="cannot open bag .*nope.mcap"):
        BagReader(tmp_path / "nope.mcap")
    (tmp_path / "x.mcap").write_bytes(b"not a bag at all")
    with pytest.raises(BagError, match="is not an MCAP file"):
        BagReader(tmp_path / "x.mcap")
    with pytest.raises(ConfigError, match="compression"):
        BagWriter(tmp_path / "y.mcap", compression="gzip")
    with pytest.raises(BagError, match="cannot create bag"):
        BagWriter(tmp_path / "no_dir" / "z.mcap")
    with BagWriter(tmp_path / "t.mcap") as w, pytest.raises(ConfigError, match="ns >= 0"):
        w.put("/text", m.Text(data="x"), -1)


def test_a_full_queue_drops_new_messages_and_counts_them_per_topic(tmp_path: Path) -> None:
    img = m.Image(header=m.Header(), data=np.zeros((480, 640, 3), np.uint8))
    w = BagWriter(tmp_path / "b.mcap", max_queue_bytes=4 * img.data.nbytes)
    accepted = sum(w.put("/img", img, i) for i in range(200))  # far faster than the thread compresses them
    stats = w.close()
    assert stats.written["/img"] == accepted and stats.dropped["/img"] == 200 - accepted > 0
    assert len(list(BagReader(tmp_path / "b.mcap").messages())) == accepted
