"""A pytest plugin: the failure of every test's attempt that pytest-rerunfailures ran again, printed at the end of the
run with how the rerun ended.

A rerun's first failure is otherwise lost: the JUnit report keeps only the last attempt, and on the suite's xdist
workers the attempt's output is not shown. The workers send every report to the controller (``rerun`` among the
outcomes), which keeps the last lines of each failure and prints them in a section of the terminal summary, so that a
test that fails now and then leaves its reason in the CI log."""

from __future__ import annotations

import pytest

TAIL_LINES = 40
"""How many of a failure's last lines are kept: the assertion and the frames nearest to it."""

SECTION = "failed attempts that were run again"

_reruns: list[tuple[str, str, str]] = []  # (node id, phase, the failure's last lines)
_final: dict[str, str] = {}  # node id -> the outcome of its last attempt's call (or of a failed setup or teardown)


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if report.outcome == "rerun":  # type: ignore[comparison-overlap]  # pytest-rerunfailures' outcome
        lines = report.longreprtext.splitlines()
        _reruns.append((report.nodeid, report.when or "", "\n".join(lines[-TAIL_LINES:])))
    elif report.when == "call" or report.failed:
        _final[report.nodeid] = report.outcome


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    if not _reruns:
        return
    terminalreporter.section(SECTION)
    for nodeid, when, text in _reruns:
        then = {"passed": "passed", "failed": "failed again"}.get(_final.get(nodeid, ""), "did not finish")
        terminalreporter.write_line(f"--- {nodeid} ({when}), its failed attempt (its rerun {then}):")
        terminalreporter.write_line(text)
