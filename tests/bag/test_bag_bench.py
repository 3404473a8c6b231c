"""``uniros bench bag`` end to end, short and small: four real-time envs, their arms' sims, a camera and the
recorder as real processes; the bag reads back equal to what the recorder received (the figures themselves come
from the full run, docs/howto/record-and-view.md)."""

from __future__ import annotations

from pathlib import Path

import pytest

from uniros_async.bench.bag import BagBenchConfig, main
from uniros_async.errors import ConfigError

pytestmark = pytest.mark.slow


def test_a_short_run_reads_back_equal(tmp_path: Path) -> None:
    lines: list[str] = []
    out = tmp_path / "b.mcap"
    records = main(BagBenchConfig(duration_s=3.0, baseline_s=0.0, width=64, height=48, out=str(out)), log=lines.append)
    *envs, bag = records
    assert [r["env"] for r in envs] == ["rx200 sim", "rx200 emulated-real", "ned2 sim", "ned2 emulated-real"]
    assert all(r["bag"] == "recording" and r["ticks"] > 10 for r in envs)
    assert bag["read_back_equal"] and bag["frames_equal"] and bag["dropped"] == 0
    assert bag["camera_recorded"] >= 30 and bag["written"] > bag["camera_recorded"] and bag["file_mb"] > 0
    assert not out.exists()  # removed after reading back unless keep=True
    table = "\n".join(lines)
    assert "read back equal to what the recorder received: yes" in table and "rx200 emulated-real" in table


def test_bad_settings_are_named() -> None:
    with pytest.raises(ConfigError, match="bench bag"):
        BagBenchConfig(duration_s=0)
