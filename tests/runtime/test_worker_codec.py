"""The worker protocol's frames (runtime/worker.py ``pack``/``unpack``): arrays by value whatever their layout,
numpy scalars as Python ones, malformed frames refused by name. No processes: the codec alone."""

from __future__ import annotations

import numpy as np
import pytest

from uniros_async.errors import CodecError
from uniros_async.runtime.worker import pack, unpack


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
    msg = unpack(pack({"r": np.float32(0.5), "n": np.int64(3), "o": np.array([1, "x"], dtype=object), (1, 2): "t"}))
    assert msg["r"] == 0.5 and type(msg["r"]) is float and msg["n"] == 3 and type(msg["n"]) is int
    assert msg["o"] == [1, "x"]
    assert msg["(1, 2)"] == "t"  # a tuple key comes back as its str


def test_malformed_frames_are_refused_by_name() -> None:
    with pytest.raises(CodecError, match="malformed worker frame"):
        unpack(b"\xc1")
    with pytest.raises(CodecError, match="expected a map, got list"):
        unpack(pack({"x": 1})[:0] + b"\x91\x01")
