"""Sweep figures: empirical and exact rates against ensemble size, Q/R scale and window K1.

For each value, over the seeds of the latest `ensemble_size`, `noise` and `window` sweeps: the
empirical k = 60..80 closed-loop rate (Monte Carlo, EnKF observer) and the exact rate of the
designed gain on the true plant (sqrt(rho(E[Acl (x) Acl])), no Monte Carlo), mean with a 95%
t-interval over the seeds where it is finite. Below each panel, the fraction of diverged
closed-loop paths at every value (a failed or partly failed point is shown as such, never only
missing); a rate point with diverged paths has an open marker.

    python experiments/fig_sweeps.py [--root outputs] [--out outputs/report]
"""
import matplotlib.ticker
import numpy as np
import pandas as pd

from rdsexp import report

NAME = "sweeps"
TITLES = {"ensemble_size": "ensemble size", "noise": "EnKF noise scales", "window": "modeling window"}
PANELS = (("ensemble_size", "enkf.ensemble_size", "ensemble size M"),
          ("noise", None, "scale of Q (R = 0.01) or R (Q as paper)"),
          ("window", "identification.K1", "window length $K_1$"))


def points(runs: list[report.Run], key: str) -> pd.DataFrame:
    """Per run: the swept value, empirical closed-loop rate, exact rate on the true plant, and the
    fraction of closed-loop paths that diverged."""
    rows = []
    for r in runs:
        metrics = r.table("metrics").set_index("experiment")
        gains = r.table("gains")
        closed = "closed_loop" in metrics.index
        rows.append({"value": r.get(key), "empirical": metrics.loc["closed_loop", "rate"] if closed else np.nan,
                     "exact": gains[gains["selected"]]["rate_plant"].iloc[0],
                     "diverged": metrics.loc["closed_loop", "failed_fraction"] if closed else 1.0})
    return pd.DataFrame(rows)


YLIM = (0.75, 1.1)          # rate axis; the diverged fraction has its own row, so no point is off scale unseen


def plot_series(ax, ax_div, frame: pd.DataFrame, label: str, color, marker):
    """Rates (top axes) with 95% t-intervals over seeds, and the fraction of diverged closed-loop
    paths (bottom axes) at every value, so a failed or partly failed point is shown as such."""
    for column, ls in (("empirical", "-"), ("exact", "--")):
        stats = [(v, *report.seed_interval(g[column])[:3], g["diverged"].mean()) for v, g in frame.groupby("value")]
        v, mean, lo, hi, diverged = map(np.array, zip(*stats))
        ax.errorbar(v, mean, yerr=[mean - lo, hi - mean], color=color, ls=ls, marker=marker, ms=3, capsize=2,
                    label=f"{label} {column}".strip())
        if column != "empirical":
            continue
        partial = diverged > 0                      # some paths diverged: open marker on the rate
        ax.plot(v[partial], mean[partial], ls="none", marker=marker, ms=6, mfc="white", color=color)
        ax_div.plot(v, diverged, color=color, ls="-", marker=marker, ms=3, label=label or None)
        for x, f in zip(v[diverged > 0], diverged[diverged > 0]):
            ax_div.annotate(f"{f:.0%}", (x, f), xytext=(2, 2), textcoords="offset points", fontsize=5.5, color=color)


def draw(sweeps: dict[str, list[report.Run]]):
    fig, axes = report.figure(report.PAGE_WIDTH, 3.3, 2, 3, sharey="row", sharex="col",
                              gridspec_kw={"height_ratios": [3, 1]})
    for ax, ax_div, (sweep, key, xlabel) in zip(axes[0], axes[1], PANELS):
        runs = sweeps.get(sweep) or []
        if sweep == "noise":
            frame_q = points([r for r in runs if r.get("enkf.r_scale") == 1.0], "enkf.q_scale")
            frame_r = points([r for r in runs if r.get("enkf.q_scale") == 1.0], "enkf.r_scale")
            if len(frame_q):
                plot_series(ax, ax_div, frame_q, "Q scale", "black", "o")
            if len(frame_r):
                plot_series(ax, ax_div, frame_r, "R scale", "0.55", "s")
            ax.set_xscale("log")
            ax_div.set_xticks([0.25, 0.5, 1, 2, 4], ["1/4", "1/2", "1", "2", "4"])
            ax_div.minorticks_off()
        elif runs:
            plot_series(ax, ax_div, points(runs, key), "", "black", "o")
            if sweep == "ensemble_size":
                ax.set_xscale("log")
                values = sorted({r.get(key) for r in runs})
                ax_div.set_xticks(values, [f"{v:g}" for v in values])
                ax_div.minorticks_off()
        seeds = len({r.get("seed") for r in runs})
        ax_div.set_xlabel(xlabel)
        ax.set_title(f"{TITLES[sweep]} ({len(runs)} runs, {seeds} seed{'s' if seeds != 1 else ''})")
        ax.legend(frameon=False, fontsize=5.5)
    axes[0, 0].set_ylabel("mean-square rate\n(exact: of the designed gain\non the true plant)")
    axes[0, 0].set_ylim(*YLIM)
    axes[1, 0].set_ylabel("paths\ndiverged")
    axes[1, 0].set_ylim(-0.05, 1.15)
    axes[1, 0].yaxis.set_major_formatter(matplotlib.ticker.PercentFormatter(1.0, decimals=0))
    return fig


def caption(sweeps: dict[str, list[report.Run]]) -> str:
    k_from, k_to = next((r.rate_window for runs in sweeps.values() for r in runs), (60, 80))
    return ("Sweeps of the EnKF's ensemble size, of the scales of its artificial noises Q and R, and of the "
            "modeling window K1. Solid (empirical): the closed loop's two-point rate "
            f"k = {k_from}..{k_to} from the Monte Carlo paths, with the EnKF observer. Dashed (exact): the exact "
            "mean-square rate sqrt(rho(E[Acl (x) Acl])) of the gain designed in that run, on the true plant "
            "(ideal state feedback, no Monte Carlo). Points: mean over seeds, bars: 95% t-interval over the seeds "
            "with a finite rate (a value where every seed's loop diverged has no rate point). Bottom row: the "
            "fraction of closed-loop paths that diverged (mean over seeds), at every value; an open marker on a "
            "rate point says some of its paths diverged.")


def main(argv=None):
    args = report.arguments(__doc__.splitlines()[0], argv)
    sweeps = {name: report.load_runs(args.root, name) for name, _, _ in PANELS}
    used = [r for runs in sweeps.values() for r in runs]
    if not used:
        raise report.LineageError(f"no stored runs of the sweeps {', '.join(sweeps)} under {args.root}")
    report.check_versions(used, args.allow_mixed)
    return report.save_figure(draw(sweeps), args.out, NAME, used, __file__, caption(sweeps))


if __name__ == "__main__":
    report.script(main)
