"""The rows of ``uniros bench throughput``: each implementation's vector env (``_vector``: make_vec's, gymnasium's
AsyncVectorEnv, free or with its worker pinned, SB3's SubprocVecEnv, and the Ray rows' while a Ray cluster is open),
and how a row is measured against the bare env step: ``_run`` for the rx200 rows (paired blocks, then back to back),
``_run_trivial`` for the N = 1 rows of the cheap envs (every row's blocks interleaved in one run). What the figures
mean, and the tables they make: ``bench/throughput.py``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import os
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from uniros_async.bench import _stepmeter
from uniros_async.bench._environ import environ_set
from uniros_async.bench._ray_rows import RAY_IMPLS, RayRows
from uniros_async.bench._stepmeter import (
    TRAIL_S,
    Floor,
    Meter,
    bare_block,
    quiesce,
    sps_ci,
    tight,
    timed_block,
)
from uniros_async.bench.envs import DICT_ID, IMAGE_ID, make_env
from uniros_async.runtime.cores import usable_cpus
from uniros_async.stats import median_ci

IMPLS = ("uniros", "gymnasium-async", "sb3-subproc")
ENV_ID = "uniros/Rx200Reach-v0"
# absolute joint targets: the action mode the recorded figures were measured with (the task default is deltas)
ENV_KW: dict[str, Any] = {"turn_based": True, "action_mode": "absolute", "max_episode_steps": 10**9}
TRIVIAL_ID = "CartPole-v1"
PLACED_IMPLS = ("gymnasium-async@agent-core", "gymnasium-async@other-core")
"""Extra rows of the CartPole table: gymnasium's AsyncVectorEnv with its worker pinned to the core the agent's thread
is pinned to for that row's blocks, and to the other core. Its overhead is bimodal on a VM (a pipe round trip on
one core is two context switches; across cores each wake-up is an IPI to a halted vCPU), and a free-running worker
lands in one mode or the other from run to run; these rows measure both in the same run."""
SPACE_IDS = (DICT_ID, IMAGE_ID)
QUIET_S = 0.001
"""Untimed pause before each block of the trivial env's interleaved rows: longer than a worker's poll for its next
request (``worker.TURN_SPIN_NS``, 200 us), so no row starts while the previous row's worker still polls."""
_RAY: RayRows | None = None
"""The Ray rows' cluster while ``main`` runs with ``backend="ray"`` (``_vector`` builds their vector envs)."""
CROWDED_N = 4
"""From this many sub-envs on, a row's back-to-back phase runs until the 95 % interval of its steps/s is within
``CI_GOAL`` (at least ``MIN_TIGHT_STEPS`` or ``steps`` steps, at most ``MAX_TIGHT_STEPS``): there the workers
share the cores, and a row's steps/s says how well they share them."""


def _vector(
    impl: str, n: int, env_id: str, kwargs: dict[str, Any], transport: str = "shm", envs_per_worker: int = 1
) -> tuple[Any, Callable[[], Any], Callable[[Any], Any]]:
    """(vec env, reset(): seeds 0..n-1, step(actions)) for one implementation."""
    if _RAY is not None and impl in RAY_IMPLS:
        return _RAY.vector(impl, n, env_id, kwargs, pad=env_id == ENV_ID, envs_per_worker=envs_per_worker)
    if impl == "uniros":
        from uniros_async.runtime import make_vec

        venv = make_vec(
            [env_id] * n, pad=env_id == ENV_ID, transport=transport, envs_per_worker=envs_per_worker, **kwargs
        )
        return venv, lambda: venv.reset(seed=0), venv.step
    factory = functools.partial(make_env, env_id, kwargs)
    if impl.startswith("gymnasium-async"):
        from gymnasium.vector import AsyncVectorEnv

        avenv = AsyncVectorEnv([factory] * n, context="spawn")
        if impl in PLACED_IMPLS:
            cpu = _placed_cpus()[PLACED_IMPLS.index(impl)]
            for proc in avenv.processes:
                assert proc.pid is not None  # started by AsyncVectorEnv
                os.sched_setaffinity(proc.pid, {cpu})
        return avenv, lambda: avenv.reset(seed=0), avenv.step
    from stable_baselines3.common.vec_env import SubprocVecEnv

    sb = SubprocVecEnv([factory] * n, start_method="spawn")

    def reset() -> Any:
        sb.seed(0)
        return sb.reset()

    def step(actions: Any) -> Any:
        sb.step_async(actions)
        return sb.step_wait()

    return sb, reset, step


def _placed_cpus() -> tuple[int, int]:
    """(the agent's core for the placed rows, the other core): the first two this process may run on."""
    cpus = usable_cpus()
    return cpus[0], cpus[1]


@contextlib.contextmanager
def _agent_placed(impl: str) -> Iterator[None]:
    """For a placed row (``PLACED_IMPLS``), pin the calling thread (the agent's) to its core while the row's blocks
    run, then give it back the cores it had; nothing for another row."""
    if impl not in PLACED_IMPLS:
        yield
        return
    had = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {_placed_cpus()[0]})
    try:
        yield
    finally:
        os.sched_setaffinity(0, had)


def _actions(space: Any, steps: int) -> list[Any]:
    """One action per step for a single env (seeded: every run steps the same trajectory)."""
    rng = np.random.default_rng(0)
    if hasattr(space, "n"):
        return [int(rng.integers(space.n)) for _ in range(steps)]
    return [rng.uniform(space.low, space.high).astype(np.float32) for _ in range(steps)]


def _run(
    impl: str,
    n: int,
    bare: Any,
    env_id: str,
    kwargs: dict[str, Any],
    steps: int,
    floor: Floor | None = None,
    block: int = 8,
    transport: str = "shm",
    shared_cores: str | None = None,
    envs_per_worker: int = 1,
) -> dict[str, Any]:
    """One row (see the module docstring); ``shared_cores``: the ``UNIROS_SHARED_CORES`` its vector env is made
    with (None: as this process has it); ``envs_per_worker``: its ``make_vec``'s."""
    block = min(block, steps)
    crowded = n >= CROWDED_N
    longest = max(_stepmeter.MAX_TIGHT_STEPS, steps + 1) if crowded else steps + 1
    actions = _actions(bare.action_space, steps + 1 + longest)
    batch = [np.stack([a] * n) if isinstance(a, np.ndarray) else np.full(n, a) for a in actions]
    with environ_set("UNIROS_SHARED_CORES", shared_cores):  # the supervisor reads it when it connects its workers
        venv, reset, step = _vector(impl, n, env_id, kwargs, transport, envs_per_worker)
    vec_t: list[float] = []
    bare_t: list[float] = []
    floor_t: list[float] = []
    try:
        reset()
        bare.reset(seed=0)
        if floor is not None:
            floor.reset(0)
        # paired: steps k..k+B-1 of the bare env back to back, then the same steps of the floor, then of the
        # vector env (same states, same actions, the same moment's load); the first step of each block is left out
        for k0 in range(0, steps + 1 - block + 1, block):
            ks = range(k0, k0 + block)
            b = bare_block(bare, actions, ks)
            quiesce(bare)
            if floor is not None:
                floor_t += [floor.step_s(actions[k]) for k in ks][1:]
            v = timed_block(step, batch, ks)
            time.sleep(TRAIL_S)  # the workers' trailing work (the next servo tick) must not overlap the bare step
            bare_t += b[1:]
            vec_t += v[1:]
        # local workers: their CPU time here (each process once: envs_per_worker envs share one)
        meter = Meter(list(dict.fromkeys(getattr(venv, "pids", ()))) if impl == "uniros" else [])
        # throughput: back to back (crowded rows: in chunks, the bound's bare steps timed between them)
        tight_t, tight_bare = tight(step, batch, actions, steps + 1, steps + 1, n, meter, bare if crowded else None)
    finally:
        venv.close()
    record = _record(env_id, impl, n, tight_t, vec_t, bare_t)
    record["envs_per_worker"] = envs_per_worker
    meter.fill(record, n)
    if tight_bare:
        record["bound_bare_ms"] = round(float(np.median(tight_bare)) * 1e3, 3)
    if crowded:
        lo, hi = sps_ci(tight_t, n)
        record["steps_per_s_ci"] = None if np.isnan(lo) else [round(lo, 1), round(hi, 1)]
        record["tight_steps"] = len(tight_t)
    if floor_t:
        record["floor_ms"] = round(float(np.median(floor_t)) * 1e3, 3)
        record["overhead_over_floor_us"] = round(float(np.median(np.subtract(vec_t, floor_t))) * 1e6, 1)
    return record


@dataclasses.dataclass
class _Row:
    """One row of the trivial env's tables while it is measured: an implementation's vector env of one sub-env, or
    two of them stepped in turn (a training env and an evaluation env, or two tasks)."""

    impl: str
    envs: list[tuple[Any, Callable[[], Any], Callable[[Any], Any]]]
    vec_t: list[float] = dataclasses.field(default_factory=list)
    bare_t: list[float] = dataclasses.field(default_factory=list)
    tight_t: list[float] = dataclasses.field(default_factory=list)


def _run_trivial(
    impls: tuple[str, ...],
    in_turns: tuple[str, ...],
    bare: Any,
    env_id: str,
    steps: int,
    block: int = 20,
    transport: str = "shm",
) -> list[dict[str, Any]]:
    """The trivial env's rows (one vector env of one sub-env per implementation in ``impls``, and two of them
    stepped in turn per implementation in ``in_turns``), all measured in one interleaved run: per round, in an order
    shuffled from round to round (seeded), each row steps k..k+B-1 of the bare env back to back, then the same steps
    of its vector env (of each of its two, in turn), the first step of each block left out as in ``_run``. Every row
    so meets the same moments of this shared machine's load, which a row after row run does not (one row may fall in
    a busy second of the host, the next not); then rounds of back-to-back blocks of each single vector env for
    steps/s. Before each row's block the benchmark pauses ``QUIET_S``, so that no row starts while the previous
    row's workers still poll for a next request (a uniros worker polls 200 us), and no row always follows the same
    one. The workers idle while the other rows step, as a worker does between its env's blocks."""
    actions = _actions(bare.action_space, steps + block)
    rows: list[_Row] = []
    try:
        for impl in impls:
            rows.append(_Row(impl, [_vector(impl, 1, env_id, {}, transport)]))
        for impl in in_turns:
            rows.append(_Row(impl, [_vector(impl, 1, env_id, {}, transport) for _ in range(2)]))
        for row in rows:
            for _, reset, _ in row.envs:
                reset()
        bare.reset(seed=0)
        batch = [np.full(1, a) for a in actions]
        order = np.random.default_rng(0)
        for k0 in range(0, steps, block):
            ks = range(k0, k0 + block)
            for i in order.permutation(len(rows)):
                row = rows[i]
                with _agent_placed(row.impl):
                    time.sleep(QUIET_S)
                    b = bare_block(bare, actions, ks)
                    for _, _, step in row.envs:
                        row.vec_t += timed_block(step, batch, ks)[1:]
                        row.bare_t += b[1:]
        singles = [row for row in rows if len(row.envs) == 1]
        for k0 in range(0, steps, block):
            for i in order.permutation(len(singles)):
                with _agent_placed(singles[i].impl):
                    time.sleep(QUIET_S)
                    singles[i].tight_t += timed_block(singles[i].envs[0][2], batch, range(k0, k0 + block))
    finally:
        for row in rows:
            for venv, _, _ in row.envs:
                venv.close()
    return [
        _record(env_id, row.impl, 1, row.tight_t, row.vec_t, row.bare_t)
        if len(row.envs) == 1
        else {**_record(env_id, row.impl, 1, row.vec_t, row.vec_t, row.bare_t), "envs_in_turn": 2}
        for row in rows
    ]


def _record(
    env_id: str, impl: str, n: int, per_step: list[float], vec_t: list[float], bare_t: list[float]
) -> dict[str, Any]:
    """A row's record: steps/s from the median of ``per_step`` (seconds per vector step of ``n`` envs), the overhead
    as the median of (vector step - bare step) over the paired steps with its 95 % confidence interval (``median_ci``),
    and both medians."""
    diffs = np.subtract(vec_t, bare_t)
    lo, hi = median_ci(diffs)
    return {
        "env": env_id,
        "impl": impl,
        "n_envs": n,
        "steps_per_s": round(n / float(np.median(per_step)), 1),
        "overhead_us": round(float(np.median(diffs)) * 1e6, 1),
        "overhead_ci_us": None if np.isnan(lo) else [round(lo * 1e6, 1), round(hi * 1e6, 1)],
        "bare_ms": round(float(np.median(bare_t)) * 1e3, 3),
        "step_ms": round(float(np.median(vec_t)) * 1e3, 3),
    }


def _placed_impls() -> tuple[str, ...]:
    """``PLACED_IMPLS`` where this process may run on two cores or more, else none."""
    return PLACED_IMPLS if len(usable_cpus()) >= 2 else ()


def ray_rows() -> RayRows | None:
    """The Ray rows' cluster while ``open_ray_rows`` holds it open, else None."""
    return _RAY


@contextlib.contextmanager
def open_ray_rows(backend: str, address: str | None) -> Iterator[RayRows | None]:
    """With ``backend="ray"``: the Ray rows' cluster at ``address`` (None: a local one), started, in ``_RAY`` for
    the block (``_vector`` builds their vector envs from it) and closed after it; otherwise None."""
    global _RAY
    if backend != "ray":
        yield None
        return
    rows = RayRows(address)
    _RAY = rows
    try:
        rows.start()
        yield rows
    finally:
        rows.close()
        _RAY = None
