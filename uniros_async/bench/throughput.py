"""``uniros bench throughput``: vectorised stepping over worker processes, ours against gymnasium and SB3.

In one run, for N = 1, 2, 4, 8 copies of the rx200 reach env in accelerated turn-based mode (``turn_based=True``:
the sim advances in lockstep inside ``step``, as fast as the CPU allows), each implementation steps the same
sequence of random actions from the same reset seed: ``uniros_async.make_vec`` (workers over shared memory),
gymnasium's ``AsyncVectorEnv`` and SB3's ``SubprocVecEnv`` (both over pickled pipes, spawn).

The reference, "the bare env step", is the same env made with ``gymnasium.make`` in this process and stepped as a
user would (``env.step``; its world runs on the env's own loop thread), on the same trajectory: the turn-based sim
is deterministic, so step k costs the bare env and every sub-env the same physics. Each row first steps them in
alternating blocks (steps k..k+B-1 of the bare env back to back, then the same steps of the vector env: same states,
same actions, the same minute's machine load; the bare env's loop thread is let finish its block's trailing work,
untimed, before the vector block, and the workers theirs, ``TRAIL_S``, before the next bare block), then the vector
env alone, back to back. Within a block both run as a training loop steps them, one step right after the other; the
first step of each block, which starts on idle (halted, cache-cold) cores, is left out of both. Reported per row:

- ``steps_per_s``: N / median time per vector step, back to back (aggregate env steps per second);
- ``overhead_us``: median over k of (vector step k - bare step k) in the alternating phase, the per-step overhead
  (meaningful at N = 1; above that the workers share the machine's cores). The rx200 step itself scatters by
  milliseconds from step to step here (the same physics, 5-12 ms), so its figure is only as good as the number of
  steps; the trivial env's figure is the precise one. ``overhead_ci_us``: its 95 % confidence interval
  (``stats.median_ci``, distribution-free), printed beside it, which says how many steps a figure rests on;
- ``bare_ms`` / ``step_ms``: the medians of both in the alternating phase;
- at N = 1 also ``floor_ms``, the env's own step time with nothing around it (``Floor``: the env attached to a
  loop in this thread, its step coroutine timed from inside; a third block between the two), and
  ``overhead_over_floor_us``: median over k of (vector step k - floor step k). The bare gymnasium step pays the
  hand-over to its loop thread; a worker of ``make_vec`` runs the env attached to its own loop and does not, so
  the first overhead can be negative; the second is what the runtime costs on top of the env's work.

A second table does the same for a trivial env (gymnasium's ``CartPole-v1``, ~10 us a step), N = 1: what each
runtime costs per step when the env costs nothing. Two more rows of it pin gymnasium's AsyncVectorEnv worker to the
agent's core (the agent's thread pinned there for those rows' blocks) and to the other core (``PLACED_IMPLS``): its
overhead is bimodal, and the free row falls in either mode; the line under the tables gives uniros's overhead as a
fraction of all three. A third steps two vector envs of that env in turn, a block of
20 steps each, as a training loop with an evaluation env does (``envs_in_turn`` in the records): a worker woken
after its pause must not find itself sharing the agent's core. The rows of both tables are measured in one run,
their blocks interleaved in a shuffled order (``_vector_rows._run_trivial``; every row's vector env and how it is
measured are in bench/_vector_rows.py), so that each meets the same moments of the host's
load; ``steal_pct`` in their records is the hypervisor's steal over that run, printed above them. The physics
bound on aggregate steps/s is printed beside: min(N, cores) / bare step time.

``--backend ray`` adds, in the same run, workers placed by Ray (on another node over our tcp, and on the agent's
node over shm), local workers over tcp and a plain Ray actor call per step to the trivial env's table, and the
Ray-placed workers to the rx200 rows (``bench/_ray_rows.py``).

Rows of ``CROWDED_N`` (4) or more sub-envs step back to back, at least ``MIN_TIGHT_STEPS`` (400) steps and until
the 95 % interval of their steps/s is within ``CI_GOAL`` (+-2.5 %), and print it, with their % of the physics bound
and the CPU time per env step of the local workers and of the agent's process (read from /proc: a figure that
does not depend on how busy the host is). They step in chunks of ``TIGHT_CHUNK``, each followed by ``BOUND_BLOCK``
steps of the bare env, and their bound is from those bare steps (``bound_bare_ms``): timed in the same seconds as
the rate it bounds, where this host's speed drifts by several % from one second to the next.
``--repeat R`` (``main_repeat``) measures only those rows of ``make_vec`` (and of Ray-placed workers with
``--backend ray``), R runs each with new workers, and prints each run's % of the bound; ``--shared-cores`` adds a
row per ``UNIROS_SHARED_CORES`` mode (``worker.shared_cores_mode``) in the same runs.

A fourth and a fifth table measure the same way, N = 1, envs whose observations are what other pipelines carry
(``bench/envs.py``; their steps cost next to nothing): a goal env's Dict observation (three float64 arrays), and an
Atari-style 84x84x3 uint8 frame, which ``make_vec`` carries in its shm ring and gymnasium's AsyncVectorEnv in its
shared memory, SB3's SubprocVecEnv through its pickled pipe. A line under them gives the image env's uniros
overhead as a fraction of gymnasium's.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
from collections.abc import Callable
from typing import Any

import numpy as np

from uniros_async.bench._ray_rows import RAY_IMPLS, overhead_lines
from uniros_async.bench._stepmeter import Floor
from uniros_async.bench._vector_rows import (
    CROWDED_N,
    ENV_ID,
    ENV_KW,
    IMPLS,
    PLACED_IMPLS,
    SPACE_IDS,
    TRIVIAL_ID,
    _placed_impls,
    _run,
    _run_trivial,
    open_ray_rows,
    ray_rows,
)
from uniros_async.bench.common import cpu_times, progress_counter, report, steal_percent
from uniros_async.bench.envs import DICT_ID, IMAGE_ID, make_env
from uniros_async.errors import ConfigError
from uniros_async.runtime.cores import SHARED_CORES_MODES
from uniros_async.transports._shm_ring import describe_ring_end

__all__ = ["IMPLS", "ThroughputBenchConfig", "main"]

SPACE_STEPS = 500
"""Steps per row of the Dict and image envs' tables (interleaved as the trivial env's)."""
TRIVIAL_STEPS = 1000
"""Steps per row of the trivial env's tables (50 rounds of every row, interleaved: ``_run_trivial``): a few
seconds in all, in a slow hour too."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class ThroughputBenchConfig:
    n_envs: tuple[int, ...] = (1, 2, 4, 8)
    steps: int = 100
    quick: bool = False
    json_path: str | None = None
    transport: str = "shm"
    """How ``make_vec`` reaches its workers (``shm`` or ``tcp`` on loopback); the peers use their pipes either way."""
    progress: bool = True
    """A progress bar over the rows (tqdm, on stderr)."""
    backend: str = "local"
    """``ray``: add the Ray rows (``bench/_ray_rows.py``) on the cluster at ``ray_address`` (None: a local one)."""
    ray_address: str | None = None
    """The Ray cluster's address for ``backend="ray"`` (None: a local two-node cluster started for the run)."""
    shared_cores: tuple[str, ...] = ()
    """With ``repeat``: one row per ``UNIROS_SHARED_CORES`` mode (``worker.shared_cores_mode``) for each N and
    backend, their runs interleaved (empty: as this process has it)."""
    envs_per_worker: tuple[str, ...] = ("auto",)
    """How many envs one worker process of ``make_vec`` hosts in its rows (local and Ray-placed), per N: ``auto``
    (make_vec's default, decided by its own rule), a count, or ``cores`` for one process per core where the envs
    outnumber the cores (``per_worker``). The first value for the full bench; with ``repeat``, one row per value,
    runs interleaved."""
    repeat: int = 0
    """> 0: measure only the make_vec rows at ``CROWDED_N`` or more sub-envs (and the Ray-placed ones with
    ``backend="ray"``), ``repeat`` runs of each, every run with new workers, and print each run's % of the physics
    bound (``main_repeat``)."""

    def __post_init__(self) -> None:
        if not self.n_envs or min(self.n_envs) < 1 or self.steps < 5:
            raise ConfigError(f"n_envs must be >= 1 and steps >= 5, got {self.n_envs}, {self.steps}")
        if self.repeat < 0:
            raise ConfigError(f"repeat must be >= 0 (0: the full bench once), got {self.repeat}")
        bad = [m for m in self.shared_cores if m not in SHARED_CORES_MODES]
        if bad:
            raise ConfigError(f"shared_cores modes must be among {SHARED_CORES_MODES}, got {bad}")
        if self.repeat and max(self.n_envs) < CROWDED_N:
            raise ConfigError(f"repeat measures rows of >= {CROWDED_N} sub-envs; n_envs {self.n_envs} has none")
        if self.transport not in ("shm", "tcp"):
            raise ConfigError(f"transport must be 'shm' or 'tcp', got {self.transport!r}")
        if self.backend not in ("local", "ray"):
            raise ConfigError(f"backend must be 'local' or 'ray', got {self.backend!r}")
        for value in self.envs_per_worker:
            per_worker(value, 1, 1)


def per_worker(value: str, n: int, cores: int) -> int:
    """Envs per worker process for ``n`` sub-envs on ``cores`` cores: ``value`` a count >= 1; ``cores``: as many
    as make one process per core when the envs outnumber the cores (ceil(n / cores)), else 1; or ``auto``: what
    make_vec's default decides for ``n`` of the bench's accelerated envs (``runtime.specs.plan_envs_per_worker``,
    the function make_vec itself calls).

    Raises:
        ConfigError: none of these.
    """
    if value == "auto":
        from uniros_async.runtime.specs import plan_envs_per_worker

        return plan_envs_per_worker([(ENV_ID, dict(ENV_KW))] * n, [False] * n, "auto")[0]
    if value == "cores":
        return -(-n // cores) if n > cores else 1
    if not value.isdigit() or int(value) < 1:
        raise ConfigError(f"envs_per_worker: expected a count >= 1, 'cores' or 'auto', got {value!r}")
    return int(value)


RX200_WIDE_US = 100.0
"""An rx200 N = 1 row whose overhead interval is wider than this (each way) gets a hint to pin it down."""


def _rx200_hint(records: list[dict[str, Any]]) -> list[str]:
    """A line under the rx200 table when its N = 1 uniros figure rests on too few steps to say much."""
    for r in records:
        if r["env"] == ENV_ID and r["n_envs"] == 1 and r["impl"] == IMPLS[0]:
            ci = r["overhead_ci_us"]
            if ci is None or (ci[1] - ci[0]) / 2 > RX200_WIDE_US:
                return [
                    "(the rx200 step scatters by milliseconds from step to step, so these overheads rest on too few",
                    " steps: `--n-envs 1 --steps 1500` pins N = 1 down to about +-50 us in ~4 min)",
                ]
    return []


def _interval(ci: list[float] | None) -> str:
    return "too few steps" if ci is None else f"{ci[0]:.0f} .. {ci[1]:.0f}"


def _measure(
    config: ThroughputBenchConfig,
    ns: tuple[int, ...],
    steps: int,
    in_turns: tuple[str, ...],
    records: list[dict[str, Any]],
    bar: Callable[..., None],
) -> None:
    """Run every row into ``records``, counting each on ``bar``."""
    ray = ray_rows() is not None
    impls = IMPLS + (("uniros-ray",) if ray else ())
    cores = os.cpu_count() or 1
    trivial_impls = IMPLS + _placed_impls() + (RAY_IMPLS if ray else ())
    bare = make_env(ENV_ID, ENV_KW)
    try:
        floor: Floor | None = Floor(ENV_ID, ENV_KW)
    except ImportError:  # a tree without the attached mode (to compare an older runtime with the same benchmark)
        floor = None
    try:
        for n in ns:
            for impl in impls:
                floor_n = floor if n == 1 else None
                k = per_worker(config.envs_per_worker[0], n, cores) if impl in ("uniros", "uniros-ray") else 1
                how = config.transport
                records.append(_run(impl, n, bare, ENV_ID, ENV_KW, steps, floor_n, transport=how, envs_per_worker=k))
                bar(1)
    finally:
        if floor is not None:
            floor.close()
        bare.close()
    trivial = make_env(TRIVIAL_ID, {})
    try:
        cpu0 = cpu_times()
        rows = _run_trivial(trivial_impls, in_turns, trivial, TRIVIAL_ID, TRIVIAL_STEPS, transport=config.transport)
        steal = steal_percent(cpu0, cpu_times())
        for r in rows:
            r["steal_pct"] = None if steal is None else round(steal, 2)
        records += rows
        bar(len(rows))
    finally:
        trivial.close()
    space_steps = min(SPACE_STEPS, TRIVIAL_STEPS // 5) if config.quick else SPACE_STEPS
    for env_id in SPACE_IDS:
        env = make_env(env_id, {})
        try:
            rows = _run_trivial(IMPLS, (), env, env_id, space_steps, transport=config.transport)
            records += rows
            bar(len(rows))
        finally:
            env.close()


def _bound_pct(record: dict[str, Any], cores: int) -> None:
    """Add a row's physics bound (min(N, cores) / its own bare step) and its steps/s as a % of it (and of the
    interval's ends) to ``record``."""
    bound = min(record["n_envs"], cores) / (record.get("bound_bare_ms", record["bare_ms"]) / 1e3)
    record["bound_steps_per_s"] = round(bound, 1)
    record["bound_pct"] = round(100 * record["steps_per_s"] / bound, 1)
    ci = record.get("steps_per_s_ci")
    record["bound_pct_ci"] = None if ci is None else [round(100 * c / bound, 1) for c in ci]


def _pct_interval(record: dict[str, Any]) -> str:
    ci = record.get("bound_pct_ci")
    return "too few steps" if ci is None else f"{ci[0]:.0f}-{ci[1]:.0f} %"


def _cpu_line(record: dict[str, Any]) -> str:
    if "worker_cpu_ms" not in record:
        return ""
    line = f"; CPU per env step: workers {record['worker_cpu_ms']:.2f} ms, agent {record['agent_cpu_ms']:.3f} ms"
    if "cores_ours_pct" in record:
        ours, idle = record["cores_ours_pct"], record["cores_idle_pct"]
        line += f"; the cores: ours {ours:.0f} %, idle {idle:.0f} %, other processes {max(100 - ours - idle, 0):.0f} %"
    return line


def _host_state(load0: tuple[float, ...], cpu0: Any) -> str:
    steal = steal_percent(cpu0, cpu_times())
    load1 = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),)
    return (
        f"host: 1-min load average {load0[0]:.2f} at the start, {load1[0]:.2f} at the end;"
        f" hypervisor steal {'unknown' if steal is None else f'{steal:.1f} %'} of CPU time meanwhile"
    )


def main_repeat(config: ThroughputBenchConfig, *, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """``--repeat R``: the make_vec rows with ``CROWDED_N`` or more sub-envs (workers over ``config.transport``,
    and with ``backend="ray"`` workers placed by Ray on the other node, over tcp), ``R`` runs of each; per run the
    rows in turn, each with new workers (where the scheduler puts them is decided anew), each against the bare step
    timed between its own blocks (``_run``). Prints each run's steps/s as a % of the physics bound, with its 95 %
    interval, and the CPU time per env step of the local workers and the agent."""
    cores = os.cpu_count() or 1
    ns = tuple(n for n in config.n_envs if n >= CROWDED_N)
    impls = ("uniros",) + (("uniros-ray",) if config.backend == "ray" else ())
    modes: tuple[str | None, ...] = config.shared_cores or (None,)
    records: list[dict[str, Any]] = []
    load0 = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),)
    cpu0 = cpu_times()
    with open_ray_rows(config.backend, config.ray_address) as cluster:
        pers = config.envs_per_worker
        n_rows = config.repeat * len(ns) * len(impls) * len(modes) * len(pers)
        bar = progress_counter(n_rows, config.progress, "throughput bench", "row")
        bare = make_env(ENV_ID, ENV_KW)
        try:
            for run in range(1, config.repeat + 1):
                for n in ns:
                    for impl in impls:
                        for mode, per in itertools.product(modes, pers):
                            steps, how, k = config.steps, config.transport, per_worker(per, n, cores)
                            r = _run(
                                impl,
                                n,
                                bare,
                                ENV_ID,
                                ENV_KW,
                                steps,
                                transport=how,
                                shared_cores=mode,
                                envs_per_worker=k,
                            )
                            r["run"] = run
                            r["shared_cores"] = mode or os.environ.get("UNIROS_SHARED_CORES", "pin")
                            _bound_pct(r, cores)
                            records.append(r)
                            bar(1)
        finally:
            bare.close()
            bar(0, done=True)
        where = cluster.describe() if cluster is not None else ""
    lines = [
        f"{ENV_ID} (turn-based, accelerated) on {cores} cores, {config.repeat} runs of each row (new workers every"
        f" run): steps/s as a % of the physics bound min(N, cores) / bare step, each row against the bare step timed"
        f" between its own blocks; make_vec's local workers over {config.transport}",
        _host_state(load0, cpu0),
    ]
    if where:
        lines.append(where + " (uniros-ray: workers placed by Ray there, over tcp)")
    head = f"{'N':>3} {'impl':<12} {'cores':<8} {'per proc':>8}  {'% of the physics bound, run by run':<44} {'min':>6}"
    lines += [
        "",
        "(cores: UNIROS_SHARED_CORES, what the workers do when they outnumber the cores; per proc: envs per worker"
        " process, make_vec's envs_per_worker)",
        head,
    ]
    lines.append("-" * len(head))
    for n in ns:
        for impl in impls:
            for mode, k in dict.fromkeys((r["shared_cores"], r["envs_per_worker"]) for r in records):
                rows = [
                    r
                    for r in records
                    if (r["n_envs"], r["impl"], r["shared_cores"], r["envs_per_worker"]) == (n, impl, mode, k)
                ]
                if not rows:
                    continue
                pcts = [r["bound_pct"] for r in rows]
                runs = " ".join(f"{p:5.1f}" for p in pcts)
                lines.append(f"{n:>3} {impl:<12} {mode:<8} {k:>8}  {runs:<44} {min(pcts):>6.1f}")
    lines += ["", "each run: steps/s, its 95 % interval (as % of the bound), steps back to back, bare step"]
    for r in records:
        lines.append(
            f"  run {r['run']} N={r['n_envs']} {r['impl']:<12} {r['shared_cores']:<8} x{r['envs_per_worker']}"
            f" {r['steps_per_s']:7.1f}"
            f" steps/s of {r['bound_steps_per_s']:.0f}: {r['bound_pct']:5.1f} % ({_pct_interval(r)},"
            f" {r['tight_steps']} steps; bare {r.get('bound_bare_ms', r['bare_ms']):.2f} ms){_cpu_line(r)}"
        )
    report("\n".join(lines), records, config.json_path, log)
    return records


def main(config: ThroughputBenchConfig, *, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    if config.repeat:
        return main_repeat(config, log=log)
    ns = tuple(n for n in config.n_envs if n <= 4) if config.quick else config.n_envs
    if not ns:
        raise ConfigError(f"--quick runs N <= 4 only, and n_envs {config.n_envs} has none")
    steps = min(config.steps, 30) if config.quick else config.steps  # --quick: within its minute on a slow hour too
    cores = os.cpu_count() or 1
    records: list[dict[str, Any]] = []
    in_turns = IMPLS[:2] if config.quick else IMPLS  # (--quick: against gymnasium's only, to keep within its minute)
    ray = config.backend == "ray"
    n_rows = len(ns) * (len(IMPLS) + ray) + len(IMPLS) + len(_placed_impls()) + len(RAY_IMPLS) * ray + len(in_turns)
    n_rows += len(SPACE_IDS) * len(IMPLS)
    with open_ray_rows(config.backend, config.ray_address) as cluster:
        bar = progress_counter(n_rows, config.progress, "throughput bench", "row")
        try:
            _measure(config, ns, steps, in_turns, records, bar)
        finally:
            bar(0, done=True)
        where = cluster.describe() if cluster is not None else ""
    bare_ms = float(np.median([r["bare_ms"] for r in records if r["env"] == ENV_ID]))
    width = max(16, *(len(r["impl"]) for r in records))
    head = (
        f"{'N':>3} {'impl':<{width}} {'env steps/s':>12} {'overhead us/step':>17} {'its 95 % CI':>18} {'step ms':>8}"
        f" {'bare ms':>8}"
    )
    lines = [
        f"{ENV_ID} (turn-based, accelerated), {steps} steps per row, bare step {bare_ms:.2f} ms median, {cores} cores;"
        f" make_vec's workers over {config.transport}"
        + (f" (ring end: {describe_ring_end()})" if config.transport == "shm" else ""),
        head,
        "-" * len(head),
    ]
    for r in records:
        if r["env"] == TRIVIAL_ID and r["impl"] == IMPLS[0]:
            what = (
                "two vector envs of one env each, stepped in turn: a training and an evaluation env"
                if r.get("envs_in_turn")
                else "trivial env: the runtime's own cost per step"
            )
            if not r.get("envs_in_turn"):
                steal = r.get("steal_pct")
                lines += [
                    *_rx200_hint(records),
                    "",
                    f"{TRIVIAL_ID}: {TRIVIAL_STEPS} steps per row, the rows' blocks interleaved; hypervisor steal "
                    + ("unknown" if steal is None else f"{steal:.1f} % of CPU time")
                    + " meanwhile (the VM's cores were taken away that long)",
                ]
            lines += ["", f"{TRIVIAL_ID} ({what})", head, "-" * len(head)]
        if r["env"] in SPACE_IDS and r["impl"] == IMPLS[0]:
            what = "Dict observation, 3 float64 arrays" if r["env"] == DICT_ID else "84x84x3 uint8 frame observation"
            lines += ["", f"{r['env'].partition(':')[2]} ({what}; N = 1, rows interleaved)", head, "-" * len(head)]
        lines.append(
            f"{r['n_envs']:>3} {r['impl']:<{width}} {r['steps_per_s']:>12.1f} {r['overhead_us']:>17.1f}"
            f" {_interval(r['overhead_ci_us']):>18} {r['step_ms']:>8.3f} {r['bare_ms']:>8.3f}"
        )
    lines.append("")
    if ray:
        lines += [where, *overhead_lines(records, TRIVIAL_ID)]
    for r in records:
        if "floor_ms" in r:
            lines.append(
                f"N=1 {r['impl']}: the env's own step (floor) {r['floor_ms']:.3f} ms; overhead over it"
                f" {r['overhead_over_floor_us']:.1f} us (over the bare gymnasium step: {r['overhead_us']:.1f} us)"
            )
    for n in ns:
        rows = {r["impl"]: r for r in records if r["n_envs"] == n and r["env"] == ENV_ID}
        ratio = rows["uniros"]["steps_per_s"] / rows["gymnasium-async"]["steps_per_s"]
        bound = min(n, cores) / (bare_ms / 1e3)
        lines.append(
            f"N={n}: uniros / gymnasium-async steps/s = {ratio:.2f}x; physics bound min(N, {cores} cores) / bare step"
            f" = {bound:.0f} steps/s"
        )
        for impl in ("uniros", "uniros-ray"):
            row = rows.get(impl)
            if row is not None and "steps_per_s_ci" in row:
                _bound_pct(row, cores)
                lines.append(
                    f"  {impl}: {row['bound_pct']:.1f} % of its bound ({_pct_interval(row)}, {row['tight_steps']}"
                    f" steps back to back){_cpu_line(row)}"
                )
    for label, env_id, in_turn in (
        ("CartPole", TRIVIAL_ID, False),
        ("CartPole in turn", TRIVIAL_ID, True),
        ("image env", IMAGE_ID, False),
    ):
        pair = {r["impl"]: r for r in records if r["env"] == env_id and bool(r.get("envs_in_turn")) == in_turn}
        if "uniros" in pair and pair.get("gymnasium-async", {}).get("overhead_us", 0) > 0:
            ours, theirs = pair["uniros"]["overhead_us"], pair["gymnasium-async"]["overhead_us"]
            line = f"{label}: uniros overhead / gymnasium-async overhead = {ours / theirs:.2f}"
            placed = [ours / pair[i]["overhead_us"] for i in PLACED_IMPLS if pair.get(i, {}).get("overhead_us", 0) > 0]
            if len(placed) == 2:
                line += f" (its worker on the agent's core: {placed[0]:.2f}; on the other core: {placed[1]:.2f})"
            lines.append(line)
    report("\n".join(lines), records, config.json_path, log)
    return records
