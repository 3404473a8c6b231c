"""``uniros bench latency``: the paper's timing figures (UniROS Figures 8 to 10), with learners and worker processes.

Real-time (wall-clock) scenarios; every env runs in its own worker process (``uniros_async.make`` /
``make_vec``), so a learner's GIL never stalls an env loop. Per env (and learner) the benchmark reports the
actuator cycle, the action cycle, the observation age and the action latency (defined in ``looptiming``): median,
IQR, p99, max and count, as a table, ``--json`` records and ``--plot`` box plots.

Scenarios:

- ``single``: the rx200 sim (10 Hz), action cycle 0.8 s, learned by SB3's synchronous TD3 and then by the
  asynchronous TD3 learner, one after the other in the same run (the paper's Figures 8 and 9).
- ``concurrent`` (the default): rx200 sim, rx200 emulated real, ned2 sim (25 Hz), ned2 emulated real, at once,
  under one learner (default the asynchronous one; the paper's Figure 10).
- ``turn-based``: the rx200 task in real-time mode, then as the turn-based env of a real arm (``turn_based=True,
  clock="wall"``: no env loop; each step sends one command, waits the action cycle and builds the returns from the
  newest joint state received), the same number of steps of a scripted agent on the same wall clock.
- ``sweep``: env-loop rates 1 to 100 Hz (action cycle 0.8 s), and action cycles 100 to 1400 ms (10 Hz), with a
  scripted agent: timing only.

``--backend ray`` (``single`` and ``concurrent``): every env's worker placed by Ray instead of started here, the steps
over our tcp between the nodes; without ``--ray-address``, on a local cluster started for the run: a head (the agent
and the learner) and one node per arm type, each advertising a resource the arm's envs ask for (``RAY_ARM_NODES``).
On a shared host run it in a network namespace, where Ray cannot bind the host's interfaces (docs/scaling.md).

``--duration`` is the wall time of each phase (each learner, mode or sweep point); learners get
``learning_starts`` small so that they train during a short run. TD3 follows the paper's hyperparameters.

Under load (``--load cpu gil torch gc``, with ``single`` or ``concurrent``): the scenario runs once per load and
scheduling class (``--sched rt off``: the ``UNIROS_LOOP_PRIORITY`` the workers and the acting thread start with),
and a load table follows the main one (``LOADS``):

- ``cpu``: one process per core spins at normal priority (nice 0) beside everything;
- ``gil``: a thread in the agent's process holds the GIL in long stretches (``sum(range(N))``, one C call that
  never lets the GIL go, ~10-30 ms each here), with no pause in between;
- ``torch``: the learner's updates use as many torch threads as the machine has cores;
- ``gc``: a thread in the agent's process allocates a few hundred thousand small objects and collects them
  (``gc.collect()``), again and again.

The load table gives per env the actuator cycle's median, p99 and max and the action cycle's median and IQR, and
checks the actuator goal under load with the real-time class (``loads.LOAD_P99_GOAL_MS``,
``loads.LOAD_MAX_GOAL_MS`` above the period).

Idle cores are kept awake during a run (``priority.cores_kept_awake``: one SCHED_IDLE busy-poll process per core,
which any other thread preempts), as cyclictest keeps cores out of idle states: on a virtual machine a halted core
goes back to the host, and waking it for a tick costs the host's scheduling delay (hypervisor steal; the table's
footer prints its share). ``--allow-idle`` measures the machine as it idles by default. The footer also counts
the real-time threads of other processes on the host and the CPU time they used during the run: at their
priorities they delay this run's loops whatever its own class.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib.util
import logging
import math
import os
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from uniros_async.bench._environ import environ_set
from uniros_async.bench.common import cpu_times, real_time_elsewhere, real_time_threads, report, steal_percent
from uniros_async.bench.loads import LOADS, LoadStats, format_load_table, open_load
from uniros_async.bench.looptiming import (
    ARM_OF_ENV_ID,
    ScriptedReachAgent,
    Series,
    format_table,
    loop_metrics,
    since,
    to_records,
)
from uniros_async.errors import ConfigError
from uniros_async.priority import cores_kept_awake, gil_switch_interval, real_time_thread

__all__ = ["LEARNERS", "LOADS", "SCENARIOS", "SCHED_CLASSES", "LatencyBenchConfig", "main", "open_load"]

logger = logging.getLogger(__name__)

SCENARIOS = ("single", "concurrent", "turn-based", "sweep")
SCHED_CLASSES = ("rt", "off")
"""``UNIROS_LOOP_PRIORITY`` values a load run compares: the real-time class when permitted, and none."""
LEARNERS = ("sb3-td3", "async-td3")
# the default run (concurrent) needs 15-40 s beside its phase (torch, 4 workers, 2 emulated arms, the plot)
DEFAULT_DURATION_S = {"single": 60.0, "concurrent": 80.0, "turn-based": 60.0, "sweep": 12.0}
DEFAULT_LEARNERS = {"single": ("sb3-td3", "async-td3"), "concurrent": ("async-td3",)}
SWEEP_RATES_HZ = (1.0, 5.0, 10.0, 20.0, 50.0, 100.0)
SWEEP_CYCLES_S = (0.1, 0.2, 0.4, 0.8, 1.4)
RX200 = "uniros/Rx200Reach-v0"
NED2 = "uniros/Ned2Reach-v0"
BACKENDS = ("local", "ray")
RAY_ARM_NODES = {RX200: "rx200_pc", NED2: "ned2_pc"}
"""``--backend ray`` without ``--ray-address``: the local cluster's nodes besides the head (where the agent and the
learner run), one per arm type, each advertising this resource (2 of it, and 2 CPUs); each env's worker asks for 1
of its arm's, as a lab's arm PCs would (docs/howto/cluster.md)."""
CONCURRENT_ENVS: tuple[tuple[str, str], ...] = (
    (RX200, "sim"),
    (RX200, "emulated-real"),
    (NED2, "sim"),
    (NED2, "emulated-real"),
)
PLOT_SUFFIXES = (".png", ".svg", ".pdf")
ASYNC_TD3_MODULE = "uniros_async.training.async_td3"


@dataclasses.dataclass(frozen=True, kw_only=True)
class LatencyBenchConfig:
    """What ``uniros bench latency`` runs.

    Attributes:
        scenario: one of ``SCENARIOS``.
        duration_s: wall seconds of each phase; None: the scenario's default (``DEFAULT_DURATION_S``).
        learners: for ``single`` and ``concurrent``: which of ``LEARNERS`` to run; None: the scenario's default.
        action_cycle_s: the action cycle of ``single``, ``concurrent`` and ``turn-based``.
        think_ms: the scripted agent thinks a uniform 0 to this many ms before each step (``turn-based``, ``sweep``).
        learning_starts: steps before a learner starts training.
        seed: seeds the envs, the learners and the scripted agent.
        json_path: write the records there as JSON.
        plot_path: write box plots there (.png, .svg or .pdf; needs matplotlib).
        progress: show a progress bar (tqdm, on stderr).
        keep_cores_awake: run ``priority.cores_kept_awake`` (one SCHED_IDLE busy-poll process per core) during the
            scenario, as cyclictest keeps cores out of idle states; False lets idle cores halt (``--allow-idle``).
        loads: run the scenario under each of these ``LOADS`` (``single`` and ``concurrent`` only); () for none.
        sched_classes: with ``loads``: the ``SCHED_CLASSES`` to run each load under.
        backend: ``local`` (every env's worker on this machine) or ``ray`` (``single`` and ``concurrent``: every
            worker placed by Ray, ``RAY_ARM_NODES``; the agent and the learner stay here).
        ray_address: with ``ray``: the cluster (``HOST:PORT``; its scheduler places the workers); None: a local
            cluster started for the run, a head (the agent) and one node per arm type (``RAY_ARM_NODES``).
    """

    scenario: str = "concurrent"
    duration_s: float | None = None
    learners: tuple[str, ...] | None = None
    action_cycle_s: float = 0.8
    think_ms: float = 50.0
    learning_starts: int = 10
    seed: int = 0
    json_path: str | None = None
    plot_path: str | None = None
    progress: bool = True
    keep_cores_awake: bool = True
    loads: tuple[str, ...] = ()
    sched_classes: tuple[str, ...] = SCHED_CLASSES
    backend: str = "local"
    ray_address: str | None = None

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ConfigError(f"backend must be one of {list(BACKENDS)}, got {self.backend!r}")
        if self.backend == "ray" and (self.scenario not in DEFAULT_LEARNERS or self.loads):
            raise ConfigError(
                f"--backend ray runs a learner scenario ({sorted(DEFAULT_LEARNERS)}) without --load, got scenario "
                f"{self.scenario!r}{' with --load' if self.loads else ''}"
            )
        if self.scenario not in SCENARIOS:
            raise ConfigError(f"unknown scenario {self.scenario!r}; choose from {list(SCENARIOS)}")
        bad_loads = [x for x in self.loads if x not in LOADS]
        if bad_loads or len(set(self.loads)) != len(self.loads):
            raise ConfigError(f"loads: expected distinct ones of {list(LOADS)}, got {list(self.loads)}")
        if self.loads and self.scenario not in DEFAULT_LEARNERS:
            raise ConfigError(
                f"--load runs a learner scenario ({sorted(DEFAULT_LEARNERS)}), not {self.scenario!r}: the loads "
                "stand beside a learner"
            )
        bad_cls = [x for x in self.sched_classes if x not in SCHED_CLASSES]
        if bad_cls or not self.sched_classes or len(set(self.sched_classes)) != len(self.sched_classes):
            raise ConfigError(
                f"sched_classes: expected distinct ones of {list(SCHED_CLASSES)}, got {list(self.sched_classes)}"
            )
        if self.duration_s is not None and not (math.isfinite(self.duration_s) and self.duration_s > 0):
            raise ConfigError(f"duration_s must be a number > 0, got {self.duration_s}")
        if self.learners is not None:
            if self.scenario not in DEFAULT_LEARNERS:
                raise ConfigError(
                    f"scenario {self.scenario!r} runs a scripted agent (timing only) and takes no learner; "
                    f"learners go with {sorted(DEFAULT_LEARNERS)}"
                )
            bad = [x for x in self.learners if x not in LEARNERS]
            if bad or not self.learners:
                raise ConfigError(f"unknown learner(s) {bad or list(self.learners)}; choose from {list(LEARNERS)}")
            if len(set(self.learners)) != len(self.learners):
                raise ConfigError(f"learners repeated: {list(self.learners)}")
        if not 0 < self.action_cycle_s <= 60:
            raise ConfigError(f"action_cycle_s must be in (0, 60], got {self.action_cycle_s}")
        if self.think_ms < 0:
            raise ConfigError(f"think_ms must be >= 0, got {self.think_ms}")
        shortest = min(SWEEP_CYCLES_S) if self.scenario == "sweep" else self.action_cycle_s
        if self.think_ms / 1e3 >= shortest:
            raise ConfigError(
                f"think_ms={self.think_ms} must be below the shortest action cycle ({shortest * 1e3:g} ms)"
            )
        if self.learning_starts < 1:
            raise ConfigError(f"learning_starts must be >= 1, got {self.learning_starts}")
        if self.plot_path is not None and Path(self.plot_path).suffix.lower() not in PLOT_SUFFIXES:
            raise ConfigError(f"plot path {self.plot_path!r} must end with one of {list(PLOT_SUFFIXES)}")

    @property
    def phase_s(self) -> float:
        """Wall seconds of each phase."""
        return self.duration_s if self.duration_s is not None else DEFAULT_DURATION_S[self.scenario]

    @property
    def run_learners(self) -> tuple[str, ...]:
        """The learners this run trains (empty for the scripted scenarios)."""
        if self.learners is not None:
            return self.learners
        return DEFAULT_LEARNERS.get(self.scenario, ())

    def phases(self) -> int:
        """How many timed phases the scenario has (for the progress bar)."""
        if self.scenario == "sweep":
            return len(_sweep_points())
        if self.scenario == "turn-based":
            return 2  # real-time, then turn-based, both on the wall clock
        per_load = max(1, len(self.run_learners))
        return per_load * len(self.loads) * len(self.sched_classes) if self.loads else per_load


def _sweep_points() -> list[tuple[float, float]]:
    """(env-loop rate Hz, action cycle s) of the sweep: the rates at 0.8 s, then the cycles at 10 Hz (no repeat)."""
    points = [(r, 0.8) for r in SWEEP_RATES_HZ]
    points += [(10.0, c) for c in SWEEP_CYCLES_S if (10.0, c) not in points]
    return points


def async_td3_available() -> bool:
    """Whether the asynchronous TD3 learner (``uniros_async.training.async_td3``) is in this installation."""
    try:
        return importlib.util.find_spec(ASYNC_TD3_MODULE) is not None
    except ModuleNotFoundError:  # pragma: no cover - uniros_async.training itself missing
        return False


# ------------------------------------------------------------------------------------------ progress


class _Progress:
    """A tqdm bar over the scenario's timed seconds, advanced by wall time from a thread (learners own the loop)."""

    def __init__(self, total_s: float, enabled: bool, desc: str) -> None:
        self._bar: Any = None
        self._base = 0.0
        self._t0: float | None = None
        self._cap = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if enabled:
            from uniros_async._progress import progress_bar

            self._bar = progress_bar(
                total=round(total_s), desc=desc, unit="s", leave=False, bar_format="{l_bar}{bar}| {n:.0f}/{total_fmt} s"
            )
            self._thread = threading.Thread(target=self._run, name="latency bench progress", daemon=True)
            self._thread.start()

    @contextlib.contextmanager
    def phase(self, seconds: float) -> Iterator[None]:
        """Count the wall time of the block, up to ``seconds``, then move the bar past it."""
        self._t0, self._cap = time.monotonic(), seconds
        try:
            yield
        finally:
            self._t0 = None
            self._base += seconds
            self._show(self._base)

    def _run(self) -> None:
        while not self._stop.wait(0.5):
            t0 = self._t0
            if t0 is not None:
                self._show(self._base + min(self._cap, time.monotonic() - t0))

    def _show(self, n: float) -> None:
        if self._bar is not None:
            self._bar.n = min(float(self._bar.total), n)
            self._bar.refresh()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        if self._bar is not None:
            self._bar.close()


# ------------------------------------------------------------------------------------------ learners


def _td3_kwargs(n_actions: int, cfg: LatencyBenchConfig) -> dict[str, Any]:
    """The paper's TD3 hyperparameters, with ``learning_starts`` small so a short run trains."""
    from stable_baselines3.common.noise import NormalActionNoise

    return {
        "learning_rate": 3e-4,
        "buffer_size": 100_000,
        "learning_starts": cfg.learning_starts,
        "batch_size": 256,
        "tau": 0.005,
        "gamma": 0.99,
        "train_freq": 1,
        "gradient_steps": 1,
        "policy_delay": 2,
        "target_policy_noise": 0.2,
        "target_noise_clip": 0.5,
        "action_noise": NormalActionNoise(np.zeros(n_actions), 0.1 * np.ones(n_actions)),
        "policy_kwargs": {"net_arch": [400, 300]},
        "seed": cfg.seed,
        "device": "cpu",
        "verbose": 0,
    }


def _learner_class(name: str) -> type:
    if name == "sb3-td3":
        from stable_baselines3 import TD3

        return TD3
    if not async_td3_available():
        raise ConfigError(
            f"learner 'async-td3' needs {ASYNC_TD3_MODULE}, which this installation lacks; "
            "run with --learner sb3-td3, or install a version with the asynchronous learner"
        )
    import importlib

    cls: type = importlib.import_module(ASYNC_TD3_MODULE).AsyncTD3
    return cls


def _check_learners(cfg: LatencyBenchConfig) -> None:
    """Fail before any process starts when a learner is unavailable."""
    for name in cfg.run_learners:
        if name == "async-td3" and not async_td3_available():
            _learner_class(name)  # raises the ConfigError


def _step_recorder(venv: Any) -> Any:
    """An SB3 VecEnvWrapper that records, per step, when the agent got the returns and which envs were done."""
    from stable_baselines3.common.vec_env import VecEnvWrapper

    class StepRecorder(VecEnvWrapper):
        def __init__(self, venv: Any) -> None:
            super().__init__(venv)
            self.recv_ns: list[int] = []
            self.dones: list[np.ndarray] = []

        def reset(self) -> Any:
            return self.venv.reset()

        def step_wait(self) -> Any:
            obs, rewards, dones, infos = self.venv.step_wait()
            self.recv_ns.append(time.monotonic_ns())
            self.dones.append(np.asarray(dones, dtype=bool).copy())
            return obs, rewards, dones, infos

    return StepRecorder(venv)


def _run_learner(
    name: str,
    vec: Any,
    labels: Sequence[tuple[str, str]],
    cfg: LatencyBenchConfig,
    progress: _Progress,
    *,
    torch_threads: int = 1,
    tag: str = "",
    load: str | None = None,
) -> list[Series]:
    """Train learner ``name`` on ``vec`` (a UnirosVectorEnv) for one phase, under ``load`` (``open_load``) if given;
    the timing of each of its envs (``tag`` is appended to the learner's label)."""
    import torch
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.logger import Logger

    # one thread: beside env loops on 2 cores, more threads stall updates (the torch load asks for more)
    torch.set_num_threads(torch_threads)
    cls = _learner_class(name)
    rec = _step_recorder(vec.as_sb3())
    n_actions = int(np.prod(vec.single_action_space.shape))
    kwargs = _td3_kwargs(n_actions, cfg)
    if name == "async-td3":
        kwargs["torch_threads"] = torch_threads
    model = cls("MlpPolicy", rec, **kwargs)
    # the bench reads nothing SB3 logs: without a logger of its own, every learn() makes a /tmp/SB3-<time> folder
    model.set_logger(Logger(folder=None, output_formats=[]))
    steps = max(2, math.ceil(cfg.phase_s / cfg.action_cycle_s))

    class _Deadline(BaseCallback):
        """Stops learning at the phase's end even when steps overran their cycle."""

        def __init__(self, end: float) -> None:
            super().__init__()
            self.end = end

        def _on_step(self) -> bool:
            return time.monotonic() < self.end

    before = vec.call("timing_snapshot")  # not clear=True: see stats.since
    with progress.phase(cfg.phase_s):
        # + 30 s: learn()'s own start (its reset) must not cut the phase short; the step count ends it. The
        # asynchronous learner joins its update thread before learn() returns or raises.
        # the agent's acting thread runs real-time when permitted, like the env loops (uniros_async.priority)
        loaded = open_load(load) if load is not None else contextlib.nullcontext(LoadStats())
        with loaded as stats, real_time_thread(), gil_switch_interval():
            model.learn(total_timesteps=steps * vec.num_envs, callback=_Deadline(time.monotonic() + cfg.phase_s + 30.0))
    if stats.stretches_ms:
        logger.info(
            "%s load: the GIL held %.1f ms median, %.1f ms max per stretch (%d stretches)",
            load,
            float(np.median(stats.stretches_ms)),
            max(stats.stretches_ms),
            len(stats.stretches_ms),
        )
    snaps = [since(now, then) for now, then in zip(vec.call("timing_snapshot"), before, strict=True)]
    rates = vec.get_attr("env_loop_rate_hz")
    any_done = {k for k, d in enumerate(rec.dones) if bool(np.any(d))}
    out = []
    for (env, row), snap, rate in zip(labels, snaps, rates, strict=True):
        out.append(
            Series(
                env=env,
                learner=name + tag,
                samples=loop_metrics(snap, reset_after=any_done, recv_ns=rec.recv_ns),
                period_ms=1e3 / float(rate),
                action_cycle_ms=cfg.action_cycle_s * 1e3,
                row=row,
                step_overruns=int(snap.get("step_overruns", 0)),
            )
        )
    return out


def _env_label(env_id: str, robot: str) -> str:
    return f"{ARM_OF_ENV_ID[env_id]} {robot}"


def _run_learner_scenario(
    specs: Sequence[tuple[str, str]], cfg: LatencyBenchConfig, progress: _Progress
) -> list[Series]:
    from uniros_async.runtime import make_vec

    labels = [(_env_label(e, r), _env_label(e, r)) for e, r in specs]
    if cfg.loads:
        return _run_under_loads(specs, labels, cfg, progress)
    with _ray_cluster(cfg) as placement:
        vec = make_vec(  # absolute targets, as the recorded figures were measured (the task default is deltas)
            [(e, {"robot": r, **placement(e)}) for e, r in specs],
            action_cycle_s=cfg.action_cycle_s,
            action_mode="absolute",
            call_timeout_s=60.0,
        )
        try:
            out: list[Series] = []
            for name in cfg.run_learners:
                out += _run_learner(name, vec, labels, cfg, progress)
            return out
        finally:
            vec.close()


@contextlib.contextmanager
def _ray_cluster(cfg: LatencyBenchConfig) -> Iterator[Callable[[str], dict[str, Any]]]:
    """With ``backend="ray"``: connected to the cluster (a local one of ``RAY_ARM_NODES`` unless ``ray_address``)
    for the block; yields each env id's ``worker`` keyword ({} with the local backend)."""
    if cfg.backend != "ray":
        yield lambda env_id: {}
        return
    if cfg.ray_address is not None:
        from uniros_async.runtime.ray_backend import connect

        connect(cfg.ray_address)
        yield lambda env_id: {"worker": {"ray": {"address": cfg.ray_address}}}
        return
    from uniros_async.bench._ray_rows import local_cluster

    nodes = [{"num_cpus": 2, "resources": {name: 2}} for name in RAY_ARM_NODES.values()]
    with local_cluster(nodes) as address:
        logger.info("local Ray cluster at %s: the agent on the head, the workers on %s", address, nodes)
        yield lambda env_id: {"worker": {"ray": {"resources": {RAY_ARM_NODES[env_id]: 1}}}}


# ------------------------------------------------------------------------------------------ loads


def _run_under_loads(
    specs: Sequence[tuple[str, str]], labels: Sequence[tuple[str, str]], cfg: LatencyBenchConfig, progress: _Progress
) -> list[Series]:
    from uniros_async.runtime import make_vec

    n_cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    out: list[Series] = []
    for cls in cfg.sched_classes:
        # the workers started in the block, and the acting thread, take that class
        with environ_set("UNIROS_LOOP_PRIORITY", cls):
            vec = make_vec(  # absolute targets, as in _run_learner_scenario
                [(e, {"robot": r}) for e, r in specs],
                action_cycle_s=cfg.action_cycle_s,
                action_mode="absolute",
                call_timeout_s=60.0,
            )
            try:
                for load in cfg.loads:
                    for name in cfg.run_learners:
                        threads = n_cores if load == "torch" else 1
                        out += _run_learner(
                            name, vec, labels, cfg, progress, torch_threads=threads, tag=f" +{load} {cls}", load=load
                        )
            finally:
                vec.close()
    return out


# ------------------------------------------------------------------------------------------ scripted agents


def _run_scripted(
    env_kwargs: dict[str, Any], label: str, row: str, box: str, steps: int, cfg: LatencyBenchConfig, *, wall: bool
) -> Series:
    """``steps`` steps of the scripted agent on the rx200 reach env in a worker; its timing."""
    from uniros_async.runtime import make

    agent = ScriptedReachAgent("rx200", think_ms=cfg.think_ms, seed=cfg.seed)
    # a ProxyEnv (its call() reaches the env in the worker); absolute targets: the scripted agent aims at points
    env: Any = make(RX200, **{"action_mode": "absolute", **env_kwargs})
    try:
        env.reset(seed=cfg.seed)
        env.call("timing_snapshot", clear=True)
        recv_ns: list[int] = []
        reset_after: set[int] = set()
        for k in range(steps):
            _, _, terminated, truncated, _ = env.step(agent.act())
            recv_ns.append(time.monotonic_ns())
            if terminated or truncated:
                reset_after.add(k)
                env.reset()
        snap = env.call("timing_snapshot")
        rate = float(env.call("env_loop_rate_hz"))
    finally:
        env.close()
    return Series(
        env=label,
        learner="scripted",
        samples=loop_metrics(snap, reset_after=reset_after, recv_ns=recv_ns if wall else None),
        period_ms=1e3 / rate,
        action_cycle_ms=float(env_kwargs.get("action_cycle_s", cfg.action_cycle_s)) * 1e3,
        row=row,
        box=box,
        step_overruns=int(snap.get("step_overruns", 0)),
    )


def _run_turn_based(cfg: LatencyBenchConfig, progress: _Progress) -> list[Series]:
    steps = max(2, math.ceil(cfg.phase_s / cfg.action_cycle_s))
    kw = {"robot": "sim", "action_cycle_s": cfg.action_cycle_s}
    with progress.phase(cfg.phase_s):
        real_time = _run_scripted(kw, "rx200 sim real-time", "rx200 sim", "real-time", steps, cfg, wall=True)
    # the turn-based env of a real arm (openai_ros style) on the same wall clock: no env loop, one command per
    # step, returns built at the end of the cycle from the newest joint state received
    with progress.phase(cfg.phase_s):
        turn = _run_scripted(
            {**kw, "turn_based": True, "clock": "wall"},
            "rx200 sim turn-based",
            "rx200 sim",
            "turn-based",
            steps,
            cfg,
            wall=True,
        )
    return [real_time, turn]


def _run_sweep(cfg: LatencyBenchConfig, progress: _Progress) -> list[Series]:
    out = []
    for rate, cycle in _sweep_points():
        steps = max(2, math.ceil(cfg.phase_s / cycle))
        label = f"rx200 sim {rate:g} Hz {cycle * 1e3:g} ms"
        kw = {"robot": "sim", "action_cycle_s": cycle, "env_loop_rate_hz": rate}
        with progress.phase(cfg.phase_s):
            out.append(_run_scripted(kw, label, label, "scripted", steps, cfg, wall=True))
    return out


# ------------------------------------------------------------------------------------------ main


def run(config: LatencyBenchConfig) -> list[Series]:
    """Run the scenario and return its series (no printing); see ``main``.

    Raises:
        ConfigError: a learner that this installation lacks (before any process starts).
        WorkerError: an env's worker failed (its traceback attached); every worker is stopped.
    """
    _check_learners(config)
    progress = _Progress(config.phase_s * config.phases(), config.progress, f"latency bench ({config.scenario})")
    try:
        if config.scenario == "single":
            return _run_learner_scenario([(RX200, "sim")], config, progress)
        if config.scenario == "concurrent":
            return _run_learner_scenario(CONCURRENT_ENVS, config, progress)
        if config.scenario == "turn-based":
            return _run_turn_based(config, progress)
        return _run_sweep(config, progress)
    finally:
        progress.close()


def main(config: LatencyBenchConfig, *, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Run the scenario, print the table, write JSON and the plot when asked; returns the records.

    Raises:
        ConfigError: a learner this installation lacks, or a plot asked for without matplotlib (both before any
            process starts).
        WorkerError: an env's worker failed.
    """
    if config.plot_path is not None and importlib.util.find_spec("matplotlib") is None:
        raise ConfigError("--plot needs matplotlib: pip install matplotlib (or the [bench] extra)")
    awake: contextlib.AbstractContextManager[list[int]] = (
        cores_kept_awake() if config.keep_cores_awake else contextlib.nullcontext([])
    )
    with awake as pollers:
        cpu0, rt0 = cpu_times(), real_time_threads(exclude_tree_of=os.getpid())
        series = run(config)
        steal = steal_percent(cpu0, cpu_times())
        elsewhere = real_time_elsewhere(rt0, real_time_threads(exclude_tree_of=os.getpid()))
    records = to_records(config.scenario, series)
    title = f"uniros bench latency --scenario {config.scenario} --duration {config.phase_s:g}"
    if config.backend == "ray":
        title += " --backend ray" + (f" --ray-address {config.ray_address}" if config.ray_address else "")
    machine = (
        ""
        if steal is None
        else (
            f"\nhypervisor steal during the run: {steal:.1f} % of CPU time (the VM's cores were taken away that long; "
            "above ~1 % expect late ticks no scheduling class can prevent)"
        )
    )
    machine += "\n" + elsewhere
    if pollers:
        machine += f"\nidle cores: kept awake by {len(pollers)} SCHED_IDLE poller(s) (--allow-idle lets them halt)"
    else:
        why = "no SCHED_IDLE here" if config.keep_cores_awake else "--allow-idle"
        machine += f"\nidle cores: allowed to halt ({why})"
    if config.loads:
        title += f" --load {' '.join(config.loads)} --sched {' '.join(config.sched_classes)}"
        machine += "\n\n" + format_load_table(series)
    report(f"{title}\n{format_table(series, records)}{machine}", records, config.json_path, log)
    if config.plot_path is not None:
        from uniros_async.bench._plot import box_plots

        box_plots(series, config.plot_path, title=title)
        log(f"wrote {config.plot_path}")
    return records
