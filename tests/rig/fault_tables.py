"""docs/reliability.md's fault tables from a fault report (``UNIROS_FAULT_REPORT``: one JSON line per fault run, as
``tests/faults`` appends them), so that the tables show one run's figures and nothing else.

    UNIROS_FAULT_REPORT=faults.jsonl python -m pytest -q tests/faults/test_tcp_arm_faults.py \\
        tests/faults/test_ros1_arm_faults.py
    PYTHONPATH=tests python -m rig.fault_tables faults.jsonl     # the sections, then the recovery summary

Each fault gets a ``### name`` section with one row per link and duration, in the order of ``FAULT_ORDER``; a run
that is in the report twice (a rerun) keeps its last line.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

FAULT_ORDER = [
    "partition",
    "loss 1 %",
    "loss 10 %",
    "loss 50 %",
    "tcp reset",
    "starved link (tbf 8 kbit/s)",
    "link down",
    "frozen arm (SIGSTOP)",
    "arm output dropped",
    "arm address removed",
    "registry port blocked",
    "registry restarted",
]
"""The sections' order (``tests/faults/_faults.FAULTS``'s)."""

LINKS = {
    "tcp": "tcp (`uniros robot serve`)",
    "tcp (registry in its own process)": "tcp, registry in its own process",
    "ros1": "ROS 1 (rosmaster, driver, bridge)",
}
"""A report's ``link`` -> its name in the tables, in the rows' order."""

HEADER = (
    "| link | fault lasts (s) | arm holds after fault (s) | hold after last command (s / arm ticks) | agent notices "
    "after fault (s) | agent loop late (s) | RobotErrors | next good step after the link's return (s) | a new process "
    "sees the arm / its first state (s) | oldest state a step returned on (s) | stale commands applied / dropped | "
    "uncaught |"
)


def _s(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def _row(r: dict[str, Any]) -> str:
    hold = "-"
    if r.get("hold_after_last_command_s") is not None:
        hold = f"{r['hold_after_last_command_s']:.2f} / {r['hold_ticks_after_last_command']}"
    seen = "-"
    if "new_process_sees_arm" in r:
        seen = ("yes" if r["new_process_sees_arm"] else "no") + f" / {_s(r.get('new_process_first_state_s'))}"
    stale = f"{r['stale_commands_applied']} / {r['stale_commands_dropped']}"
    if r["link"] == "ros1":
        stale = "no stamp; see below"
    cells = [
        LINKS.get(r["link"], r["link"]),
        f"{r['duration_s']:g}",
        _s(r.get("hold_after_fault_s")),
        hold,
        _s(r.get("notice_after_fault_s")),
        _s(r.get("agent_loop_late_s")),
        str(r["robot_errors"]),
        _s(r["recovery_after_clear_s"]),
        seen,
        _s(r.get("max_state_stamp_age_at_step_s")),
        stale,
        str(r["uncaught_exceptions"]),
    ]
    return "| " + " | ".join(cells) + " |"


def load(path: Path) -> list[dict[str, Any]]:
    """The report's runs, one per (fault, link, duration): the last line of each."""
    runs: dict[tuple[str, str, float], dict[str, Any]] = {}
    for line in path.read_text().splitlines():
        if line.strip():
            r = json.loads(line)
            runs[(r["fault"], r["link"], float(r["duration_s"]))] = r
    return list(runs.values())


def tables(runs: list[dict[str, Any]]) -> str:
    """The ``### fault`` sections, each with its table."""
    order = {name: i for i, name in enumerate(LINKS)}
    out: list[str] = []
    for fault in FAULT_ORDER + sorted({r["fault"] for r in runs} - set(FAULT_ORDER)):
        rows = sorted(
            (r for r in runs if r["fault"] == fault), key=lambda r: (order.get(r["link"], 99), r["duration_s"])
        )
        if rows:
            out += [f"### {fault}", "", HEADER, "|" + "---|" * 12, *(_row(r) for r in rows), ""]
    return "\n".join(out)


def summary(runs: list[dict[str, Any]]) -> str:
    """The next good step after the link's return, per duration, and the new processes' first states."""
    faults_links = {(r["fault"], r["link"]) for r in runs}
    parts = []
    for d in sorted({r["duration_s"] for r in runs}):
        rec = [r["recovery_after_clear_s"] for r in runs if r["duration_s"] == d]
        parts.append(f"at {d:g} s {min(rec):.2f}-{max(rec):.2f} s (median {statistics.median(rec):.2f} s)")
    firsts = [r["new_process_first_state_s"] for r in runs if r.get("new_process_first_state_s") is not None]
    seen = sum(bool(r.get("new_process_sees_arm")) for r in runs)
    return (
        f"Next good step after the link's return, over the {len(runs)} fault runs ({len(faults_links)} faults on "
        f"their links, each at {len({r['duration_s'] for r in runs})} durations): {', '.join(parts)}; the largest "
        f"{max(r['recovery_after_clear_s'] for r in runs):.2f} s. A new process saw the arm after {seen} of them and "
        f"got its first joint state within {max(firsts):.2f} s."
    )


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("report", type=Path, help="the fault report (JSON lines)")
    args = parser.parse_args(argv)
    runs = load(args.report)
    if not runs:
        print(f"{args.report}: no fault runs", file=sys.stderr)
        return 1
    print(tables(runs))
    print(summary(runs))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
