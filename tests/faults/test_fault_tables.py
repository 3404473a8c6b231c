"""``rig.fault_tables``: docs/reliability.md's fault tables from a fault report (no fault is injected here)."""

from __future__ import annotations

import json
from pathlib import Path

from rig.fault_tables import load, summary, tables


def _line(fault: str, link: str, duration_s: float, recovery_s: float, **extra: object) -> dict[str, object]:
    row: dict[str, object] = {
        "fault": fault, "link": link, "duration_s": duration_s, "hold_after_fault_s": 0.637,
        "hold_after_last_command_s": 0.6, "hold_ticks_after_last_command": 6, "notice_after_fault_s": None,
        "agent_loop_late_s": 0.0, "robot_errors": 2, "recovery_after_clear_s": recovery_s,
        "stale_commands_applied": 0, "stale_commands_dropped": 1, "max_state_stamp_age_at_step_s": 0.406,
        "uncaught_exceptions": 0,
    }  # fmt: skip
    row.update(extra)
    return row


def test_one_section_per_fault_in_order_with_the_last_line_of_a_rerun(tmp_path: Path) -> None:
    report = tmp_path / "faults.jsonl"
    lines = [
        _line("tcp reset", "ros1", 5, 0.5, new_process_sees_arm=True, new_process_first_state_s=0.21),
        _line("partition", "tcp", 30, 9.9, new_process_sees_arm=True, new_process_first_state_s=0.05),
        _line("partition", "tcp", 30, 1.2, new_process_sees_arm=True, new_process_first_state_s=0.08),  # the rerun
        _line("partition", "tcp", 0.5, 0.19, new_process_sees_arm=False, new_process_first_state_s=None),
    ]
    report.write_text("".join(json.dumps(r) + "\n" for r in lines))
    runs = load(report)
    text = tables(runs)
    assert text.index("### partition") < text.index("### tcp reset")
    rows = [line for line in text.splitlines() if line.startswith("| tcp") or line.startswith("| ROS 1")]
    assert rows == [
        "| tcp (`uniros robot serve`) | 0.5 | 0.64 | 0.60 / 6 | - | 0.00 | 2 | 0.19 | no / - | 0.41 | 0 / 1 | 0 |",
        "| tcp (`uniros robot serve`) | 30 | 0.64 | 0.60 / 6 | - | 0.00 | 2 | 1.20 | yes / 0.08 | 0.41 | 0 / 1 | 0 |",
        "| ROS 1 (rosmaster, driver, bridge) | 5 | 0.64 | 0.60 / 6 | - | 0.00 | 2 | 0.50 | yes / 0.21 | 0.41 "
        "| no stamp; see below | 0 |",
    ]
    said = summary(runs)
    assert "over the 3 fault runs (2 faults on their links" in said and "the largest 1.20 s" in said
    assert "saw the arm after 2 of them" in said and "within 0.21 s" in said
