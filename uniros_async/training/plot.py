"""Learning curves of runs, as in the UniROS paper's figures: mean episode length, mean return and success rate
against env steps (or, ``x="minutes"``, against wall-clock minutes since training started: real-time runs), one
panel each, written to PNG.

Training curves are moving averages over ``window`` training episodes (episodes.csv, with exploration noise);
evaluation points (eval.csv: the deterministic policy on fresh episodes) are drawn as dots joined by a dashed
line in the same colour. Several runs (a sweep) are overlaid; a multi-task run draws one curve per env.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from uniros_async.errors import ConfigError

__all__ = ["plot_runs", "read_curves"]

X_AXES = {"steps": ("step", 1.0), "minutes": ("wall_s", 1 / 60)}  # x: the logs' column and its scale
PANELS = (
    ("length", "mean_length", "mean episode length"),
    ("return", "mean_return", "mean return"),
    ("success", "success_rate", "success rate"),
)


def _read_csv(path: Path) -> list[dict[str, str]]:
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def read_curves(run_dir: str | Path) -> tuple[dict[str, dict[str, np.ndarray]], dict[str, dict[str, np.ndarray]]]:
    """(training episodes, evaluations) of a run, per task: arrays keyed by column.

    Raises:
        ConfigError: the directory has neither episodes.csv nor eval.csv.
    """
    d = Path(run_dir)
    eps, evs = _read_csv(d / "episodes.csv"), _read_csv(d / "eval.csv")
    if not eps and not evs:
        raise ConfigError(f"{str(d)!r} is not a run directory with episodes.csv or eval.csv (or both are empty)")

    def group(rows: list[dict[str, str]], cols: Sequence[str]) -> dict[str, dict[str, np.ndarray]]:
        out: dict[str, dict[str, list[float]]] = {}
        for r in rows:
            g = out.setdefault(r["task"], {c: [] for c in cols})
            for c in cols:
                g[c].append(float(r[c]) if r.get(c) not in (None, "") else np.nan)  # runs older than a column
        return {t: {c: np.asarray(v) for c, v in g.items()} for t, g in out.items()}

    return (
        group(eps, ("step", "return", "length", "success", "wall_s")),
        group(evs, ("step", "success_rate", "mean_return", "mean_length", "wall_s")),
    )


def _moving(x: np.ndarray, window: int) -> np.ndarray:
    if len(x) == 0:
        return x
    c = np.cumsum(np.insert(x.astype(np.float64), 0, 0.0))
    n = np.minimum(np.arange(1, len(x) + 1), window)  # a shorter window at the start
    return np.asarray((c[1:] - c[np.arange(len(x)) + 1 - n]) / n)


def plot_runs(
    run_dirs: Sequence[str | Path],
    *,
    out: str | Path | None = None,
    labels: Sequence[str] | None = None,
    window: int = 20,
    title: str | None = None,
    x: str = "steps",
    tasks: Sequence[str] | None = None,
) -> Path:
    """Draw the three panels for every run (and task) into one PNG; returns its path.

    Args:
        out: PNG path; default ``<first run>/curves.png``.
        labels: a legend label per run (default: the directory names).
        window: training episodes per moving average.
        x: ``"steps"`` (env steps, summed over the envs of a run) or ``"minutes"`` (wall-clock minutes since
            training started, from the logs' ``wall_s``).
        tasks: draw only these envs of each run (the names in its logs' ``task`` column, e.g. ``ned2_sim``);
            None: every env.

    Raises:
        ConfigError: a directory without logs, a label count that does not match the runs, ``x="minutes"`` for
            a run whose logs have no wall-clock times, or a task that none of the runs has.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if labels is not None and len(labels) != len(run_dirs):
        raise ConfigError(f"--labels: {len(labels)} labels for {len(run_dirs)} runs")
    if window < 1:
        raise ConfigError(f"window must be >= 1, got {window}")
    if x not in X_AXES:
        raise ConfigError(f"x must be one of {tuple(X_AXES)}, got {x!r}")
    xcol, xscale = X_AXES[x]
    names = list(labels) if labels else [Path(r).name for r in run_dirs]
    curves = [read_curves(r) for r in run_dirs]
    if x == "minutes":
        for run, (eps, evs) in zip(run_dirs, curves, strict=True):
            if any(np.isnan(g["wall_s"]).any() for g in [*eps.values(), *evs.values()]):
                raise ConfigError(f"{str(run)!r}: its logs have no wall_s column (a run older than it); use x='steps'")
    if tasks is not None:
        known = list(dict.fromkeys(t for eps, evs in curves for t in [*eps, *evs]))
        missing = [t for t in tasks if t not in known]
        if missing:
            raise ConfigError(f"--tasks: no run has {missing}; the runs' tasks are {known}")
        curves = [
            ({t: g for t, g in eps.items() if t in tasks}, {t: g for t, g in evs.items() if t in tasks})
            for eps, evs in curves
        ]
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.6))
    colors: Any = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    k = 0
    for name, (eps, evs) in zip(names, curves, strict=True):
        tasks = list(dict.fromkeys([*eps, *evs]))
        for task in tasks:
            color = colors[k % len(colors)]
            k += 1
            lab = name if len(tasks) == 1 else (task if len(curves) == 1 else f"{name} {task}")
            e, v = eps.get(task), evs.get(task)
            for ax, (col, ecol, _) in zip(axes, PANELS, strict=True):
                if e is not None and len(e["step"]):
                    ex = e[xcol] * xscale
                    ax.plot(ex, _moving(e[col], window), color=color, lw=1.4, label=f"{lab} (train)")
                if v is not None and len(v["step"]):
                    vx = v[xcol] * xscale
                    ax.plot(vx, v[ecol], color=color, lw=0.9, ls="--", marker="o", ms=3, label=f"{lab} (eval)")
    for ax, (_, _, ylabel) in zip(axes, PANELS, strict=True):
        ax.set_xlabel("env steps" if x == "steps" else "wall-clock minutes")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[2].set_ylim(-0.02, 1.02)
    handles, leg = axes[2].get_legend_handles_labels()
    fig.legend(handles, leg, loc="lower center", ncol=min(4, max(1, len(leg))), fontsize=8, frameon=False)
    fig.suptitle(
        title or ", ".join(names) + f"  (train: moving average of {window} episodes; eval: deterministic)", fontsize=10
    )
    rows = (len(leg) + 3) // 4
    fig.tight_layout(rect=(0, 0.04 + 0.035 * rows, 1, 0.95))
    path = Path(out) if out else Path(run_dirs[0]) / "curves.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
