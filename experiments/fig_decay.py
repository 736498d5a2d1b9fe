"""Figs. "decay_proposed" and "decay_open": sqrt(E||q_k||^2) over the 200 paths of one run.

Closed loop with the proposed gain (or the open-loop plant with the same samples): the Monte Carlo
curve with its 95% band, the exact curve of the ideal loop (state feedback, true distribution), the
slope lambda^k through the k = 60 value, and the k = 60..80 rate (this run, and over all seeds).

    python experiments/fig_decay.py [--root outputs] [--out outputs/report]
"""
import numpy as np

from rdsexp import report


def draw(run: report.Run, experiment: str, all_runs: list[report.Run]):
    q = report.trajectory_array(run.table("trajectories"), experiment, "q")
    exact = run.table("exact")
    metrics = run.table("metrics").set_index("experiment").loc[experiment]
    gains = run.table("gains")
    lam = gains[gains["selected"]]["lam"].iloc[0]
    k_from, k_to = int(metrics["k_from"]), int(metrics["k_to"])
    k = np.arange(q.shape[0])
    mid, low, high = report.rms_with_band(q)
    fig, ax = report.figure(report.COLUMN_WIDTH, 2.6)
    ax.fill_between(k, low, high, color="0.8", lw=0, label="95% band")
    ax.semilogy(k, mid, color="black", label=f"EnKF loop, {q.shape[1]} paths")
    ideal = exact[exact["experiment"] == experiment]
    ax.semilogy(ideal["k"], ideal["rms"], color="0.4", ls="--", label="ideal loop, exact")
    if experiment == "closed_loop":
        ax.semilogy(k[k_from:], mid[k_from] * lam ** (k[k_from:] - k_from), color="0.2", ls=":",
                    label=rf"$\lambda^k$, $\lambda$ = {lam:.4f}")
    rates = [r.table("metrics").set_index("experiment").loc[experiment, "rate"] for r in all_runs]
    mean, lo, hi, n = report.seed_interval(rates)
    ax.set_title(f"rate k = {k_from}..{k_to}: {metrics['rate']:.4f} [{metrics['rate_low']:.4f}, "
                 f"{metrics['rate_high']:.4f}]\nover {n} seeds: {mean:.4f} [{lo:.4f}, {hi:.4f}]", fontsize=7)
    ax.set_xlabel("$k$")
    ax.set_ylabel(r"$\sqrt{E\|q_k\|^2}$")
    ax.legend(frameon=False, loc="lower left")
    return fig


def main(argv=None):
    args = report.arguments(__doc__.splitlines()[0], argv)
    runs = report.select(report.paper_runs(args), gain__method="proposed")
    run = report.first_seed(runs)
    return [report.save_figure(draw(run, experiment, runs), args.out, name, runs, __file__)
            for experiment, name in (("closed_loop", "decay_proposed"), ("open_loop", "decay_open"))]


if __name__ == "__main__":
    main()
