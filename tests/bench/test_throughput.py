"""``uniros bench throughput``: one short row per implementation, the JSON schema, the table and bad configs.

Real worker processes of all three implementations; the test checks what the records say and how they relate,
never a figure's size (that is the benchmark's job, docs/performance.md).
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np
import pytest

from uniros_async.bench import _stepmeter, _vector_rows, throughput
from uniros_async.errors import ConfigError
from uniros_async.runtime.cores import usable_cpus

pytestmark = pytest.mark.slow


def test_a_short_run_prints_the_table_and_writes_every_record(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "t.json"
    lines: list[str] = []
    cores_before = os.sched_getaffinity(0)
    records = throughput.main(
        throughput.ThroughputBenchConfig(n_envs=(1,), steps=5, json_path=str(out)), log=lines.append
    )
    # the progress bar: 3 rx200 rows, 3 CartPole rows and 2 of gymnasium's placed, 3 rows of two envs in turn,
    # 3 Dict-env rows, 3 image-env rows
    err = capsys.readouterr().err
    n = 15 + len(throughput._placed_impls())
    assert "throughput bench" in err and f"{n}/{n}" in err
    assert json.loads(out.read_text()) == records
    rows = {(r["env"], r["impl"]) for r in records}
    envs = (throughput.ENV_ID, throughput.TRIVIAL_ID, *throughput.SPACE_IDS)
    placed = {(throughput.TRIVIAL_ID, i) for i in throughput._placed_impls()}
    assert rows == {(e, i) for e in envs for i in throughput.IMPLS} | placed
    in_turns = [r for r in records if r.get("envs_in_turn")]
    assert sorted(r["impl"] for r in in_turns) == sorted(throughput.IMPLS)
    assert all(r["env"] == throughput.TRIVIAL_ID and r["envs_in_turn"] == 2 for r in in_turns)
    for r in records:
        assert {"impl", "n_envs", "steps_per_s", "overhead_us", "overhead_ci_us"} <= r.keys()
        if r["env"] == throughput.TRIVIAL_ID:  # 950 paired steps: an interval around the median
            lo, hi = r["overhead_ci_us"]
            assert lo <= r["overhead_us"] <= hi
            assert 0.0 <= r["steal_pct"] <= 100.0  # measured over the interleaved run (this is Linux)
        elif r["env"] in throughput.SPACE_IDS:  # 475 paired steps
            lo, hi = r["overhead_ci_us"]
            assert lo <= r["overhead_us"] <= hi
        else:  # 5 steps, the first of the block left out: too few for a 95 % interval
            assert r["overhead_ci_us"] is None
        assert r["n_envs"] == 1 and r["steps_per_s"] > 0 and r["bare_ms"] > 0 and r["step_ms"] > 0
        if r["env"] == throughput.ENV_ID:  # the floor is measured beside the rx200 rows at N = 1
            assert r["floor_ms"] > 0 and isinstance(r["overhead_over_floor_us"], float)
        else:
            assert "floor_ms" not in r
    text = "\n".join(lines)
    assert "gymnasium-async" in text and "sb3-subproc" in text and "physics bound" in text
    assert "stepped in turn" in text
    assert "UnirosBenchDictObs-v0 (Dict observation" in text and "UnirosBenchImageObs-v0 (84x84x3 uint8" in text
    for label in ("CartPole", "CartPole in turn", "image env"):  # the ratios the goals are stated in
        assert f"\n{label}: uniros overhead / gymnasium-async overhead = " in text
    if throughput._placed_impls():
        assert "(its worker on the agent's core: " in text and "; on the other core: " in text
    assert os.sched_getaffinity(0) == cores_before  # the agent's thread got its cores back after the placed rows
    assert "95 % CI" in text and "too few steps" in text
    assert "--n-envs 1 --steps 1500" in text  # 5 rx200 steps: the hint to pin N = 1 down
    assert "make_vec's workers over shm (ring end: compiled)" in text  # which shm ring end the rows ran on


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="the placed rows need two cores")
def test_the_placed_gymnasium_rows_pin_its_worker_and_the_agent_for_their_blocks() -> None:
    agent_cpu, other_cpu = _vector_rows._placed_cpus()
    had = os.sched_getaffinity(0)
    for impl, cpu in zip(throughput.PLACED_IMPLS, (agent_cpu, other_cpu), strict=True):
        venv, reset, step = _vector_rows._vector(impl, 1, throughput.TRIVIAL_ID, {})
        try:
            reset()
            (proc,) = venv.processes
            assert os.sched_getaffinity(proc.pid) == {cpu}
            with _vector_rows._agent_placed(impl):
                assert os.sched_getaffinity(0) == {agent_cpu}
                step(np.zeros(1, np.int64))
            assert os.sched_getaffinity(0) == had
            with _vector_rows._agent_placed("gymnasium-async"):  # the free row: left where it is
                assert os.sched_getaffinity(0) == had
        finally:
            venv.close()


@pytest.mark.parametrize("kw", [{"n_envs": ()}, {"n_envs": (0,)}, {"steps": 2}])
def test_bad_configs_are_refused(kw: dict[str, object]) -> None:
    with pytest.raises(ConfigError, match="n_envs must be >= 1 and steps >= 5"):
        throughput.ThroughputBenchConfig(**kw)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="transport must be 'shm' or 'tcp', got 'udp'"):
        throughput.ThroughputBenchConfig(transport="udp")


def test_quick_refuses_env_counts_it_would_all_drop() -> None:
    with pytest.raises(ConfigError, match="--quick runs N <= 4 only"):
        throughput.main(throughput.ThroughputBenchConfig(n_envs=(8,), quick=True, progress=False))


def test_the_uniros_rows_can_run_over_tcp(monkeypatch: pytest.MonkeyPatch) -> None:
    """With ``transport="tcp"`` the uniros rows' steps travel over tcp connections: the agent's ends of them send
    the actions of every step (a spy on the real transport's count of sent frames)."""
    from uniros_async.transports.tcp import TcpTransport

    sent: list[int] = []
    count_sent = TcpTransport._count_sent

    def spy(self: TcpTransport, n: int) -> None:
        sent.append(n)
        count_sent(self, n)

    monkeypatch.setattr(TcpTransport, "_count_sent", spy)
    config = throughput.ThroughputBenchConfig(n_envs=(1,), steps=5, transport="tcp", progress=False)
    records = throughput.main(config, log=lambda _: None)
    uniros = [r for r in records if r["impl"] == "uniros"]
    assert uniros and all(r["steps_per_s"] > 0 for r in uniros)
    # the rx200, CartPole, in-turn, Dict and image rows: at least 5 steps each over tcp
    assert len(sent) >= 5 * len(uniros), f"{len(sent)} frames over tcp for {len(uniros)} uniros rows"


def test_the_rx200_hint_shows_only_when_the_n1_interval_is_wide() -> None:
    def rows(ci: list[float] | None) -> list[dict[str, object]]:
        return [{"env": throughput.ENV_ID, "n_envs": 1, "impl": "uniros", "overhead_ci_us": ci}]

    assert throughput._rx200_hint(rows([10.0, 60.0])) == []
    assert "--steps 1500" in "".join(throughput._rx200_hint(rows([-300.0, 400.0])))
    assert "--steps 1500" in "".join(throughput._rx200_hint(rows(None)))  # too few steps for any interval


def test_repeat_runs_the_crowded_rows_run_by_run_with_their_intervals(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(_stepmeter, "MAX_TIGHT_STEPS", 30)  # the interval's goal would take hundreds of steps
    lines: list[str] = []
    config = throughput.ThroughputBenchConfig(
        n_envs=(1, 4), steps=5, repeat=2, shared_cores=("pin", "off"), progress=False
    )
    records = throughput.main(config, log=lines.append)
    # N = 1 is no crowded row: 2 runs x N = 4 x 2 modes, in that order
    assert [(r["run"], r["n_envs"], r["shared_cores"]) for r in records] == [
        (1, 4, "pin"),
        (1, 4, "off"),
        (2, 4, "pin"),
        (2, 4, "off"),
    ]
    for r in records:
        assert r["impl"] == "uniros" and r["env"] == throughput.ENV_ID
        assert 6 <= r["tight_steps"] <= 30  # at least the row's steps, at most the cap
        assert r["bound_steps_per_s"] > 0 and r["bound_pct"] == pytest.approx(
            100 * r["steps_per_s"] / r["bound_steps_per_s"], rel=0.01
        )
        if r["steps_per_s_ci"] is not None:
            lo, hi = r["steps_per_s_ci"]
            assert lo <= r["steps_per_s"] <= hi
            assert r["bound_pct_ci"][0] <= r["bound_pct"] <= r["bound_pct_ci"][1]
        assert r["worker_cpu_ms"] > 0 and r["agent_cpu_ms"] >= 0  # the workers' own CPU time, read from /proc
        assert r["cores_ours_pct"] > 0 and 0 <= r["cores_idle_pct"] <= 100  # and what the cores did meanwhile
    text = "\n".join(lines)
    assert "% of the physics bound, run by run" in text and "host: 1-min load average" in text
    # the summary table shows each row's runs (as the records have them) and their minimum
    for mode in ("pin", "off"):
        rows = [r for r in records if r["shared_cores"] == mode]
        pcts = [r["bound_pct"] for r in rows]
        per_proc = rows[0]["envs_per_worker"]
        assert _summary_row(text, 4, mode, per_proc) == [*(round(p, 1) for p in pcts), round(min(pcts), 1)]
    # and one line per run with its steps/s and % of the bound, as recorded
    for r in records:
        sps, pct = _run_line(text, r["run"], 4, r["shared_cores"], r["envs_per_worker"])
        assert sps == pytest.approx(r["steps_per_s"], abs=0.05) and pct == pytest.approx(r["bound_pct"], abs=0.05)
    assert "CPU per env step: workers" in text and "; the cores: ours " in text and " other processes " in text


def _summary_row(text: str, n: int, mode: str, per_proc: int) -> list[float]:
    """The figures of the summary table's row for N = ``n``, uniros, ``mode`` and ``per_proc`` envs per process."""
    rows = [
        line.split()[4:] for line in text.splitlines() if line.split()[:4] == [str(n), "uniros", mode, str(per_proc)]
    ]
    assert len(rows) == 1, f"no single summary row for N={n} {mode} x{per_proc} in:\n{text}"
    return [float(x) for x in rows[0]]


def _run_line(text: str, run: int, n: int, mode: str, per_proc: int) -> tuple[float, float]:
    """Steps/s and % of the bound on the line of run ``run`` of that row."""
    pattern = rf"run {run} N={n} uniros\s+{mode}\s+x{per_proc}\s+([\d.]+) steps/s of \d+:\s+([\d.]+) %"
    found = re.findall(pattern, text)
    assert len(found) == 1, f"no single line for run {run} N={n} {mode} x{per_proc} in:\n{text}"
    return float(found[0][0]), float(found[0][1])


@pytest.mark.parametrize(
    ("kw", "what"),
    [
        ({"repeat": -1}, "repeat must be >= 0"),
        ({"repeat": 2, "n_envs": (1, 2)}, "repeat measures rows of >= 4 sub-envs"),
        ({"shared_cores": ("sometimes",)}, "shared_cores modes must be among"),
    ],
)
def test_bad_repeat_configs_are_refused(kw: dict[str, object], what: str) -> None:
    with pytest.raises(ConfigError, match=what):
        throughput.ThroughputBenchConfig(**kw)  # type: ignore[arg-type]


def test_repeat_rows_with_envs_grouped_one_process_per_core(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(_stepmeter, "MAX_TIGHT_STEPS", 30)
    lines: list[str] = []
    config = throughput.ThroughputBenchConfig(
        n_envs=(4,), steps=5, repeat=1, envs_per_worker=("cores",), progress=False
    )
    (record,) = throughput.main(config, log=lines.append)
    cores = os.cpu_count() or 1
    assert record["envs_per_worker"] == throughput.per_worker("cores", 4, cores)
    assert record["worker_cpu_ms"] > 0  # the processes' CPU time, each process counted once
    sps, pct = _run_line("\n".join(lines), 1, 4, "pin", record["envs_per_worker"])
    assert sps == pytest.approx(record["steps_per_s"], abs=0.05) and pct == pytest.approx(record["bound_pct"], abs=0.05)


def test_per_worker_counts_envs_per_process() -> None:
    assert throughput.per_worker("cores", 8, 2) == 4
    assert throughput.per_worker("cores", 5, 2) == 3
    assert throughput.per_worker("cores", 2, 2) == 1  # no more envs than cores: a process each
    assert throughput.per_worker("3", 8, 2) == 3
    # auto: what make_vec's default decides for the bench's accelerated rx200 on this machine's cores
    cores = len(usable_cpus())
    for n in (1, cores, 2 * cores, 4 * cores):
        assert throughput.per_worker("auto", n, cores) == (-(-n // cores) if n > cores else 1)
    assert throughput.ThroughputBenchConfig().envs_per_worker == ("auto",)  # the bench measures the default
    for bad in ("0", "two", "-1", ""):
        with pytest.raises(ConfigError, match="envs_per_worker: expected a count >= 1, 'cores' or 'auto', got"):
            throughput.ThroughputBenchConfig(envs_per_worker=(bad,))


def test_crowded_back_to_back_phase_takes_at_least_its_floor(monkeypatch: pytest.MonkeyPatch) -> None:
    """A crowded row steps MIN_TIGHT_STEPS even when --steps asks for fewer and its interval is tight already, and
    timed bare blocks follow each chunk; the cap still wins over the floor."""
    import gymnasium as gym

    bare = gym.make("CartPole-v1")
    bare.reset(seed=0)
    actions = [0, 1] * 600
    batch = [np.array([a] * 4) for a in actions]

    # the interval counts as tight whatever the host does to these sub-microsecond steps: what is checked is the
    # floor and the cap
    monkeypatch.setattr(_stepmeter, "sps_halfwidth", lambda times, n: 0.0)

    def run(floor: int, cap: int) -> tuple[list[float], list[float]]:
        monkeypatch.setattr(_stepmeter, "MIN_TIGHT_STEPS", floor)
        monkeypatch.setattr(_stepmeter, "MAX_TIGHT_STEPS", cap)
        return _stepmeter.tight(lambda a: None, batch, actions, 1, 6, 4, _stepmeter.Meter([]), bare)

    times, bare_t = run(200, 2000)
    chunks = -(-200 // (_stepmeter.TIGHT_CHUNK - 1))  # each chunk's first step is left out
    assert len(times) == chunks * (_stepmeter.TIGHT_CHUNK - 1)
    assert len(bare_t) == chunks * (_stepmeter.BOUND_BLOCK - 1)
    times, _ = run(200, 60)
    assert len(times) < 60
    bare.close()
