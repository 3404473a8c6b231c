"""``uniros eval --sweep``: success against imperfection strength, each knob alone and all together.

For every curve (a knob of ``uniros_async.sim.imperfections``, or ``"all"``) and every strength, the policy is
evaluated over ``episodes`` episodes on an env whose knob (``"all"``: every knob) is at that strength, a new arm
every episode: the env's ``randomize`` with the range ``[strength, strength]``, so each episode draws its own
calibration offsets, dynamics perturbation and noise at that strength, from the evaluation's seed. Strength 0 is
the nominal sim. The results go to a JSON file (each point with its 95 % Wilson interval) and a matplotlib plot of
success rate against strength, one line a curve.

``plot_compare`` draws the ``"all"`` curves of several policies' sweeps, one panel per env id, each point with its
Wilson interval (``python -m uniros_async.training.sweep --out PNG SWEEP.json ...``).
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from uniros_async.errors import ConfigError
from uniros_async.sim.imperfections import KNOBS, MAX_STRENGTH

__all__ = ["CURVES", "STRENGTHS", "plot_compare", "plot_sweep", "sweep_checkpoint", "wilson", "write_sweep"]

STRENGTHS = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0)
CURVES = ("all", *KNOBS)


def wilson(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The Wilson score interval of a success rate (``z`` 1.96: 95 %), as (low, high) fractions.

    Raises:
        ConfigError: ``n`` < 1 or ``successes`` outside [0, n].
    """
    if n < 1 or not 0 <= successes <= n:
        raise ConfigError(f"wilson: expected 0 <= successes <= n and n >= 1, got {successes}/{n}")
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


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
        ``{"checkpoint", "label", "env_id", "kwargs", "episodes", "seed", "strengths", "curves": {curve: [point,
        ...]}}``, a point being ``{"strength", "success_rate", "successes", "episodes", "wilson95",
        "mean_return", "mean_length"}``.

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
            knobs = KNOBS if curve == "all" else (curve,)
            arm = {"randomize": {k: [s, s] for k in knobs}} if s else {}
            r = evaluate_checkpoint(checkpoint, env_id, {**kwargs, **arm}, episodes=episodes, seed=seed, label=label)
            point = {
                "strength": s,
                "success_rate": r.success_rate,
                "successes": r.successes,
                "episodes": r.episodes,
                "wilson95": list(wilson(r.successes, r.episodes)),
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
        "label": label,
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


def plot_compare(
    results: Sequence[dict[str, Any]], out: str | Path, *, curve: str = "all", title: str | None = None
) -> Path:
    """One panel per env id: success (%) against strength of ``curve``, a line per result (a policy's sweep,
    labelled by its ``label`` or checkpoint), each point with its 95 % Wilson interval.

    Raises:
        ConfigError: a result without ``curve``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    envs: dict[str, list[dict[str, Any]]] = {}
    for res in results:
        if curve not in res["curves"]:
            raise ConfigError(f"plot_compare: {res['checkpoint']} has no curve {curve!r}; it has {list(res['curves'])}")
        envs.setdefault(res["env_id"], []).append(res)
    fig, axes = plt.subplots(1, len(envs), figsize=(6 * len(envs), 4.5), squeeze=False, sharey=True)
    for ax, (env_id, group) in zip(axes[0], envs.items(), strict=True):
        for res in group:
            points = res["curves"][curve]
            xs = [p["strength"] for p in points]
            ys = [100.0 * p["success_rate"] for p in points]
            lo = [100.0 * (p["success_rate"] - wilson(p["successes"], p["episodes"])[0]) for p in points]
            hi = [100.0 * (wilson(p["successes"], p["episodes"])[1] - p["success_rate"]) for p in points]
            label = res.get("label") or Path(res["checkpoint"]).name
            ax.errorbar(xs, ys, yerr=[lo, hi], marker="o", capsize=4, lw=1.8, label=label)
        ax.set_title(env_id)
        ax.set_xlabel(f"strength of {curve} knobs (0: the sim, 1: a real arm's estimate)")
        ax.set_ylim(-3, 103)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="lower left")
    axes[0][0].set_ylabel(f"success over {results[0]['episodes']} episodes (%), 95 % Wilson interval")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(out)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m uniros_async.training.sweep --out PNG SWEEP.json ...``: ``plot_compare`` of sweeps' JSON files."""
    parser = argparse.ArgumentParser(prog="python -m uniros_async.training.sweep", description=plot_compare.__doc__)
    parser.add_argument("sweeps", nargs="+", help="JSON files written by uniros eval --sweep --json")
    parser.add_argument("--out", required=True, help="the PNG to write")
    parser.add_argument("--curve", default="all", help="the curve to compare (default: all knobs together)")
    parser.add_argument("--labels", nargs="+", default=None, help="a label per JSON file (default: their own)")
    parser.add_argument("--title", default=None)
    args = parser.parse_args(argv)
    results = [json.loads(Path(p).read_text()) for p in args.sweeps]
    if args.labels is not None:
        if len(args.labels) != len(results):
            parser.error(f"--labels: expected {len(results)} labels (one per JSON file), got {len(args.labels)}")
        results = [{**r, "label": lab} for r, lab in zip(results, args.labels, strict=True)]
    print(f"wrote {plot_compare(results, args.out, curve=args.curve, title=args.title)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
