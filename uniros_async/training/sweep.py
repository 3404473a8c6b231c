"""``uniros eval --sweep``: success against imperfection strength, each knob alone and all together.

For every curve (a knob of ``uniros_async.sim.imperfections``, or ``"all"``) and every strength, the policy is
evaluated over ``episodes`` episodes on an env with ``imperfections={knob: strength}`` (``"all"``: every knob at
that strength); the results go to a JSON file and a matplotlib plot of success rate against strength, one line a
curve. The env must run its arm in its own process on the sim clock (``robot="sim"`` or ``"emulated-real"``,
``clock="sim"``).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from uniros_async.errors import ConfigError
from uniros_async.sim.imperfections import KNOBS, MAX_STRENGTH

__all__ = ["CURVES", "STRENGTHS", "plot_sweep", "sweep_checkpoint"]

STRENGTHS = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0)
CURVES = ("all", *KNOBS)


def _check(curves: Sequence[str], strengths: Sequence[float]) -> None:
    unknown = [c for c in curves if c not in CURVES]
    if unknown:
        raise ConfigError(f"--sweep-knobs: unknown {unknown}; expected some of {list(CURVES)}")
    bad = [s for s in strengths if not 0.0 <= s <= MAX_STRENGTH]
    if bad or not strengths:
        raise ConfigError(f"--strengths: expected values in [0, {MAX_STRENGTH}], got {list(strengths)}")


def sweep_checkpoint(
    checkpoint: str | Path,
    env_id: str,
    kwargs: dict[str, Any],
    *,
    episodes: int = 200,
    seed: int = 0,
    curves: Sequence[str] = CURVES,
    strengths: Sequence[float] = STRENGTHS,
    label: str | None = None,
    on_point: Callable[[str, float, Any], None] | None = None,
) -> dict[str, Any]:
    """Evaluate ``checkpoint`` on ``env_id`` at every strength of every curve.

    Strength 0 is the same env for every curve, so it is evaluated once and shared.

    Returns:
        ``{"checkpoint", "env_id", "kwargs", "episodes", "seed", "strengths", "curves": {curve: [point, ...]}}``,
        a point being ``{"strength", "success_rate", "successes", "episodes", "mean_return", "mean_length"}``.

    Raises:
        ConfigError: an unknown curve, a strength outside [0, 3], or ``imperfections`` already in ``kwargs``.
    """
    from uniros_async.training.evaluate import evaluate_checkpoint

    _check(curves, strengths)
    if "imperfections" in kwargs:
        raise ConfigError("--sweep sets imperfections itself: leave it out of --env-kwargs")
    kwargs = {k: v for k, v in kwargs.items() if k != "randomize"}  # fixed strengths, not a training range
    zero: dict[str, Any] | None = None
    out: dict[str, list[dict[str, Any]]] = {}
    for curve in curves:
        points = out.setdefault(curve, [])
        for s in strengths:
            if s == 0.0 and zero is not None:
                points.append(zero)
                continue
            imp: float | dict[str, float] = s if curve == "all" else {curve: s}
            r = evaluate_checkpoint(
                checkpoint, env_id, {**kwargs, "imperfections": imp}, episodes=episodes, seed=seed, label=label
            )
            point = {
                "strength": s,
                "success_rate": r.success_rate,
                "successes": r.successes,
                "episodes": r.episodes,
                "mean_return": r.mean_return,
                "mean_length": r.mean_length,
            }
            if s == 0.0:
                zero = point
            points.append(point)
            if on_point is not None:
                on_point(curve, s, point)
    return {
        "checkpoint": str(checkpoint),
        "env_id": env_id,
        "kwargs": kwargs,
        "episodes": episodes,
        "seed": seed,
        "strengths": list(strengths),
        "curves": out,
    }


def plot_sweep(results: Sequence[dict[str, Any]], out: str | Path, *, labels: Sequence[str] | None = None) -> Path:
    """One panel per result (a policy's sweep): success rate (%) against strength, a line per curve."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(results)
    fig, axes = plt.subplots(1, n, figsize=(6 * n, 4.5), squeeze=False, sharey=True)
    for i, res in enumerate(results):
        ax = axes[0][i]
        for curve, points in res["curves"].items():
            xs = [p["strength"] for p in points]
            ys = [100.0 * p["success_rate"] for p in points]
            ax.plot(xs, ys, marker="o", lw=2.5 if curve == "all" else 1.2, color="k" if curve == "all" else None)
            ax.lines[-1].set_label(curve)
        ax.set_title(labels[i] if labels else Path(res["checkpoint"]).name)
        ax.set_xlabel("strength (0: the sim, 1: a real arm's estimate)")
        ax.set_ylim(-3, 103)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel(f"success over {results[0]['episodes']} episodes (%)")
    axes[0][-1].legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    path = Path(out)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_sweep(result: dict[str, Any], json_path: str | Path) -> Path:
    """Write a sweep's result as JSON."""
    path = Path(json_path)
    path.write_text(json.dumps(result, indent=2))
    return path
