"""docs/performance.md's tables are what bench/report.py makes of the committed records, and the records are the
ones the docs cite.

A table edited by hand, or a record replaced without ``uniros bench report write``, fails here.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from uniros_async.bench import report
from uniros_async.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]
RECORDS = ROOT / "benchmarks" / "results"


def test_performance_md_tables_match_the_committed_records() -> None:
    doc = report.DOC.read_text()
    assert doc.count("<!-- table: ") >= 10
    assert report.stale(doc) == []
    assert report.render(doc) == doc


def test_a_changed_figure_makes_its_table_stale(tmp_path: Path) -> None:
    doc = report.DOC.read_text()
    results = tmp_path / "results"
    results.mkdir()
    for f in RECORDS.glob("*.json"):
        (results / f.name).write_bytes(f.read_bytes())
    rec = json.loads((results / "timers.json").read_text())
    rec["rows"][0]["median_ms"] += 1.0
    (results / "timers.json").write_text(json.dumps(rec))
    assert report.stale(doc, results) == ["timers.json timers"]
    assert report.stale(report.render(doc, results), results) == []


def test_record_wraps_a_bench_output_with_its_command_host_and_date(tmp_path: Path) -> None:
    src = tmp_path / "out.json"
    src.write_text(json.dumps([{"impl": "uniros WallClock", "rate_hz": 10.0, "median_ms": 0.004, "p99_ms": 0.07,
                                "max_ms": 1.0, "count": 600, "overruns": 0}]))  # fmt: skip
    dest = report.record(src, tmp_path / "timers.json", command="uniros bench timers")
    rec = report.load_record(dest)
    assert rec.command == "uniros bench timers"
    assert re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d UTC", rec.date)
    assert "-core" in rec.host and "Python" in rec.host
    doc = "<!-- table: timers.json timers -->\n<!-- end table -->\n"
    table = report.render(doc, tmp_path)
    assert "| uniros WallClock | 10 | 0.0040 | 0.070 | 1.000 | 600 | 0 |" in table


def test_bad_records_and_fences_say_what_was_expected(tmp_path: Path) -> None:
    (tmp_path / "bare.json").write_text("[]")
    with pytest.raises(ConfigError, match="expected a record"):
        report.load_record(tmp_path / "bare.json")
    (tmp_path / "partial.json").write_text('{"rows": []}')
    with pytest.raises(ConfigError, match="lacks command, host, date"):
        report.load_record(tmp_path / "partial.json")
    with pytest.raises(ConfigError, match="cannot read the record"):
        report.load_record(tmp_path / "missing.json")
    (tmp_path / "t.json").write_text('{"rows": [{"impl": "x"}], "command": "c", "host": "h", "date": "d"}')
    with pytest.raises(ConfigError, match="unknown table kind 'nope'.*expected one of"):
        report.render("<!-- table: t.json nope -->\n<!-- end table -->", tmp_path)
    with pytest.raises(ConfigError, match="no row of t.json matches"):
        report.render("<!-- table: t.json timers impl=y -->\n<!-- end table -->", tmp_path)


def test_every_record_is_cited_by_the_docs() -> None:
    records = sorted(p.name for p in RECORDS.iterdir())
    assert 0 < len(records) <= 40
    docs = "".join(p.read_text() for p in [*ROOT.glob("docs/**/*.md"), ROOT / "benchmarks" / "README.md"])
    uncited = [name for name in records if name not in docs]
    assert uncited == [], f"records no doc cites: {uncited}"


@pytest.mark.slow
def test_cli_check_exits_0_on_the_committed_doc() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "uniros_async.cli", "bench", "report", "check"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
