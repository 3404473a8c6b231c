"""The tables of docs/performance.md, generated from the benches' JSON records in benchmarks/results.

A record is what a bench's ``--json`` wrote, wrapped with the run's facts by ``record``::

    {"command": "uniros bench timers --duration 60", "host": "2-core x86_64 VM, ...", "date": "2026-11-22 20:48 UTC",
     "rows": [...the bench's rows...]}

In the doc, a table is fenced by two comments that name its records, the kind of table made from their rows and,
optionally, which rows (``KEY=VALUE``: a row's KEY is VALUE)::

    <!-- table: timers.json timers -->
    ...generated: each record's date, host and command, then the table...
    <!-- end table -->

``render`` fills every fenced table from its record, ``stale`` lists the ones that differ from what is in the doc
(tests/bench/test_report.py runs it on the committed doc, so a table edited by hand or a record replaced without
regenerating fails). Commands::

    python -m uniros_async.bench.report record OUT.json benchmarks/results/NAME.json --command "uniros bench ..."
    python -m uniros_async.bench.report write    # regenerate docs/performance.md's tables in place
    python -m uniros_async.bench.report check    # exit 1 naming each stale table

(``uniros bench report ...`` is the same.)
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import os
import platform
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from uniros_async.errors import ConfigError

__all__ = ["KINDS", "Record", "load_record", "main", "record", "render", "stale"]

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "performance.md"
RESULTS = ROOT / "benchmarks" / "results"

_FENCE = re.compile(r"<!-- table: (?P<spec>[^\n]*?) -->\n(?P<body>.*?)<!-- end table -->", re.DOTALL)

Row = dict[str, Any]


@dataclasses.dataclass(frozen=True, kw_only=True)
class Record:
    """One bench run: its rows and how and where it ran."""

    rows: list[Row]
    command: str
    host: str
    date: str


def load_record(path: Path) -> Record:
    """Read a record (the wrapped form ``record`` writes).

    Raises:
        ConfigError: the file is missing, not JSON, or lacks rows, command, host or date (each named).
    """
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise ConfigError(f"cannot read the record {path}: {exc.strerror}") from exc
    except ValueError as exc:
        raise ConfigError(f"{path} is not JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a record {{command, host, date, rows}}, got a bare {type(data).__name__}")
    missing = [k for k in ("rows", "command", "host", "date") if k not in data]
    if missing:
        raise ConfigError(f"{path}: the record lacks {', '.join(missing)}")
    return Record(rows=list(data["rows"]), command=str(data["command"]), host=str(data["host"]), date=str(data["date"]))


def host_facts() -> str:
    """This machine as a record names it: cores, architecture, memory, Python, MuJoCo and kernel."""
    try:
        mem_gib = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
        mem = f", {mem_gib:.0f} GiB"
    except (ValueError, OSError):
        mem = ""
    try:
        import mujoco

        mj = f", mujoco {mujoco.__version__}"
    except ImportError:
        mj = ""
    py = platform.python_version()
    return f"{os.cpu_count()}-core {platform.machine()}{mem}, Python {py}{mj}, Linux {platform.release()}"


def record(src: Path, dest: Path, *, command: str, host: str | None = None, date: str | None = None) -> Path:
    """Wrap a bench's ``--json`` output as a record: its rows with the command, this host and the run's date (the
    file's modification time, UTC, unless given).

    Raises:
        ConfigError: ``src`` is not a list of rows.
    """
    try:
        rows = json.loads(src.read_text())
    except (OSError, ValueError) as exc:
        raise ConfigError(f"cannot read the bench output {src}: {exc}") from exc
    if isinstance(rows, dict) and "rows" in rows:
        rows = rows["rows"]
    if not isinstance(rows, list):
        raise ConfigError(f"{src}: expected the list of rows a bench's --json writes, got {type(rows).__name__}")
    when = date or dt.datetime.fromtimestamp(src.stat().st_mtime, dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    out = {"command": command, "host": host or host_facts(), "date": when, "rows": rows}
    dest.write_text(json.dumps(out, indent=1) + "\n")
    return dest


def _f(value: Any, digits: int = 1) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:,.{digits}f}"
    return str(value)


def _table(header: Sequence[str], rows: Sequence[Sequence[str]], right_from: int = 1) -> list[str]:
    align = ["---" if i < right_from else "---:" for i in range(len(header))]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(align) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return lines


def _metric(rows: list[Row], env: str, learner: str, metric: str) -> Row | None:
    for r in rows:
        if r["env"] == env and r["learner"] == learner and r["metric"] == metric:
            return r
    return None


def _keys(rows: list[Row], *names: str) -> list[tuple[Any, ...]]:
    seen: dict[tuple[Any, ...], None] = {}
    for r in rows:
        seen.setdefault(tuple(r.get(n) for n in names), None)
    return list(seen)


def _label(row: Row, key: str, rows: list[Row]) -> str:
    """``row[key]``, and the record it came from when the rows come from several."""
    many = len({r.get("_record") for r in rows}) > 1
    return f"{row[key]} ({row['_record']})" if many else str(row[key])


def _latency(rows: list[Row]) -> list[str]:
    """Per env and learner: actuator cycle, action cycle, observation age and action latency (ms)."""
    out = []
    for rec, env, learner in _keys(rows, "_record", "env", "learner"):
        part = [r for r in rows if r.get("_record") == rec]
        cells = [env, _label({"learner": learner, "_record": rec}, "learner", rows)]
        for metric, fields in (
            ("actuator_cycle", ("median_ms", "iqr_ms", "max_ms")),
            ("action_cycle", ("median_ms", "iqr_ms")),
            ("observation_age", ("median_ms",)),
            ("action_latency", ("median_ms",)),
        ):
            m = _metric(part, env, learner, metric)
            cells.append(" / ".join(_f(m[f], 3) if m and m["count"] else "-" for f in fields))
        out.append(cells)
    header = [
        "env",
        "learner",
        "actuator cycle median / IQR / max",
        "action cycle median / IQR",
        "observation age median",
        "action latency median",
    ]
    return _table(header, out, right_from=2)


def _action_cycle(rows: list[Row]) -> list[str]:
    """The action cycle's IQR (ms) per arm, a row per setting and a column per path: learners labelled
    ``"PATH, SETTING"`` (e.g. ``"eval process (rt), training ranked higher"``)."""
    labels = [learner for (learner,) in _keys(rows, "learner")]
    paths = list(dict.fromkeys(label.rsplit(", ", 1)[0] for label in labels))
    settings = list(dict.fromkeys(label.rsplit(", ", 1)[-1] for label in labels))
    envs = [e for (e,) in _keys(rows, "env")]
    out = []
    for setting in settings:
        cells = [setting]
        for path in paths:
            ms = [_metric(rows, e, f"{path}, {setting}", "action_cycle") for e in envs]
            cells.append(", ".join(_f(m["iqr_ms"], 2) if m and m["count"] else "-" for m in ms))
        out.append(cells)
    return _table(["setting", *[f"{path}: IQR per arm" for path in paths]], out)


def _actuator_by_load(rows: list[Row]) -> list[str]:
    """Per load and scheduling class (the learner's label): each env's actuator-cycle p99 / max (ms)."""
    envs = [e for (e,) in _keys(rows, "env")]
    out = []
    for (learner,) in _keys(rows, "learner"):
        cells = [learner]
        for env in envs:
            m = _metric(rows, env, learner, "actuator_cycle")
            cells.append(f"{_f(m['p99_ms'], 2)} / {_f(m['max_ms'], 2)}" if m else "-")
        out.append(cells)
    return _table(["learner, load, class", *[f"{e}: p99 / max" for e in envs]], out)


def _transport(rows: list[Row]) -> list[str]:
    """Per transport: round-trip p50 and one-way messages/s at each payload."""
    payloads = [p for (p,) in _keys(rows, "payload")]
    out = []
    for (name,) in _keys(rows, "transport"):
        by = {r["payload"]: r for r in rows if r["transport"] == name}
        p50 = [_f(by[p]["rtt_p50_us"]) if p in by else "-" for p in payloads]
        rate = [_f(by[p]["throughput_msg_s"], 0) if p in by else "-" for p in payloads]
        out.append([name, *p50, *rate])
    header = ["transport", *[f"{p} rtt p50 us" for p in payloads], *[f"{p} msgs/s" for p in payloads]]
    return _table(header, out)


def _timers(rows: list[Row]) -> list[str]:
    """Fire-time error per timer and rate (ms)."""
    out = [
        [
            r["impl"],
            _f(r["rate_hz"], 0),
            _f(r["median_ms"], 4),
            _f(r["p99_ms"], 3),
            _f(r["max_ms"], 3),
            _f(r["count"]),
            _f(r["overruns"]),
        ]
        for r in rows
    ]
    return _table(["timer", "Hz", "median ms", "p99 ms", "max ms", "fires", "overruns"], out)


def _simclock(rows: list[Row]) -> list[str]:
    """Speed of the accelerated sim against real time."""
    out = [[r["case"], _f(r["x_real_time"]), _f(r.get("wall_s"), 3)] for r in rows]
    return _table(["case", "x real time", "wall s"], out)


def _throughput(rows: list[Row]) -> list[str]:
    """Per env and N, a column per implementation: the overhead over the bare step (us, median) and the aggregate
    steps/s."""
    impls = [i for (i,) in _keys(rows, "impl")]
    out = []
    for env, n, turn in _keys(rows, "env", "n_envs", "envs_in_turn"):
        by = {r["impl"]: r for r in rows if (r["env"], r["n_envs"], r.get("envs_in_turn")) == (env, n, turn)}
        cells = [env.rsplit(":", 1)[-1], f"{n}{' in turn' if turn else ''}"]
        cells += [f"{_f(by[i]['overhead_us'])} us, {_f(by[i]['steps_per_s'], 0)}/s" if i in by else "-" for i in impls]
        out.append(cells)
    return _table(["env", "N", *impls], out, right_from=2)


def _throughput_repeat(rows: list[Row]) -> list[str]:
    """Per N, implementation and envs per worker: the share of the physics bound in each run."""
    out = []
    for n, impl, per in _keys(rows, "n_envs", "impl", "envs_per_worker"):
        pct = [r["bound_pct"] for r in rows if (r["n_envs"], r["impl"], r.get("envs_per_worker")) == (n, impl, per)]
        met = sum(p >= 90.0 for p in pct)
        out.append([_f(n), impl, _f(per), ", ".join(_f(p) for p in pct), f"{met} of {len(pct)}"])
    return _table(["N", "implementation", "envs per worker", "% of the bound, run by run", "runs >= 90 %"], out, 3)


def _roundtrip(rows: list[Row]) -> list[str]:
    """Round trips per client (us)."""
    out = [
        [_label(r, "client", rows), _f(r["p50_us"]), _f(r["p90_us"]), _f(r["p99_us"]), _f(r["count"]), _f(r["lost"])]
        for r in rows
    ]
    return _table(["client", "p50 us", "p90 us", "p99 us", "count", "lost"], out)


KINDS: dict[str, Callable[[list[Row]], list[str]]] = {
    "latency": _latency,
    "action_cycle": _action_cycle,
    "actuator_by_load": _actuator_by_load,
    "transport": _transport,
    "timers": _timers,
    "simclock": _simclock,
    "throughput": _throughput,
    "throughput_repeat": _throughput_repeat,
    "roundtrip": _roundtrip,
}
"""Table kinds by name: each turns a record's rows into the lines of a markdown table."""


def _block(spec: str, results: Path) -> str:
    """The generated text of one fence: ``FILE[+FILE...] KIND [KEY=VALUE ...]`` (the rows of every file, those
    whose KEY is VALUE when filters are given, as one table of that kind)."""
    words = spec.split()
    if len(words) < 2:
        raise ConfigError(f"table fence {spec!r}: expected 'FILE[+FILE...] KIND [KEY=VALUE ...]'")
    files, kind, filters = words[0].split("+"), words[1], words[2:]
    if kind not in KINDS:
        raise ConfigError(f"unknown table kind {kind!r} in fence {spec!r}; expected one of {sorted(KINDS)}")
    wanted = dict(f.split("=", 1) for f in filters if "=" in f)
    lines, rows = [], []
    for file in files:
        rec = load_record(results / file)
        lines.append(f"`{rec.command}`: {rec.date}, {rec.host} (`benchmarks/results/{file}`).")
        stem = file.removesuffix(".json")
        rows += [{**r, "_record": stem} for r in rec.rows if all(str(r.get(k)) == v for k, v in wanted.items())]
    if not rows:
        raise ConfigError(f"table fence {spec!r}: no row of {', '.join(files)} matches {wanted}")
    if len(lines) > 1:  # one record per list item
        lines = [f"- {line}" for line in lines]
    return "\n".join([*lines, "", *KINDS[kind](rows)]) + "\n"


def render(doc: str, results: Path = RESULTS) -> str:
    """``doc`` with every fenced table regenerated from its records in ``results``.

    Raises:
        ConfigError: a record is missing or malformed, or a fence names an unknown kind or matches no row.
    """

    def fill(m: re.Match[str]) -> str:
        return f"<!-- table: {m['spec']} -->\n{_block(m['spec'], results)}<!-- end table -->"

    return _FENCE.sub(fill, doc)


def stale(doc: str, results: Path = RESULTS) -> list[str]:
    """The fences (their specs) whose table in ``doc`` differs from what ``render`` makes of their records."""
    return [m["spec"] for m in _FENCE.finditer(doc) if m["body"] != _block(m["spec"], results)]


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m uniros_async.bench.report write|check|record``; returns the exit code."""
    parser = argparse.ArgumentParser(prog="uniros bench report", description="docs/performance.md's tables")
    sub = parser.add_subparsers(dest="action", required=True)
    for name in ("write", "check"):
        p = sub.add_parser(name, help="regenerate the tables in place" if name == "write" else "list stale tables")
        p.add_argument("--doc", type=Path, default=DOC)
        p.add_argument("--results", type=Path, default=RESULTS)
    rp = sub.add_parser("record", help="wrap a bench's --json output with its command, host and date")
    rp.add_argument("src", type=Path)
    rp.add_argument("dest", type=Path)
    rp.add_argument("--command", required=True, help="the command that wrote SRC")
    rp.add_argument("--host", help="default: this machine's facts")
    rp.add_argument("--date", help="default: SRC's modification time, UTC")
    args = parser.parse_args(argv)
    try:
        if args.action == "record":
            print(record(args.src, args.dest, command=args.command, host=args.host, date=args.date))
            return 0
        text = args.doc.read_text()
        if args.action == "write":
            args.doc.write_text(render(text, args.results))
            return 0
        old = stale(text, args.results)
    except ConfigError as exc:
        print(f"uniros bench report: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"uniros bench report: cannot read or write {exc.filename}: {exc.strerror}", file=sys.stderr)
        return 2
    for name in old:
        print(f"{args.doc}: the table '{name}' is not what its records give (run: uniros bench report write)")
    return 1 if old else 0


if __name__ == "__main__":
    raise SystemExit(main())
