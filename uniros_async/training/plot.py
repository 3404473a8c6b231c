"""Learning curves of runs, as in the UniROS paper's figures: mean episode length, mean return and success rate
against env steps, one panel each, written to PNG.

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
                g[c].append(float(r[c]))
        return {t: {c: np.asarray(v) for c, v in g.items()} for t, g in out.items()}

    return (
        group(eps, ("step", "return", "length", "success")),
        group(evs, ("step", "success_rate", "mean_return", "mean_length")),
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
) -> Path:
    """Draw the three panels for every run (and task) into one PNG; returns its path.

    Args:
        out: PNG path; default ``<first run>/curves.png``.
        labels: a legend label per run (default: the directory names).
        window: training episodes per moving average.

    Raises:
        ConfigError: a directory without logs, or a label count that does not match the runs.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if labels is not None and len(labels) != len(run_dirs):
        raise ConfigError(f"--labels: {len(labels)} labels for {len(run_dirs)} runs")
    if window < 1:
        raise ConfigError(f"window must be >= 1, got {window}")
    names = list(labels) if labels else [Path(r).name for r in run_dirs]
    curves = [read_curves(r) for r in run_dirs]
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
                    ax.plot(e["step"], _moving(e[col], window), color=color, lw=1.4, label=f"{lab} (train)")
                if v is not None and len(v["step"]):
                    ax.plot(v["step"], v[ecol], color=color, lw=0.9, ls="--", marker="o", ms=3, label=f"{lab} (eval)")
    for ax, (_, _, ylabel) in zip(axes, PANELS, strict=True):
        ax.set_xlabel("env steps")
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
