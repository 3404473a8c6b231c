"""``uniros bench cameras``: its arguments and its table (the run itself: docs/performance.md's command)."""

from __future__ import annotations

import pytest

from uniros_async.bench.cameras import CameraBenchConfig, format_table, meets_goal, parse_sizes
from uniros_async.errors import ConfigError


def test_sizes_parse_and_bad_ones_are_named() -> None:
    assert parse_sizes(["none", "84x84", "640x480"]) == ((0, 0), (84, 84), (640, 480))
    with pytest.raises(ConfigError, match=r"expected WxH .* got '84'"):
        parse_sizes(["84"])
    with pytest.raises(ConfigError, match="8..1024"):
        CameraBenchConfig(sizes=((4, 4),))
    with pytest.raises(ConfigError, match="duration_s"):
        CameraBenchConfig(duration_s=0)


def test_the_table_says_which_rows_meet_the_loop_goal() -> None:
    base = {"scenario": "cameras", "period_ms": 100.0, "actuator_p99_ms": 100.9, "actuator_max_ms": 101.2}
    rows = [
        {**base, "camera": "none", "env": "rx200 sim", "actuator_median_ms": 100.0, "actuator_iqr_ms": 0.01},
        {
            **base,
            "camera": "84x84",
            "env": "rx200 sim",
            "actuator_median_ms": 100.0,
            "actuator_iqr_ms": 0.7,
            "frames": 900,
            "skipped": 3,
            "render_median_ms": 3.1,
            "frame_age_median_ms": 20.5,
        },
    ]
    for r in rows:
        r["goal_met"] = meets_goal(r["actuator_median_ms"], r["actuator_iqr_ms"], r["period_ms"])
    assert not meets_goal(100.2, 0.01, 100.0) and not meets_goal(40.0, 0.5, 40.0) and meets_goal(40.05, 0.49, 40.0)
    table = format_table(rows, CameraBenchConfig(duration_s=30)).splitlines()
    none_line = next(line for line in table if line.startswith("none"))
    cam_line = next(line for line in table if line.startswith("84x84"))
    assert none_line.endswith("met") and cam_line.endswith("MISSED")
    assert "900" in cam_line and "3.10" in cam_line and "20.5" in cam_line
