"""Gain comparison (Sec. V-B in words): every design method in the closed loop with the EnKF.

Left: sqrt(E||q_k||^2) of the first-seed run of each method (a curve stops where paths diverged).
Table gain_comparison.{csv,md}: per method, over the seeds of the `paper` sweep, the design
lambda, the exact rate of its gain on the modeled and on the true distribution, the empirical
k = 60..80 rate (mean and 95% interval over seeds) and the fraction of diverged paths.

    python experiments/fig_gains.py [--root outputs] [--out outputs/report]
"""
import numpy as np
import pandas as pd

from rdsexp import report

NAME = "gain_comparison"
STYLES = {"proposed": ("black", "-"), "policy_iteration": ("0.55", (0, (1, 1))), "nominal_lmi": ("0.3", "--"),
          "pole_placement": ("0.5", "-."), "lqr_mean": ("0.7", ":")}


def table(runs: list[report.Run]) -> pd.DataFrame:
    rows = []
    for method in STYLES:
        chosen = report.select(runs, gain__method=method)
        if not chosen:
            continue
        gains = pd.concat([r.table("gains") for r in chosen])
        gains = gains[gains["selected"]]
        metrics = pd.concat([r.table("metrics") for r in chosen])
        closed = metrics[metrics["experiment"] == "closed_loop"]
        mean, lo, hi, n = report.seed_interval(closed["rate"])
        rows.append({"method": method, "seeds": len(chosen), "status": ",".join(sorted(set(gains["status"]))),
                     "lambda_design": gains["lam"].mean(), "rate_modeled": gains["rate_model"].mean(),
                     "rate_true_plant": gains["rate_plant"].mean(), "empirical_rate": mean,
                     "empirical_low": lo, "empirical_high": hi, "finite_rate_seeds": n,
                     "diverged_fraction": closed["failed_fraction"].mean()})
    return pd.DataFrame(rows)


def draw(runs: list[report.Run], summary: pd.DataFrame):
    fig, ax = report.figure(report.COLUMN_WIDTH, 2.6)
    for row in summary.itertuples():
        run = report.first_seed(runs, row.method)
        q = report.trajectory_array(run.table("trajectories"), "closed_loop", "q")
        with np.errstate(invalid="ignore"):
            rms = np.sqrt(np.mean(np.sum(q ** 2, axis=-1), axis=1))      # NaN once a path diverged
        color, ls = STYLES[row.method]
        ax.semilogy(np.arange(rms.size), rms, color=color, ls=ls,
                    label=f"{row.method}: $\\lambda$ {row.lambda_design:.3f}, true {row.rate_true_plant:.3f}")
    ax.set_xlabel("$k$")
    ax.set_ylabel(r"$\sqrt{E\|q_k\|^2}$")
    ax.legend(frameon=False, fontsize=5.5, loc="upper left")
    return fig


def main(argv=None):
    args = report.arguments(__doc__.splitlines()[0], argv)
    runs = report.paper_runs(args)
    summary = table(runs)
    report.write_table(summary, args.out, NAME, runs, __file__)
    return report.save_figure(draw(runs, summary), args.out, NAME, runs, __file__)


if __name__ == "__main__":
    main()
