"""Messages of every type for the bag tests, and a field-by-field comparison (imported as ``_bag_messages``)."""

from __future__ import annotations

from typing import Any

import numpy as np

from uniros_async.bus import messages as m


def one_of_each(i: int) -> list[tuple[str, Any]]:
    """A message of every type in bus/messages.py, its values depending on ``i``, on a topic of its own."""
    rng = np.random.default_rng(i)
    h = m.Header(stamp_ns=1_700_000_000_000_000_000 + i * 1_000_003, frame_id=f"frame{i}")
    n = 3 + i % 4
    return [
        ("/h", h),
        (
            "/rx200/joint_states",
            m.JointState(
                header=h,
                name=tuple(f"j{k}" for k in range(n)),
                position=rng.normal(size=n),
                velocity=rng.normal(size=n),
                effort=rng.normal(size=n),
            ),
        ),
        (
            "/rx200/command",
            m.JointCommand(header=h, position=rng.normal(size=n), velocity=rng.normal(size=n), duration_s=0.1 * i),
        ),
        ("/rx200/goal", m.Pose(header=h, position=rng.normal(size=3), orientation=rng.normal(size=4))),
        (
            "/rx200/marker",
            m.Marker(header=h, ns="goal", id=i, kind="line_strip", points=rng.normal(size=(4, 3)), color=[0, 1, 0, 1]),
        ),
        ("/camera/image", m.Image(header=h, data=rng.integers(0, 255, size=(48, 64, 3), dtype=np.uint8))),
        ("/blob", m.Blob(header=h, data=rng.integers(0, 255, size=100 + i, dtype=np.uint8))),
        ("/clock", m.ClockTick(sim_time_ns=i * 40_000_000)),
        ("/empty", m.Empty()),
        ("/trigger", m.Trigger(success=i % 2 == 0, message=f"done {i}")),
        ("/text", m.Text(data=f"text {i} é")),
        ("/data", m.Data(value={"i": i, "xs": [1.5, 2.5], "s": "x"})),
    ]


def assert_same(a: Any, b: Any) -> None:
    """``a`` and ``b`` are the same message: type, and every field (arrays by value, dtype and shape)."""
    assert type(a) is type(b)
    for spec in a.__uniros_schema__:
        x, y = getattr(a, spec.name), getattr(b, spec.name)
        if spec.kind == "array":
            assert x is None and y is None or (x.dtype == y.dtype and np.array_equal(x, y)), spec.name
        elif spec.kind == "message":
            assert_same(x, y)
        else:
            assert x == y, (spec.name, x, y)
