"""Sweep figures: empirical and exact rates against ensemble size, Q/R scale and window K1.

For each value, over the seeds of the latest `ensemble_size`, `noise` and `window` sweeps: the
empirical k = 60..80 closed-loop rate and the exact rate of the designed gain on the true plant,
mean with a 95% t-interval over seeds; a triangle at the top marks a rate off the scale or not
finite (a loop that diverged).

    python experiments/fig_sweeps.py [--root outputs] [--out outputs/report]
"""
import numpy as np
import pandas as pd

from rdsexp import report

NAME = "sweeps"
PANELS = (("ensemble_size", "enkf.ensemble_size", "ensemble size M"),
          ("noise", None, "scale of Q (R = 0.01) or R (Q as paper)"),
          ("window", "identification.K1", "window length $K_1$"))


def points(runs: list[report.Run], key: str) -> pd.DataFrame:
    """Per run: the swept value, empirical closed-loop rate and exact rate on the true plant."""
    rows = []
    for r in runs:
        metrics = r.table("metrics").set_index("experiment")
        gains = r.table("gains")
        rows.append({"value": r.get(key), "empirical": metrics.loc["closed_loop", "rate"] if "closed_loop" in
                     metrics.index else np.nan, "exact": gains[gains["selected"]]["rate_plant"].iloc[0]})
    return pd.DataFrame(rows)


YLIM = (0.75, 1.1)          # rates beyond it (a diverging loop, a useless model) are marked at the top


def plot_series(ax, frame: pd.DataFrame, label: str, color, marker):
    for column, ls in (("empirical", "-"), ("exact", "--")):
        stats = [(v, *report.seed_interval(g[column])[:3]) for v, g in frame.groupby("value")]
        v, mean, lo, hi = map(np.array, zip(*stats))
        ax.errorbar(v, mean, yerr=[mean - lo, hi - mean], color=color, ls=ls, marker=marker, ms=3, capsize=2,
                    label=f"{label} {column}".strip())
        off = ~(mean <= YLIM[1])                  # above the scale or no finite rate (diverged)
        ax.plot(v[off], np.full(off.sum(), YLIM[1]), ls="none", marker="^", color=color, ms=4)


def draw(sweeps: dict[str, list[report.Run]]):
    fig, axes = report.figure(report.PAGE_WIDTH, 2.3, 1, 3, sharey=True)
    for ax, (sweep, key, xlabel) in zip(axes, PANELS):
        runs = sweeps.get(sweep) or []
        if sweep == "noise":
            frame_q = points([r for r in runs if r.get("enkf.r_scale") == 1.0], "enkf.q_scale")
            frame_r = points([r for r in runs if r.get("enkf.q_scale") == 1.0], "enkf.r_scale")
            if len(frame_q):
                plot_series(ax, frame_q, "Q scale", "black", "o")
            if len(frame_r):
                plot_series(ax, frame_r, "R scale", "0.55", "s")
            ax.set_xscale("log")
            ax.set_xticks([0.25, 0.5, 1, 2, 4], ["1/4", "1/2", "1", "2", "4"])
            ax.minorticks_off()
        elif runs:
            plot_series(ax, points(runs, key), "", "black", "o")
            if sweep == "ensemble_size":
                ax.set_xscale("log")
        ax.set_xlabel(xlabel)
        ax.set_title(f"sweep {sweep}: {len(runs)} runs")
        ax.legend(frameon=False, fontsize=5.5)
    axes[0].set_ylabel("mean-square rate ($\\blacktriangle$: off scale)")
    axes[0].set_ylim(*YLIM)
    return fig


def main(argv=None):
    args = report.arguments(__doc__.splitlines()[0], argv)
    sweeps = {name: report.load_runs(args.root, name) for name, _, _ in PANELS}
    used = [r for runs in sweeps.values() for r in runs]
    report.check_versions(used, args.allow_mixed)
    return report.save_figure(draw(sweeps), args.out, NAME, used, __file__)


if __name__ == "__main__":
    main()
