"""``uniros bench latency``: the metrics, the scenarios (a few seconds each), the JSON schema and the errors.

The scenarios run real worker processes and real wall-clock env loops; they check plausibility (an actuator
cycle near the loop period), never performance: the figures are the benchmark's job (docs/performance.md).
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path
from typing import Any

import pytest

from uniros_async.bench import latency
from uniros_async.bench.looptiming import METRICS, Series, format_table, loop_metrics, since, to_records
from uniros_async.cli import main as cli_main
from uniros_async.errors import ConfigError

KEYS = {"scenario", "env", "learner", "metric", "median_ms", "iqr_ms", "p99_ms", "max_ms", "count"}
MS = 1_000_000


# ---------------------------------------------------------------------------------------------- metrics


def test_loop_metrics_skip_resets_silent_ticks_and_use_the_agents_receive_time() -> None:
    ticks = [i * 100 * MS for i in range(12)]
    commanded = [t for i, t in enumerate(ticks) if i not in (5,)]  # tick 5 sent nothing (e.g. an unsafe hold)
    commanded.append(ticks[7] + 3 * MS)  # a hold sent outside a tick is no actuator cycle
    snap: dict[str, Any] = {
        "tick_ns": ticks,
        "command_ns": sorted(commanded),
        # step 0 (after the initial reset) and step 2 (after the reset at step 1) end on the aligned grid
        "action_ns": [50 * MS, 1250 * MS, 1660 * MS, 2450 * MS, 3251 * MS],
        "step_ns": [1201 * MS, 1601 * MS, 2401 * MS, 3201 * MS],
        "observation_age_ns": [1 * MS, 1 * MS, 1 * MS, 1 * MS],
        "action_latency_ns": [50 * MS, 50 * MS],
        "step_overruns": 0,
    }
    m = loop_metrics(snap, reset_after={1}, recv_ns=[1202 * MS, 1603 * MS, 2401 * MS, 3210 * MS])
    assert m["actuator_cycle"] == [100.0] * 9  # 11 periods, minus the two around the silent tick 5
    # periods 0 -> 1 and 2 -> 3 are first steps (aligned), 1 -> 2 spans the reset: only 3 -> 4 is an action cycle
    assert m["action_cycle"] == [801.0]
    assert loop_metrics(snap)["action_cycle"] == [410.0, 790.0, 801.0]  # no resets after step 0
    assert m["observation_age"] == [2.0, 1.0, 10.0]  # step 1 ended an episode
    assert m["action_latency"] == [50.0, 50.0]
    assert loop_metrics(snap)["observation_age"] == [1.0] * 4  # no receive times: the env-side age


def test_since_cuts_an_earlier_snapshot_off() -> None:
    earlier = {"tick_ns": [1, 2], "action_ns": [], "step_overruns": 1}
    later = {"tick_ns": [1, 2, 3, 4], "action_ns": [5], "step_overruns": 3}
    assert since(later, earlier) == {"tick_ns": [3, 4], "action_ns": [5], "step_overruns": 2}


def test_records_and_table_name_every_metric_even_without_samples() -> None:
    s = Series(env="rx200 sim", learner="x", samples={"actuator_cycle": [100.0, 100.2]}, period_ms=100.0)
    records = to_records("single", [s])
    assert [r["metric"] for r in records] == list(METRICS)
    assert all(set(r) == KEYS for r in records)
    assert records[1]["median_ms"] is None and records[1]["count"] == 0
    json.dumps(records, allow_nan=False)  # valid JSON: no NaN
    assert "100 +- 0.1" in format_table([s], records)


# ---------------------------------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        ({"scenario": "nope"}, ["'nope'", "concurrent", "turn-based"]),
        ({"duration_s": 0.0}, ["duration_s", "0.0"]),
        ({"duration_s": float("nan")}, ["duration_s", "nan"]),
        ({"scenario": "sweep", "learners": ("sb3-td3",)}, ["'sweep'", "no learner"]),
        ({"scenario": "single", "learners": ("ppo",)}, ["'ppo'", "sb3-td3", "async-td3"]),
        ({"scenario": "single", "learners": ("sb3-td3", "sb3-td3")}, ["repeated"]),
        ({"think_ms": 900.0}, ["think_ms=900", "800 ms"]),
        ({"scenario": "sweep", "think_ms": 100.0}, ["think_ms=100", "100 ms"]),
        ({"action_cycle_s": -1.0}, ["action_cycle_s", "-1.0"]),
        ({"plot_path": "fig.bmp"}, ["fig.bmp", ".png"]),
        ({"learning_starts": 0}, ["learning_starts", "0"]),
        ({"loads": ("cpu", "disk")}, ["'disk'", "gil", "torch"]),
        ({"scenario": "sweep", "loads": ("cpu",)}, ["'sweep'", "learner scenario"]),
        ({"loads": ("gc",), "sched_classes": ("fifo",)}, ["'fifo'", "rt", "off"]),
        ({"backend": "k8s"}, ["'k8s'", "local", "ray"]),
        ({"scenario": "sweep", "backend": "ray"}, ["'sweep'", "--backend ray", "learner scenario"]),
        ({"backend": "ray", "loads": ("cpu",)}, ["--backend ray", "with --load"]),
    ],
)
def test_bad_settings_name_the_value_and_the_choices(kwargs: dict[str, Any], words: list[str]) -> None:
    with pytest.raises(ConfigError) as info:
        latency.LatencyBenchConfig(**kwargs)
    for w in words:
        assert w in str(info.value)


def test_cli_reports_bad_arguments_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["bench", "latency", "--scenario", "single", "--learner", "ppo", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "unknown learner(s) ['ppo']" in err and "async-td3" in err
    with pytest.raises(SystemExit) as exit_info:
        cli_main(["bench", "latency", "--scenario", "nope"])
    assert exit_info.value.code == 2
    assert "invalid choice: 'nope'" in capsys.readouterr().err


def test_a_missing_async_learner_is_refused_before_any_process_starts(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(latency, "async_td3_available", lambda: False)
    with pytest.raises(ConfigError, match="--learner sb3-td3"):
        latency.run(latency.LatencyBenchConfig(scenario="concurrent", duration_s=1.0, progress=False))


# ---------------------------------------------------------------------------------------------- loads


def _cpu_ticks(pid: int) -> int:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12])  # utime + stime


def test_cpu_load_spins_one_process_per_core_and_leaves_none() -> None:
    with latency.open_load("cpu") as stats:
        assert len(stats.spinners) == len(os.sched_getaffinity(0))
        before = [_cpu_ticks(pid) for pid in stats.spinners]
        deadline = time.monotonic() + 10
        while not all(_cpu_ticks(pid) > b for pid, b in zip(stats.spinners, before, strict=True)):
            assert time.monotonic() < deadline, "the spinners did not run"
            time.sleep(0.05)
    assert not [pid for pid in stats.spinners if Path(f"/proc/{pid}").exists()]  # killed and reaped


@pytest.mark.parametrize("kind", ["gil", "gc"])
def test_gil_and_gc_loads_hold_the_gil_in_stretches_and_stop(kind: str) -> None:
    import threading

    with latency.open_load(kind) as stats:
        deadline = time.monotonic() + 20
        while len(stats.stretches_ms) < 2:
            assert time.monotonic() < deadline, f"no {kind} stretch"
            time.sleep(0.01)
    assert not [t for t in threading.enumerate() if t.name == f"{kind} load"]
    assert min(stats.stretches_ms) > 0
    assert (stats.collections >= 2) == (kind == "gc")


@pytest.mark.parametrize("kind", ["cpu", "gil", "gc"])
def test_a_load_opened_by_the_real_time_acting_thread_runs_in_the_ordinary_class(kind: str) -> None:
    """The loads compete with the loops at normal priority, as a stranger's job or a learner would: never in the
    real-time class of the thread that starts them (SCHED_RESET_ON_FORK), even where that is the acting thread."""
    import threading

    from uniros_async.priority import RESET_ON_FORK, real_time_thread, thread_scheduling

    if os.geteuid() != 0:
        pytest.skip("SCHED_RR needs root or CAP_SYS_NICE; this machine's CI runs as root")
    me = threading.get_native_id()
    with real_time_thread() as rt, latency.open_load(kind) as stats:
        assert rt and thread_scheduling()[me][0] == os.SCHED_RR | RESET_ON_FORK
        if kind == "cpu":
            for pid in stats.spinners:
                assert set(thread_scheduling(pid).values()) == {(os.SCHED_OTHER, 0)}
                assert os.getpriority(os.PRIO_PROCESS, pid) == 0
        else:
            (load,) = [t for t in threading.enumerate() if t.name == f"{kind} load"]
            assert load.native_id is not None
            assert thread_scheduling()[load.native_id] == (os.SCHED_OTHER, 0)


@pytest.mark.slow
def test_load_run_prints_the_load_table(tmp_path: Path) -> None:
    out = tmp_path / "load.json"
    cfg = latency.LatencyBenchConfig(
        scenario="single",
        learners=("async-td3",),
        duration_s=3.0,
        learning_starts=2,
        loads=("gc",),
        sched_classes=("off",),
        json_path=str(out),
        progress=False,
    )
    lines: list[str] = []
    records = latency.main(cfg, log=lines.append)
    _check(records, out, "single", {"rx200 sim"}, {"async-td3 +gc off"})
    text = "\n".join(lines)
    assert "--load gc --sched off" in text and "actuator cycle (act.) and action cycle, ms, under load" in text
    load_table = text.split("under load", 1)[1]
    (row,) = [line for line in load_table.splitlines() if line.startswith("rx200 sim")]
    assert len(row.split()) == 2 + 3 + 5  # env, label, five figures (no goal verdict without the rt class)


# ---------------------------------------------------------------------------------------------- scenarios


def _check(records: list[dict[str, Any]], path: Path, scenario: str, envs: set[str], learners: set[str]) -> None:
    assert json.loads(path.read_text()) == records
    assert all(set(r) == KEYS and r["scenario"] == scenario for r in records)
    assert {r["env"] for r in records} == envs
    assert {r["learner"] for r in records} == learners
    assert {r["metric"] for r in records} == set(METRICS)
    for r in records:
        if r["metric"] == "action_cycle" or (r["metric"] == "actuator_cycle" and "turn-based" not in r["env"]):
            assert r["count"] >= 1, r


def _median(records: list[dict[str, Any]], env: str, metric: str, learner: str | None = None) -> float:
    (r,) = [r for r in records if r["env"] == env and r["metric"] == metric and learner in (None, r["learner"])]
    return float(r["median_ms"])


@pytest.mark.slow
def test_turn_based_scenario(tmp_path: Path) -> None:
    out, plot = tmp_path / "tb.json", tmp_path / "tb.png"
    cfg = latency.LatencyBenchConfig(
        scenario="turn-based",
        duration_s=3.2,
        json_path=str(out),
        plot_path=str(plot),
        progress=False,
        keep_cores_awake=False,
    )
    lines: list[str] = []
    records = latency.main(cfg, log=lines.append)
    assert "idle cores: allowed to halt (--allow-idle)" in "\n".join(lines)
    _check(records, out, "turn-based", {"rx200 sim real-time", "rx200 sim turn-based"}, {"scripted"})
    assert plot.stat().st_size > 10_000
    assert abs(_median(records, "rx200 sim real-time", "actuator_cycle") - 100.0) < 5.0
    # the turn-based env of a real arm: no loop (no actuator cycle), one command at once (no wait for a tick)
    tb = {r["metric"]: r for r in records if r["env"] == "rx200 sim turn-based"}
    assert tb["actuator_cycle"]["count"] == 0
    assert _median(records, "rx200 sim turn-based", "action_latency") < 5.0
    assert 0.0 < _median(records, "rx200 sim real-time", "observation_age") < 50.0
    assert 0.0 < _median(records, "rx200 sim turn-based", "observation_age") < 150.0


@pytest.mark.slow
def test_sweep_scenario(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(latency, "SWEEP_RATES_HZ", (20.0,))
    monkeypatch.setattr(latency, "SWEEP_CYCLES_S", (0.2,))
    out = tmp_path / "sweep.json"
    cfg = latency.LatencyBenchConfig(
        scenario="sweep", duration_s=2.0, think_ms=20.0, json_path=str(out), progress=False
    )
    records = latency.main(cfg, log=lambda _: None)
    envs = {"rx200 sim 20 Hz 800 ms", "rx200 sim 10 Hz 200 ms"}
    _check(records, out, "sweep", envs, {"scripted"})
    assert abs(_median(records, "rx200 sim 20 Hz 800 ms", "actuator_cycle") - 50.0) < 5.0
    assert abs(_median(records, "rx200 sim 10 Hz 200 ms", "actuator_cycle") - 100.0) < 5.0


@pytest.mark.slow
def test_single_scenario_runs_both_learners(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    out, plot = tmp_path / "single.json", tmp_path / "single.png"
    sb3_logs = tmp_path / "sb3-logs"  # where SB3 would make its log folder (otherwise a /tmp/SB3-<time> per learn())
    monkeypatch.setenv("SB3_LOGDIR", str(sb3_logs))
    cfg = latency.LatencyBenchConfig(
        scenario="single", duration_s=4.0, learning_starts=2, json_path=str(out), plot_path=str(plot), progress=False
    )
    records = latency.main(cfg, log=lambda _: None)
    _check(records, out, "single", {"rx200 sim"}, {"sb3-td3", "async-td3"})
    assert plot.exists()
    assert not sb3_logs.exists()  # the bench leaves no SB3 log folder behind
    for learner in ("sb3-td3", "async-td3"):
        assert abs(_median(records, "rx200 sim", "actuator_cycle", learner) - 100.0) < 5.0
        assert abs(_median(records, "rx200 sim", "action_cycle", learner) - 800.0) < 50.0


@pytest.mark.slow
def test_concurrent_scenario_four_envs_one_learner(tmp_path: Path) -> None:
    out = tmp_path / "conc.json"
    cfg = latency.LatencyBenchConfig(
        scenario="concurrent", duration_s=4.0, learning_starts=2, json_path=str(out), progress=False
    )
    lines: list[str] = []
    records = latency.main(cfg, log=lines.append)
    n_cpus = len(os.sched_getaffinity(0))
    assert f"idle cores: kept awake by {n_cpus} SCHED_IDLE poller(s)" in "\n".join(lines)
    envs = {"rx200 sim", "rx200 emulated-real", "ned2 sim", "ned2 emulated-real"}
    _check(records, out, "concurrent", envs, {"async-td3"})
    for env in envs:
        period = 100.0 if env.startswith("rx200") else 40.0
        assert abs(_median(records, env, "actuator_cycle") - period) < 5.0, env


@pytest.mark.slow
def test_envloop_bench_uses_the_same_metrics(tmp_path: Path) -> None:
    from uniros_async.bench import envloop

    out = tmp_path / "envloop.json"
    cfg = envloop.EnvLoopBenchConfig(duration_s=2.5, arms=("ned2",), think_ms=20.0, json_path=str(out), progress=False)
    printed: list[str] = []
    records = envloop.main(cfg, log=printed.append)
    _check(records, out, "envloop", {"ned2 sim"}, {"scripted"})
    assert abs(_median(records, "ned2 sim", "actuator_cycle") - 40.0) < 5.0
    # a thinking agent spreads the action cycle: no goal beside it, and the table says why
    table = printed[0]
    (row,) = [ln for ln in table.splitlines() if " action_cycle " in ln]
    assert "+- 0.5" not in row and "random 0-20 ms of thinking" in table
    printed.clear()
    envloop.main(dataclasses.replace(cfg, think_ms=0.0, duration_s=2.0, json_path=None), log=printed.append)
    (row,) = [ln for ln in printed[0].splitlines() if " action_cycle " in ln]
    assert row.endswith("800 +- 0.5, IQR < 1") and "of thinking" not in printed[0]
