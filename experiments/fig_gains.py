"""Gain comparison (Sec. V-B in words): every design method in the closed loop with the EnKF, on every plant.

Figure: (a) sqrt(E||q_k||^2) of the first-seed run of each method on the paper's plant, with the
95% band over paths; a curve that leaves the plot (paths diverged or off scale) ends in a marker.
Methods whose curves coincide (the optimal-rate designs reach the same rate) are named together in
the caption. (b) per plant and method: the exact mean-square rate of the gain on the true plant
(open marker) and the EnKF closed-loop rate k = 60..80 with its 95% interval over seeds (filled).
Table gain_comparison.{csv,md}: per plant and method, over the seeds of its sweep, the design lambda,
the exact rate of its gain on the modeled and on the true distribution, the exact LQ cost (weights I,
from the plant's q0 and averaged over x0 ~ N(0, I)) and H2 norm (d on u to [x; F x]) on the true
plant (inf: not mean-square stable), the empirical closed-loop rate (mean and 95% interval over
seeds; for a single seed, that run's interval over its paths, `interval_over`) and the fraction of
diverged paths.

Plants: the paper's plant from the `paper` sweep; any other plant from the latest `gain_methods`
sweep that ran it (`python -m rdsexp +sweep=gain_methods plant=NAME`, or several plants at once
with `plant=a,b`). --plants restricts and orders them (default: every plant with stored runs).

    python experiments/fig_gains.py [--root outputs] [--out outputs/report] [--plants paper,other]
"""
import argparse

import numpy as np
import pandas as pd

from rdsexp import report

NAME = "gain_comparison"
SWEEPS = (report.PAPER_SWEEP, "gain_methods")   # where a plant's comparison runs are, preferred first
LABELS = {"proposed": "proposed (Thm. 2, LMI)", "policy_iteration": "mean-square policy iteration",
          "lqr_mean": "LQR on the mean model", "nominal_lmi": "nominal LMI (mean model)",
          "pole_placement": "pole placement (mean model)", "robust_box": "robust LMI (box)",
          "ms_lqr": "mean-square LQR"}
ORDER = tuple(LABELS)                   # known methods first, in this order; others after, by name
LINESTYLES = ("-", "--", "-.", ":", (0, (5, 1, 1, 1)), (0, (1, 1)), (0, (3, 1, 1, 1, 1, 1)))
GRAYS = ("black", "0.35", "0.55", "0.2", "0.45", "0.65", "0.3")
MARKERS = ("o", "s", "^", "D", "v", "P", "X")
CEILING = 1e4                           # y-axis top: a curve above it has left the plot
RATE_TOP = 1.2                          # panel (b): rates above it (unstable loops) drawn at the top
SAME_RATE = 1e-3                        # exact true-plant rates closer than this: "overlapping curves"
COSTS = ("lq_cost_q0_plant", "lq_cost_plant", "h2_plant")


def label(method: str) -> str:
    """Human label of a method id (the id itself for a method this script does not know)."""
    return LABELS.get(method, method.replace("_", " "))


def methods_present(runs: list[report.Run]) -> list[str]:
    """Every gain.method among the runs: known ones in ORDER, then the rest sorted."""
    present = {r.get("gain.method") for r in runs}
    return [m for m in ORDER if m in present] + sorted(present - set(ORDER))


def plant_name(run: report.Run) -> str:
    return run.get("plant.name") or "plant"


def comparison_runs(root, plants: list[str] | None = None) -> dict[str, list[report.Run]]:
    """{plant: runs}: per plant the latest sweep of the first name in SWEEPS that ran it (the paper's
    plant: the `paper` sweep), in --plants order (default: the paper's plant first, then by name)."""
    by_plant: dict[str, dict[str, list[report.Run]]] = {}
    for run in report.load_runs(root):
        sweep = report.sweep_of(run)
        if sweep in SWEEPS:
            by_plant.setdefault(plant_name(run), {}).setdefault(sweep, []).append(run)
    out = {}
    for plant in plants or sorted(by_plant, key=lambda p: (p != "paper", p)):
        sweeps = by_plant.get(plant, {})
        name = next((s for s in SWEEPS if s in sweeps), None)
        if name is None:
            raise report.LineageError(f"no stored {' or '.join(SWEEPS)} sweep ran plant {plant!r}: run "
                                      f"python -m rdsexp +sweep=gain_methods plant={plant}")
        latest = max(str(r.record.sweep.dir) for r in sweeps[name])
        out[plant] = [r for r in sweeps[name] if str(r.record.sweep.dir) == latest]
    return out


def table(runs: list[report.Run], plant: str | None = None) -> pd.DataFrame:
    """One row per method among `runs` (one plant): exact rates, costs, EnKF closed-loop rate over seeds."""
    rows = []
    for method in methods_present(runs):
        chosen = report.select(runs, gain__method=method)
        gains = pd.concat([r.table("gains") for r in chosen])
        gains = gains[gains["selected"]]
        metrics = pd.concat([r.table("metrics") for r in chosen])
        closed = metrics[metrics["experiment"] == "closed_loop"]
        mean, lo, hi, n = report.seed_interval(closed["rate"])
        over = "seeds"
        if n == 1 and len(closed) == 1:            # one seed: the run's own 95% interval over its paths
            mean, lo, hi, over = *closed[["rate", "rate_low", "rate_high"]].iloc[0].astype(float), "paths"
        costs = {c: gains[c].mean() if c in gains else np.nan for c in COSTS}    # inf if any seed is unstable
        rows.append({"plant": plant or plant_name(chosen[0]), "method": method, "label": label(method),
                     "seeds": len(chosen), "status": ",".join(sorted(set(gains["status"]))),
                     "lambda_design": gains["lam"].mean(), "rate_modeled": gains["rate_model"].mean(),
                     "rate_true_plant": gains["rate_plant"].mean(), **costs, "empirical_rate": mean,
                     "empirical_low": lo, "empirical_high": hi, "interval_over": over, "finite_rate_seeds": n,
                     # a method without a gain (e.g. an infeasible box) has no closed loop: all diverged
                     "diverged_fraction": closed["failed_fraction"].mean() if len(closed) else 1.0})
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


def draw_trajectories(ax, runs: list[report.Run], summary: pd.DataFrame) -> None:
    for i, row in enumerate(summary.itertuples()):
        run = report.first_seed(runs, row.method)
        q = report.trajectory_array(run.table("trajectories"), "closed_loop", "q")
        if q.size == 0:                                # no gain, no closed loop
            continue
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
    ax.legend(frameon=False, fontsize=5.5, ncols=2, loc="upper center", bbox_to_anchor=(0.5, -0.2))  # below


def draw_rates(ax, summary: pd.DataFrame) -> None:
    """Exact rate on the true plant (open) and EnKF closed-loop rate with its interval (filled), per plant."""
    methods = [m for m in ORDER if m in set(summary["method"])] + \
        sorted(set(summary["method"]) - set(ORDER))
    plants = list(dict.fromkeys(summary["plant"]))
    width = 0.7 / max(len(plants), 1)
    for j, plant in enumerate(plants):
        rows = summary[summary["plant"] == plant].set_index("method")
        x = np.array([methods.index(m) for m in rows.index]) + (j - (len(plants) - 1) / 2) * width
        marker, color = MARKERS[j % len(MARKERS)], GRAYS[j % len(GRAYS)]
        exact = rows["rate_true_plant"].to_numpy(float)
        ax.plot(x, np.minimum(exact, RATE_TOP), ls="none", marker=marker, mfc="white", color=color, ms=4,
                clip_on=False)
        emp, lo, hi = (rows[c].to_numpy(float) for c in ("empirical_rate", "empirical_low", "empirical_high"))
        inside = np.isfinite(emp) & (emp <= RATE_TOP)
        err = np.nan_to_num(np.array([emp - lo, hi - emp])[:, inside])
        ax.errorbar(x[inside], emp[inside], yerr=err, ls="none", marker=marker, color=color, ms=3, capsize=2,
                    label=f"plant {plant}")
        ax.plot(x[~inside], np.full((~inside).sum(), RATE_TOP), ls="none", marker=marker, color=color, ms=3,
                clip_on=False)
    ax.axhline(1.0, color="0.6", lw=0.6)
    ax.set_ylim(top=RATE_TOP)
    ax.set_xticks(range(len(methods)), [label(m) for m in methods], rotation=35, ha="right", fontsize=6)
    ax.set_ylabel("mean-square rate")
    ax.plot([], [], ls="none", marker="o", mfc="white", color="black", label="open: exact, true plant")
    ax.plot([], [], ls="none", marker="o", color="black", label="filled: EnKF loop, 95%")
    ax.legend(frameon=False, fontsize=5, loc="upper left", bbox_to_anchor=(1.0, 1.0))     # outside the data


def draw(runs: list[report.Run], summary: pd.DataFrame, all_plants: pd.DataFrame | None = None):
    """(a) trajectories on the first plant's runs, (b) rates of every plant in all_plants (default: summary)."""
    fig, (a, b) = report.figure(report.PAGE_WIDTH, 3.4, 1, 2, width_ratios=[1.1, 1])
    draw_trajectories(a, runs, summary)
    draw_rates(b, summary if all_plants is None else all_plants)
    a.set_title(f"(a) closed loop, plant {summary['plant'].iloc[0]}")
    b.set_title("(b) exact and EnKF closed-loop rates")
    return fig


def caption(runs: list[report.Run], summary: pd.DataFrame, all_plants: pd.DataFrame | None = None) -> str:
    all_plants = summary if all_plants is None else all_plants
    window = report.first_seed(runs).rate_window
    seeds = sorted({r.get("seed") for r in runs})
    first = min(seeds)
    paths = report.first_seed(runs).get("closed_loop.paths")
    text = (f"Gain comparison (Sec. V-B): closed loop with the EnKF observer, each method's gain designed from the "
            f"identified moments. (a) plant {summary['plant'].iloc[0]}, curves of seed {first} ({paths} paths "
            f"each), shaded: 95% band over paths; a cross marks where a curve leaves the plot (a path diverged, or "
            f"above {CEILING:g}). (b) open: exact mean-square rate of the gain on the true plant; filled: EnKF "
            f"closed-loop rate k = {window[0]}..{window[1]}, mean and 95% t-interval over seeds (one seed: over "
            f"its paths); at the top: above {RATE_TOP:g} or no finite rate. "
            f"Plants: {', '.join(dict.fromkeys(all_plants['plant']))}. "
            f"The table below is over the seeds of each plant's sweep (paper: seeds {', '.join(map(str, seeds))}).")
    for group in overlapping(summary):
        rate = summary.set_index("method").loc[group, "rate_true_plant"].mean()
        text += (f" {', '.join(label(m) for m in group)} reach the same exact rate {rate:.4f} on the true plant "
                 f"(within {SAME_RATE:g}); their curves overlap.")
    for row in all_plants.itertuples():
        if row.diverged_fraction > 0:
            text += f" {row.plant}, {row.label}: {row.diverged_fraction:.0%} of paths diverged (mean over seeds)."
    return text


def main(argv=None):
    extra = argparse.ArgumentParser(add_help=False)
    extra.add_argument("--plants", default=None, help="comma-separated plant names (default: all with runs)")
    known, rest = extra.parse_known_args(argv)
    args = report.arguments(__doc__.splitlines()[0], rest)
    per_plant = comparison_runs(args.root, known.plants.split(",") if known.plants else None)
    if not per_plant:
        raise report.LineageError(f"no stored runs of the sweeps {', '.join(SWEEPS)} under {args.root}")
    every = [r for runs in per_plant.values() for r in runs]
    report.check_versions(every, args.allow_mixed)
    tables = {plant: table(runs, plant) for plant, runs in per_plant.items()}
    summary = pd.concat(tables.values(), ignore_index=True)
    first = next(iter(per_plant))
    paths = report.save_figure(draw(per_plant[first], tables[first], summary), args.out, NAME, every, __file__,
                               caption(per_plant[first], tables[first], summary))
    # after the figure: the table and the figure share NAME.json, one record of the tables either read
    # (the figure reads the trajectories too); written before, the two records differed and every call
    # found the figure out of date and rendered it again
    report.write_table(summary, args.out, NAME, every, __file__)
    return paths


if __name__ == "__main__":
    report.script(main)
