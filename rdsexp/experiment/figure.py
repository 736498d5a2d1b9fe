"""A run's static figure, `figure.png` beside its tables: what a headless machine (an SSH session, a cluster node)
shows of a run without the Rerun viewer.

Left, each loop's RMS sqrt(E||q_k||^2) over its paths, with its 95% band, against the exact curve of its ideal
loop (state feedback on the true plant, the `exact` table), the rate window shaded and, in the legend, the rate,
its interval and the verdict; right, the modeled mean and standard deviation of each component of xi with their
95% intervals (`modeling_uncertainty`), beside the plant file's law where there is one. Drawn from what the run
keeps (the loops' ||q_k||^2, the metrics and exact tables, the summary), in the run (`runner.record`) or from a
stored run (`squares_of`: its trajectories table; `rdsexp-runs plot RUN`). Matplotlib's object interface on an
Agg canvas: no pyplot state, no backend chosen for the caller.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from ..numerics.analysis import rms_band

LOOP_COLORS = {"closed_loop": "C0", "open_loop": "C1", "online": "C2"}


def squares_of(trajectories: pd.DataFrame) -> dict[str, np.ndarray]:
    """{loop: ||q_k||^2 (K+1, P)} from a stored trajectories table (rows experiment, k, path, q[i])."""
    q = [c for c in trajectories.columns if c.startswith("q[")]
    out = {}
    for name, rows in trajectories[trajectories["experiment"] != "identification"].groupby("experiment", sort=False):
        sq = rows.assign(sq=np.sum(rows[q].to_numpy() ** 2, axis=1)).pivot(index="k", columns="path", values="sq")
        out[str(name)] = sq.to_numpy()
    return out


def draw(path: Path, squares: dict[str, np.ndarray], metrics: pd.DataFrame, exact: pd.DataFrame,
         summary: dict) -> Path:
    """Write the run's figure to `path` (PNG); returns it. squares: {loop: ||q_k||^2 (K+1, P)}."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    loops = [row for row in metrics.itertuples() if row.experiment in squares]
    has_xi = bool(summary.get("xi_mean"))
    fig = Figure(figsize=(12 if loops and has_xi else 7, 5), layout="constrained")
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(2, 2 if loops and has_xi else 1, width_ratios=[1.6, 1] if loops and has_xi else None)
    if loops:
        loop_panel(fig.add_subplot(grid[:, 0]), loops, squares, exact, summary)
    if has_xi:
        column = 1 if loops else 0
        xi_panel(fig.add_subplot(grid[0, column]), fig.add_subplot(grid[1, column]), summary)
    title = f"{summary.get('plant') or 'data run'}: modeling {summary.get('modeling_status', '-')}"
    if summary.get("gain_method"):
        title += f", gain {summary['gain_method']}"
    fig.suptitle(title)
    fig.savefig(path, dpi=100, format="png")
    return path


def loop_panel(ax, loops: list, squares: dict[str, np.ndarray], exact: pd.DataFrame, summary: dict) -> None:
    """Each loop's RMS over its finite paths with its 95% band (`analysis.rms_band`) and its ideal loop's exact curve;
    the window shaded."""
    for row in loops:
        rms, low, high = rms_band(squares[row.experiment])     # the band the tables and recordings show
        color = LOOP_COLORS.get(row.experiment.replace("_on_model", ""), None)
        shown = f"{row.rate:.4f} [{row.rate_low:.4f}, {row.rate_high:.4f}]" if np.isfinite(row.rate) else "no rate"
        ax.semilogy(np.arange(rms.size), rms, color=color,
                    label=f"{row.experiment.replace('_', ' ')}: {row.verdict}, {shown} ({100 * row.level:g}%, "
                          f"{row.paths} paths)")
        ax.fill_between(np.arange(rms.size), low, high, color=color, alpha=0.2, linewidth=0)
        ideal = exact.loc[exact["experiment"] == row.experiment, "rms"].to_numpy()
        if ideal.size:
            ax.semilogy(np.arange(ideal.size), ideal, color=color, linestyle="--", linewidth=1,
                        label=f"  ideal loop (exact), rate {row.exact_rate:.4f}")
    k_from, k_to = summary.get("rate_window") or (None, None)
    if k_from is not None:
        ax.axvspan(k_from, k_to, color="0.9", zorder=0, label=f"rate window k = {k_from}..{k_to}")
    floor = summary.get("noise_floor")
    if floor is not None and np.isfinite(floor) and floor > 0:
        ax.axhline(floor, color="0.5", linestyle=":", linewidth=1, label="noise floor (the loop at rest)")
    ax.set_xlabel("k")
    ax.set_ylabel("RMS of q_k over the paths")
    ax.legend(fontsize=7, loc="best")


def xi_panel(ax_mean, ax_std, summary: dict) -> None:
    """The modeled mean and std of each component of xi with 95% intervals (1.96 stated sds; a std's cut at 0, where
    no std lies), the plant's beside."""
    uncertainty = summary.get("modeling_uncertainty") or {}
    for ax, what in ((ax_mean, "mean"), (ax_std, "std")):
        modeled = np.asarray(summary[f"xi_{what}"], dtype=float)
        index = np.arange(modeled.size)
        sd = np.asarray(uncertainty.get(f"xi_{what}_sd") or np.full(modeled.size, np.nan), dtype=float)
        half = np.where(np.isfinite(sd), 1.96 * sd, 0)
        below = np.minimum(half, np.maximum(modeled, 0)) if what == "std" else half
        ax.errorbar(index, modeled, yerr=[below, half], fmt="o", color="C0", capsize=4,
                    label="modeled (95% interval)" if np.isfinite(sd).any() else "modeled")
        truth = summary.get(f"plant_xi_{what}")
        if truth is not None:
            ax.plot(index, truth, "x", color="C3", markersize=9, label="plant file's law")
        ax.set_xticks(index, [f"xi[{i}]" for i in index])
        ax.set_ylabel(f"{what} of xi")
        ax.legend(fontsize=7)
