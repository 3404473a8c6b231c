"""The worker protocol's frames (runtime/protocol.py ``pack``/``unpack``): arrays by value whatever their layout,
numpy scalars as Python ones, malformed frames refused by name. No processes: the codec alone."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from uniros_async.bus.codec import array_bytes
from uniros_async.errors import CodecError
from uniros_async.runtime.protocol import (
    STEP_TAG,
    PackedRequest,
    array_head,
    pack,
    pack_step_reply,
    pack_step_request,
    unpack,
    unpack_step_reply_into,
)


@pytest.mark.parametrize(
    "a",
    [
        np.arange(12, dtype=np.float32).reshape(3, 4),
        np.arange(12, dtype=np.float64).reshape(3, 4).T,  # not C-contiguous: same header key as a C array of 4x3
        np.arange(24, dtype=np.int16).reshape(2, 3, 4)[:, ::2, 1:],
        np.arange(6, dtype=">i4"),  # big-endian stays big-endian
        np.zeros((0, 5), np.uint8),
        np.array(3.5),
        np.array([True, False]),
    ],
    ids=lambda a: f"{a.dtype.str}{a.shape}",
)
def test_arrays_round_trip_by_value_and_come_back_writable(a: np.ndarray) -> None:
    for _ in range(2):  # the second time through the cached headers
        b = unpack(pack({"op": "step", "action": a}))["action"]
        assert b.dtype == a.dtype and b.shape == a.shape and np.array_equal(a, b)
        assert b.flags.writeable and b.flags.c_contiguous


def test_scalars_objects_and_odd_keys() -> None:
    msg = unpack(pack({"r": np.float64(0.5), "n": np.int64(3), "o": np.array([1, "x"], dtype=object), (1, 2): "t"}))
    assert msg["r"] == 0.5 and type(msg["r"]) is float and msg["n"] == 3 and type(msg["n"]) is int
    # other numpy scalars keep their dtype (a vector env batches an info's float32 into a float32 array)
    kept = unpack(pack({"f": np.float32(0.5), "i": np.int8(-3), "u": np.uint16(7), "b": np.bool_(True)}))
    assert type(kept["f"]) is np.float32 and kept["f"] == 0.5 and type(kept["i"]) is np.int8 and kept["i"] == -3
    assert type(kept["u"]) is np.uint16 and kept["u"] == 7 and kept["b"] is True
    assert msg["o"] == [1, "x"]
    assert msg["(1, 2)"] == "t"  # a tuple key comes back as its str


def test_malformed_frames_are_refused_by_name() -> None:
    with pytest.raises(CodecError, match="malformed worker frame"):
        unpack(b"\x92\x01")  # an array of two that ends after one
    with pytest.raises(CodecError, match="expected a map, got list"):
        unpack(pack({"x": 1})[:0] + b"\x91\x01")


@pytest.mark.parametrize("action", [np.array([0.25, -1.0], np.float32), 1, np.array(2, np.int64)], ids=repr)
@pytest.mark.parametrize("autoreset", ["next_step", "same_step", None])
def test_step_requests_round_trip_to_the_message_they_stand_for(action: object, autoreset: str | None) -> None:
    for t in (123_456_789_012, None):
        req = pack_step_request(action, autoreset, t)
        assert isinstance(req, PackedRequest) and req.get("op") == "step" and req.get("other", 7) == 7
        frame = pack(req)  # the supervisor's pack sends it as it is
        assert frame is req.frame and frame[0] == STEP_TAG
        msg = unpack(frame)
        assert msg["op"] == "step" and msg["autoreset"] == autoreset and msg.get("t") == t
        assert np.array_equal(msg["action"], action) and type(msg["action"]) is type(action)


def test_step_replies_round_trip_and_odd_infos_take_the_general_path() -> None:
    obs = np.arange(4, dtype=np.float32)
    for terminated, truncated in [(False, False), (True, False), (False, True), (True, True)]:
        frame = pack_step_reply([obs, -0.5, terminated, truncated, {"env_id": "x", "d": np.ones(2)}])
        assert frame[0] == STEP_TAG
        reply = unpack(frame)
        assert reply["ok"] is True
        o, r, te, tr, info = reply["result"]
        assert np.array_equal(o, obs) and o.dtype == obs.dtype and r == -0.5 and (te, tr) == (terminated, truncated)
        assert info["env_id"] == "x" and np.array_equal(info["d"], np.ones(2))
    # a goal env's dict observation travels in msgpack, its arrays by value
    goal_obs = {"observation": obs, "desired_goal": np.ones(3)}
    o = unpack(pack_step_reply([goal_obs, 0.0, False, False, {}]))["result"][0]
    assert set(o) == set(goal_obs) and all(np.array_equal(o[k], goal_obs[k]) for k in goal_obs)
    # an info key msgpack refuses (a tuple): the general frame, the key as its str, as for every other reply
    reply = unpack(pack_step_reply([obs, 1.0, False, False, {(1, 2): "t"}]))
    assert reply["result"][4] == {"(1, 2)": "t"} and reply["result"][1] == 1.0


def test_a_step_reply_read_into_place_matches_unpack_and_writes_nothing_it_cannot_take() -> None:
    """``unpack_step_reply_into`` (the vector env's way in) gives what ``unpack`` gives, the observation's bytes in
    the caller's buffer; an observation of another dtype, shape or encoding leaves the buffer untouched (None)."""
    obs = np.arange(6, dtype=np.float32).reshape(2, 3)
    info = {"env_id": "x", "final_obs": np.ones(2)}
    frame = memoryview(pack_step_reply([obs, 2.5, True, False, info]))
    out = np.full((2, 3), -1, np.float32)
    reward, terminated, truncated, got = unpack_step_reply_into(
        frame, memoryview(out).cast("B"), array_head(obs.dtype, obs.shape)
    )
    _, *rest = unpack(frame)["result"]
    assert np.array_equal(out, obs) and [reward, terminated, truncated] == rest[:3]
    assert got.keys() == rest[3].keys() and np.array_equal(got["final_obs"], np.ones(2))
    untouched = np.full(6, -1, np.float64)
    for head, dest in [
        (array_head(np.dtype(np.float64), (2, 3)), memoryview(untouched).cast("B")),  # the env sent float32
        (array_head(obs.dtype, (3, 2)), memoryview(out).cast("B")),  # another shape, the same size
        (array_head(obs.dtype, (2, 3)), memoryview(out).cast("B")[:12]),  # a buffer of another size
    ]:
        assert unpack_step_reply_into(frame, dest, head) is None
    assert (untouched == -1).all()
    goal = pack_step_reply([{"observation": np.zeros(3)}, 0.0, False, False, {}])  # a dict travels in msgpack
    assert unpack_step_reply_into(goal, memoryview(out).cast("B"), array_head(obs.dtype, obs.shape)) is None
    assert unpack_step_reply_into(pack({"ok": True, "result": None}), memoryview(out).cast("B"), b"") is None
    with pytest.raises(CodecError, match="info must be a map, got list"):
        bad = pack_step_reply([obs, 0.0, False, False, {}])[:-1] + b"\x90"  # the info: an empty list
        unpack_step_reply_into(bad, memoryview(out).cast("B"), array_head(obs.dtype, obs.shape))
    assert np.array_equal(out, obs)


_REQ = bytes([STEP_TAG, 1])  # a request's tag and kind; then mode, encoding, and 8 bytes of reference time
_ARRAY_HEAD = array_bytes(np.zeros(4, np.float32))[:-16]  # the header of a 4-float array, without its data


@pytest.mark.parametrize(
    ("frame", "what"),
    [
        (_REQ + bytes([0]), "header alone is 12"),
        (_REQ + bytes([9, 0]) + bytes(8), "autoreset mode 9"),
        (bytes([STEP_TAG, 5, 0, 0]) + bytes(12), "kind 5"),
        (_REQ + bytes([1, 7]) + bytes(8), "encoding 7"),
        (_REQ + bytes([1, 0]) + bytes(8) + b"\x92\x01", "incomplete input"),
        (_REQ + bytes([1, 1]) + bytes(8) + _ARRAY_HEAD + bytes(3), "needs 16 bytes, got 3"),
        (bytes([STEP_TAG, 2, 0, 0, 1, 0, 0, 0]) + bytes(8) + b"\xc0\x91\x01", "info must be a map, got list"),
        (bytes([STEP_TAG, 2, 0, 1, 99, 0, 0, 0]) + bytes(8) + _ARRAY_HEAD, "its array ends at 115"),
        (_REQ + bytes([1, 1]) + bytes(8) + b"\x03<f4\x05" + bytes(8), "5 dimensions ends at byte 57"),
        (_REQ + bytes([1, 1]) + bytes(8) + b"\x06(2)f4,\x00" + bytes(8), "not a dtype string"),
        (_REQ + bytes([1, 1]) + bytes(8) + b"\x02|O\x01" + struct.pack("<q", 1) + bytes(8), "object arrays"),
        (_REQ + bytes([1, 1]) + bytes(8) + b"\x03<f4\x02" + struct.pack("<2q", -1, -4) + bytes(16), "negative"),
    ],
    ids=[
        "truncated",
        "mode",
        "kind",
        "encoding",
        "action",
        "array",
        "info",
        "obs past the end",
        "ndim past the end",
        "dtype literal",
        "object dtype",
        "negative shape",
    ],
)
def test_malformed_step_frames_are_refused_by_name(frame: bytes, what: str) -> None:
    with pytest.raises(CodecError, match=f"malformed step frame.*{what}"):
        unpack(frame)


def test_a_step_request_with_an_unknown_autoreset_mode_is_refused_before_packing() -> None:
    with pytest.raises(ValueError, match="autoreset must be one of.*'sometimes'"):
        pack_step_request(1, "sometimes", None)


def test_packing_from_several_threads_at_once_keeps_each_message_whole() -> None:
    """The Packer is kept per thread: the ``default`` hook (every array) lets another thread run in the middle of a
    pack, which with one shared Packer would mix two messages' bytes."""
    import threading

    bad: list[str] = []

    def work(k: int) -> None:
        for i in range(300):
            msg = {"op": "step", "action": np.full(k + 1, i, np.float32), "obs": [np.arange(k + i % 5)] * 3}
            back = unpack(pack(msg))
            if not (np.array_equal(back["action"], msg["action"]) and len(back["obs"][2]) == k + i % 5):
                bad.append(f"thread {k} message {i}")

    threads = [threading.Thread(target=work, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert not bad, bad[:3]
