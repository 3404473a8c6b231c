"""Box plots of env-loop timing in the style of the UniROS paper's Figures 8 to 10 (matplotlib, no display needed).

One row of panels per env (``Series.row``), one column per metric, one box per learner or mode (``Series.box``)
on a shared axis, so that side-by-side learners compare directly. Boxes span the quartiles with the median
marked; whiskers reach 1.5 IQR; points beyond are drawn; dashed lines mark the loop period and action cycle.
"""

from __future__ import annotations

from collections.abc import Sequence

from uniros_async.bench.looptiming import METRICS, Series

__all__ = ["box_plots"]

TITLES = {
    "actuator_cycle": "actuator cycle",
    "action_cycle": "action cycle",
    "observation_age": "observation age",
    "action_latency": "action latency",
}


def box_plots(series: Sequence[Series], path: str, *, title: str = "") -> None:
    """Write the box plots of ``series`` to ``path`` (format from its suffix)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows: dict[str, list[Series]] = {}
    for s in series:
        rows.setdefault(s.row, []).append(s)
    n_rows = max(1, len(rows))
    fig, axes = plt.subplots(
        n_rows, len(METRICS), figsize=(3.4 * len(METRICS), 2.4 * n_rows + 0.6), squeeze=False, layout="constrained"
    )
    for r, (row, members) in enumerate(rows.items()):
        for c, metric in enumerate(METRICS):
            ax = axes[r][c]
            data = [s.samples.get(metric, []) or [float("nan")] for s in members]
            ax.boxplot(
                data,
                tick_labels=[s.box for s in members],
                whis=1.5,
                widths=0.5,
                flierprops={"marker": ".", "markersize": 3, "alpha": 0.5},
                medianprops={"color": "tab:red"},
            )
            ref = {"actuator_cycle": members[0].period_ms, "action_cycle": members[0].action_cycle_ms}.get(metric)
            if ref is not None:
                ax.axhline(ref, color="grey", lw=0.8, ls="--")
            ax.set_ylabel("ms")
            ax.grid(axis="y", alpha=0.3)
            ax.set_title(f"{row}: {TITLES[metric]}" if c == 0 else TITLES[metric], fontsize=9)
            ax.tick_params(labelsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)
