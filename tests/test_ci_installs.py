"""Every external command the suite runs is installed by ``.ci/run`` on a fresh machine.

The test reads the suite's sources (tests/ and the test rig the tests import) for the programs they start: the first
element of an argv given to subprocess or to the rig's ``_run``/``popen`` helpers, the program after ``ip netns
exec NS`` and after ``unshare ... --``, and every ``shutil.which("...")``. Each one must have its Debian package in
``COMMAND_PACKAGES``, and ``.ci/run`` must list that package in ``system_pkgs``. A new command in a test without
its package in both places fails here, not on the next fresh machine.
"""

from __future__ import annotations

import ast
import re
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# The Debian package of every program the suite starts.
COMMAND_PACKAGES = {
    "ip": "iproute2",
    "tc": "iproute2",
    "nft": "nftables",
    "unshare": "util-linux",
    "openssl": "openssl",
    "pgrep": "procps",
    "rosmaster": "python3-rosmaster",
    "python3": "python3-rospy",  # the system python3 that runs the rospy peers (/usr/bin/python3)
    "chromium": "chromium",  # the headless browser that photographs the live view (tests/view)
}
# Started through a helper that resolves the path at run time, so the scan below cannot see the literal name.
CALLED_THROUGH_HELPERS = {
    "rosmaster": "uniros_async.bench.ros1_peers.rosmaster_bin",
    "python3": "ros1 peers",
    "chromium": "uniros_async.view.screenshot.headless_chromium",
}
# Programs every Debian machine and this Python environment have: the essential set and our own console script.
ALWAYS_THERE = {"uniros", "sh", "bash", "true", "sleep", "kill"}

# Calls whose first positional argument (a list, or the leading strings) is an argv.
_ARGV_CALLS = {"run", "Popen", "check_output", "check_call", "create_subprocess_exec", "_run"}


def _sources() -> Iterator[Path]:
    yield from sorted((ROOT / "tests").rglob("*.py"))  # the tests and their rig (tests/rig)
    yield from sorted((ROOT / "uniros_async" / "testing").rglob("*.py"))  # the helpers users call too
    yield from sorted((ROOT / "uniros_async" / "bench").glob("ros*_peers.py"))  # the ROS peers tests share


def _strings(nodes: list[ast.expr]) -> list[str | None]:
    return [n.value if isinstance(n, ast.Constant) and isinstance(n.value, str) else None for n in nodes]


def _programs(argv: list[str | None]) -> Iterator[str]:
    if argv and argv[0]:
        yield argv[0]
    if argv[:3] == ["ip", "netns", "exec"] and len(argv) > 4 and argv[4]:
        yield argv[4]
    if argv and argv[0] == "unshare" and "--" in argv:
        after = argv.index("--") + 1
        if after < len(argv) and argv[after]:
            yield argv[after]


def called_programs() -> dict[str, set[str]]:
    """Each program the suite starts, with the files that start it."""
    found: dict[str, set[str]] = {}
    for path in _sources():
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if not isinstance(node, ast.Call):
                continue
            name = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            progs: list[str] = []
            if name == "which" and node.args:
                progs = [s for s in _strings(node.args[:1]) if s]
            elif name == "popen" and len(node.args) >= 2 and isinstance(node.args[1], ast.List):
                progs = list(_programs(_strings(list(node.args[1].elts))))  # NetnsPair.popen(namespace, argv)
            elif name in _ARGV_CALLS and node.args:
                first = node.args[0]
                argv = _strings(list(first.elts)) if isinstance(first, ast.List) else _strings(node.args)
                progs = list(_programs(argv))
            for prog in progs:
                if re.fullmatch(r"[a-z][a-z0-9_.+-]*", prog):
                    found.setdefault(prog, set()).add(str(path.relative_to(ROOT)))
    return found


def ci_packages() -> set[str]:
    text = (ROOT / ".ci" / "run").read_text()
    match = re.search(r'^system_pkgs="([^"]*)"', text, flags=re.M)
    assert match, '.ci/run has no system_pkgs="..." list of the Debian packages it installs'
    return set(match.group(1).split())


def test_the_scan_finds_the_programs_the_fault_tests_run() -> None:
    """The scan itself works: the namespaces' ``ip``, the rules' ``nft`` and ``unshare`` are found in the rig."""
    found = called_programs()
    assert {"ip", "nft", "unshare"} <= set(found), sorted(found)


def test_every_program_the_suite_runs_has_a_package() -> None:
    unknown = {
        prog: sorted(files)
        for prog, files in called_programs().items()
        if prog not in COMMAND_PACKAGES and prog not in ALWAYS_THERE
    }
    assert not unknown, (
        f"the tests start programs with no Debian package in COMMAND_PACKAGES: {unknown}; add each with its "
        "package here and to system_pkgs in .ci/run"
    )


def test_ci_installs_every_package_the_suite_needs() -> None:
    needed = set(COMMAND_PACKAGES.values())
    missing = sorted(needed - ci_packages())
    assert not missing, f".ci/run does not install {missing}: add them to its system_pkgs"


def test_the_helper_called_programs_are_still_called() -> None:
    """The programs listed as started through helpers are still named in the rig, so the table cannot go stale."""
    rig = "\n".join(p.read_text() for p in _sources())
    for prog in CALLED_THROUGH_HELPERS:
        assert prog in rig, f"{prog} is no longer named by the test rig: drop it from CALLED_THROUGH_HELPERS"
