"""Gain comparison (Sec. V-B in words): every design method in the closed loop with the EnKF.

Figure: sqrt(E||q_k||^2) of the first-seed run of each method present in the stored runs, with the
95% band over paths; a curve that leaves the plot (paths diverged or off scale) ends in a marker.
Methods whose curves coincide (the optimal-rate designs reach the same rate) are drawn in one
style family and named together in the caption. Table gain_comparison.{csv,md}: per method, over
the seeds of the `paper` sweep, the design lambda, the exact rate of its gain on the modeled and on
the true distribution, the empirical k = 60..80 rate (mean and 95% interval over seeds) and the
fraction of diverged paths.

    python experiments/fig_gains.py [--root outputs] [--out outputs/report]
"""
import numpy as np
import pandas as pd

from rdsexp import report

NAME = "gain_comparison"
LABELS = {"proposed": "proposed (Thm. 2, LMI)", "policy_iteration": "mean-square policy iteration",
          "lqr_mean": "mean-square LQ", "nominal_lmi": "nominal LMI (mean model)",
          "pole_placement": "pole placement (mean model)", "robust_box": "robust LMI (box)",
          "ms_lqr": "mean-square LQR"}
ORDER = tuple(LABELS)                   # known methods first, in this order; others after, by name
LINESTYLES = ("-", "--", "-.", ":", (0, (5, 1, 1, 1)), (0, (1, 1)), (0, (3, 1, 1, 1, 1, 1)))
GRAYS = ("black", "0.35", "0.55", "0.2", "0.45", "0.65", "0.3")
CEILING = 1e4                           # y-axis top: a curve above it has left the plot
SAME_RATE = 1e-3                        # exact true-plant rates closer than this: "overlapping curves"


def label(method: str) -> str:
    """Human label of a method id (the id itself for a method this script does not know)."""
    return LABELS.get(method, method.replace("_", " "))


def methods_present(runs: list[report.Run]) -> list[str]:
    """Every gain.method among the runs: known ones in ORDER, then the rest sorted."""
    present = {r.get("gain.method") for r in runs}
    return [m for m in ORDER if m in present] + sorted(present - set(ORDER))


def table(runs: list[report.Run]) -> pd.DataFrame:
    rows = []
    for method in methods_present(runs):
        chosen = report.select(runs, gain__method=method)
        gains = pd.concat([r.table("gains") for r in chosen])
        gains = gains[gains["selected"]]
        metrics = pd.concat([r.table("metrics") for r in chosen])
        closed = metrics[metrics["experiment"] == "closed_loop"]
        mean, lo, hi, n = report.seed_interval(closed["rate"])
        rows.append({"method": method, "label": label(method), "seeds": len(chosen),
                     "status": ",".join(sorted(set(gains["status"]))),
                     "lambda_design": gains["lam"].mean(), "rate_modeled": gains["rate_model"].mean(),
                     "rate_true_plant": gains["rate_plant"].mean(), "empirical_rate": mean,
                     "empirical_low": lo, "empirical_high": hi, "finite_rate_seeds": n,
                     "diverged_fraction": closed["failed_fraction"].mean()})
    return pd.DataFrame(rows)


def overlapping(summary: pd.DataFrame) -> list[list[str]]:
    """Groups of methods (>= 2) whose gains have the same exact rate on the true plant (to SAME_RATE)."""
    groups = []
    for row in summary.sort_values("rate_true_plant").itertuples():
        if groups and abs(row.rate_true_plant - groups[-1][1]) < SAME_RATE:
            groups[-1][0].append(row.method)
        else:
            groups.append(([row.method], row.rate_true_plant))
    return [g for g, _ in groups if len(g) > 1]


def draw(runs: list[report.Run], summary: pd.DataFrame):
    fig, ax = report.figure(report.PAGE_WIDTH * 0.62, 2.6)
    for i, row in enumerate(summary.itertuples()):
        run = report.first_seed(runs, row.method)
        q = report.trajectory_array(run.table("trajectories"), "closed_loop", "q")
        k = np.arange(q.shape[0])
        with np.errstate(invalid="ignore", over="ignore"):
            finite = np.all(np.isfinite(q), axis=(1, 2))                   # every path finite at step k
            mid, low, high = report.rms_with_band(np.where(finite[:, None, None], q, 0.0))
        shown = finite & (mid < CEILING)
        color, ls = GRAYS[i % len(GRAYS)], LINESTYLES[i % len(LINESTYLES)]
        ax.fill_between(k[shown], low[shown], np.minimum(high[shown], CEILING), color=color, alpha=0.12, lw=0)
        ax.semilogy(k[shown], mid[shown], color=color, ls=ls, label=row.label)
        if not shown.all():                        # the curve leaves the plot: mark where
            last = np.flatnonzero(shown)[-1] if shown.any() else 0
            ax.plot(k[last], min(mid[last], CEILING) if shown.any() else CEILING, marker="x", color=color, ms=5,
                    mew=1.2)
    ax.set_ylim(top=CEILING)
    report.log_ticks(ax)
    ax.set_xlabel("$k$")
    ax.set_ylabel(r"$\sqrt{E\|q_k\|^2}$")
    ax.plot([], [], ls="none", marker="x", color="black", label="leaves the plot\n(diverged / off scale)")
    ax.legend(frameon=False, loc="outside right upper")
    return fig


def caption(runs: list[report.Run], summary: pd.DataFrame) -> str:
    seeds = sorted({r.get("seed") for r in runs})
    first = min(seeds)
    paths = report.first_seed(runs).get("closed_loop.paths")
    text = (f"Gain comparison (Sec. V-B): closed loop with the EnKF observer, each method's gain designed from the "
            f"identified moments; curves of seed {first} ({paths} paths each), shaded: 95% band over paths; "
            f"the table below is over seeds {', '.join(map(str, seeds))}. A cross marks where a curve leaves the "
            f"plot (a path diverged, or above {CEILING:g}).")
    for group in overlapping(summary):
        rate = summary.set_index("method").loc[group, "rate_true_plant"].mean()
        text += (f" {', '.join(label(m) for m in group)} reach the same exact rate {rate:.4f} on the true plant "
                 f"(within {SAME_RATE:g}); their curves overlap.")
    for row in summary.itertuples():
        if row.diverged_fraction > 0:
            text += f" {row.label}: {row.diverged_fraction:.0%} of paths diverged (mean over seeds)."
    return text


def main(argv=None):
    args = report.arguments(__doc__.splitlines()[0], argv)
    runs = report.paper_runs(args)
    summary = table(runs)
    report.write_table(summary, args.out, NAME, runs, __file__)
    return report.save_figure(draw(runs, summary), args.out, NAME, runs, __file__, caption(runs, summary))


if __name__ == "__main__":
    main()
