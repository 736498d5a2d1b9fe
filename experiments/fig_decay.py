"""Figs. "decay_proposed" and "decay_open": sqrt(E||q_k||^2) over the 200 paths of one run.

Closed loop with the proposed gain (or the open-loop plant with the same samples): the Monte Carlo
curve with its 95% band, the exact curve of the ideal loop (state feedback, true distribution) and,
in the closed loop, the slope lambda^k of the gain's design rate through the k = 60 value. Both
figures share their y-limits, so the comparison the paper makes (Figs. decay_proposed, decay_open)
is visible. The numbers (k = 60..80 rates of this run and over all seeds) are in NAME.caption.md.

    python experiments/fig_decay.py [--root outputs] [--out outputs/report]
"""
import numpy as np

from rdsexp import report
from rdsexp.numerics.analysis import bootstrap_rate, largest_path_share

TITLES = {"closed_loop": "closed loop, proposed gain, EnKF observer", "open_loop": "open-loop plant, same samples"}
PAPER_FIGURE = {"closed_loop": "Fig. decay_proposed", "open_loop": "Fig. decay_open"}


def curves(run: report.Run, experiment: str):
    """(k, Monte Carlo rms, band low, band high, exact k, exact rms) of one loop of a run."""
    q = report.trajectory_array(run.table("trajectories"), experiment, "q")
    exact = run.table("exact")
    ideal = exact[exact["experiment"] == experiment]
    return (np.arange(q.shape[0]), *report.rms_with_band(q), ideal["k"].to_numpy(), ideal["rms"].to_numpy())


def shared_ylim(run: report.Run) -> tuple[float, float]:
    """y-limits covering both loops' curves and bands (log scale, whole decades)."""
    values = np.concatenate([np.concatenate(curves(run, e)[1:4] + curves(run, e)[5:]) for e in TITLES])
    values = values[np.isfinite(values) & (values > 0)]
    return 10.0 ** np.floor(np.log10(values.min())), 10.0 ** np.ceil(np.log10(values.max()))


def draw(run: report.Run, experiment: str, all_runs: list[report.Run], ylim=None):
    k, mid, low, high, k_exact, rms_exact = curves(run, experiment)
    metrics = run.table("metrics").set_index("experiment").loc[experiment]
    gains = run.table("gains")
    lam = gains[gains["selected"]]["lam"].iloc[0]
    k_from = int(metrics["k_from"])
    fig, ax = report.figure(report.COLUMN_WIDTH, 2.6)
    ax.fill_between(k, low, high, color="0.8", lw=0, label="95% band over paths")
    ax.semilogy(k, mid, color="black", label=f"EnKF loop, {int(metrics['paths'])} paths")
    ax.semilogy(k_exact, rms_exact, color="0.4", ls="--", label="ideal loop (state feedback), exact")
    if experiment == "closed_loop":
        ax.semilogy(k[k_from:], mid[k_from] * lam ** (k[k_from:] - k_from), color="0.2", ls=":",
                    label=rf"$\lambda^k$, design rate of the gain $\lambda$ = {lam:.4f}")
    ax.set_ylim(*(ylim or shared_ylim(run)))
    report.log_ticks(ax)
    ax.set_xlabel("$k$")
    ax.set_ylabel(r"$\sqrt{E\|q_k\|^2}$")
    ax.set_title(TITLES[experiment])
    ax.legend(frameon=False, loc="lower left")
    return fig


def caption(run: report.Run, experiment: str, all_runs: list[report.Run]) -> str:
    """The numbers of the figure: this run's rate (delta-method and bootstrap over paths), the
    share of the largest path, the mean over seeds; the paper's value."""
    metrics = run.table("metrics").set_index("experiment").loc[experiment]
    k_from, k_to = int(metrics["k_from"]), int(metrics["k_to"])
    rate = report.interval(*metrics[["rate", "rate_low", "rate_high"]])
    sq = report.squared_norms(run, experiment, (k_from, k_to))
    boot = bootstrap_rate(sq[0][None], sq[1][None], k_to - k_from)
    q = report.trajectory_array(run.table("trajectories"), experiment, "q")
    rates = [r.table("metrics").set_index("experiment").loc[experiment, "rate"] for r in all_runs]
    mean, lo, hi, n = report.seed_interval(rates)
    paper = report.reference()["closed_loop"]["rate_k60_k80"]
    what = ("Closed loop with the proposed gain designed from the identified moments, the EnKF as observer"
            if experiment == "closed_loop" else "Open-loop plant driven by the same d_k and the same plant samples")
    text = (f"{PAPER_FIGURE[experiment]}. {what}; seed {run.get('seed')}, {int(metrics['paths'])} paths. "
            f"Band: 95% delta-method band of E||q_k||^2 over paths. "
            f"Rate k = {k_from}..{k_to} (two-point ratio as in the paper): {rate} "
            f"(delta method over paths), bootstrap over paths [{boot[1]:.4f}, {boot[2]:.4f}]; "
            f"largest path's share of E||q_{k_to}||^2: {largest_path_share(q, k_to):.0%}. "
            f"Over {n} seeds: {report.interval(mean, lo, hi)} (mean, 95% t-interval).")
    if experiment == "closed_loop":
        text += f" Paper: {paper}."
    return text


def main(argv=None):
    args = report.arguments(__doc__.splitlines()[0], argv)
    runs = report.select(report.paper_runs(args), gain__method="proposed")
    run = report.first_seed(runs)
    ylim = shared_ylim(run)
    return [report.save_figure(draw(run, experiment, runs, ylim), args.out, name, runs, __file__,
                               caption(run, experiment, runs))
            for experiment, name in (("closed_loop", "decay_proposed"), ("open_loop", "decay_open"))]


if __name__ == "__main__":
    report.script(main)
