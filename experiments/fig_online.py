"""Online (learning-type) vs offline control, per plant: figure and table "online_PLANT"
from the `controllers` sweeps, table "online_settings_PLANT" from the `online` sweeps.

Each run of either sweep holds the offline closed loop and the online loop of the same seed on the
same plant samples. Figure, from the latest `controllers` sweep on the plant: (left)
sqrt(E||q_k||^2) of both loops with 95% bands over paths, first seed; (right) the distribution over
paths and seeds of the exact rate on the true plant of each online path's final gain, against the
offline gains' rates and the optimum. Tables, one row per controller setting (initial gain, memory,
period, window, warm-up, modeled covariance): means over seeds of the k-window closed-loop rates, diverged fractions,
the online final gains' true rates, the offline gain's true rate, and the online loop's time over
the offline closed loop's (run.json timings); `matches`: the median final true rate is within
--tolerance of the offline gain's, the k-window rate of the online loop's paths that did not
diverge within --rate-tolerance of the offline loop's (where the offline loop has no rate, a path
of it having diverged, the diverged fractions decide), and at most 1% more paths diverged: online
matches or beats offline. The caption says at which settings and at what cost.

    python experiments/fig_online.py [--root outputs] [--out outputs/report] [--tolerance 0.005]
                                     [--rate-tolerance 0.02]
"""
import numpy as np
import pandas as pd

from rdsexp import report
from rdsexp.experiment.store import files

SETTING = ("controller.initial", "controller.memory", "controller.period", "controller.window", "controller.warmup",
           "controller.forgetting", "controller.covariance")

LOOPS = {"closed_loop": ("offline (identification, then fixed F)", "black", "-"),
         "online": ("online (re-designed every period)", "tab:blue", "-")}


def decay(ax, run: report.Run) -> None:
    traj = run.table("trajectories")
    for experiment, (label, color, ls) in LOOPS.items():
        q = report.trajectory_array(traj, experiment, "q")
        mid, low, high = report.rms_with_band(q)
        k = np.arange(q.shape[0])
        ax.fill_between(k, low, high, color=color, alpha=0.2, lw=0)
        ax.semilogy(k, mid, color=color, ls=ls, label=label)
        alive = run.table("paths").query("experiment == @experiment")["failed_at"].to_numpy() < 0
        if not alive.all() and alive.any():          # a few diverging paths dominate the mean square
            ax.semilogy(k, report.rms_with_band(q[:, alive])[0], color=color, ls="--",
                        label=f"{label.split(' (')[0]}, the {alive.mean():.0%} of paths not diverged")
    ax.set_xlabel("$k$")
    ax.set_ylabel(r"$\sqrt{E\|q_k\|^2}$")
    ax.set_title(f"seed {run.get('seed')}, {int(run.get('closed_loop.paths'))} paths")
    report.log_ticks(ax)
    ax.legend(frameon=False, loc="lower left")


def final_rates(runs: list[report.Run]) -> tuple[np.ndarray, np.ndarray, float]:
    """(final online true rates over paths and seeds, offline true rate per seed, optimum)."""
    finals, offline, optimum = [], [], np.nan
    for r in runs:
        paths = r.table("paths")
        finals.append(paths[paths["experiment"] == "online"]["final_rate_plant"].to_numpy())
        m = r.table("metrics").set_index("experiment").loc["online"]
        offline.append(m["offline_rate_plant"])
        optimum = m["optimal_rate_plant"]
    return np.concatenate(finals), np.array(offline), optimum


def distribution(ax, runs: list[report.Run]) -> str:
    finals, offline, optimum = final_rates(runs)
    shown = np.sort(np.clip(finals, None, 1.2))
    ax.step(shown, np.arange(1, shown.size + 1) / shown.size, where="post", color="tab:blue",
            label="online, final gain per path")
    ax.step(np.sort(offline), np.arange(1, offline.size + 1) / offline.size, where="post", color="black",
            label="offline gain per seed")
    ax.axvline(optimum, color="0.5", ls="--", label=f"optimum {optimum:.4f}")
    ax.axvline(1.0, color="0.8", ls=":")
    ax.set_xlabel("exact rate on the true plant (clipped at 1.2)")
    ax.set_ylabel("fraction")
    ax.legend(frameon=False, loc="lower right")
    q = np.nanpercentile(finals, [10, 50, 90])
    return (f"Online final gains over {len(runs)} seeds x paths: exact true rate median {q[1]:.4f} "
            f"(10-90%: {q[0]:.4f}-{q[2]:.4f}), {np.mean(finals < 1):.0%} stable; offline gains: median "
            f"{np.nanmedian(offline):.4f} over {offline.size} seeds; optimum {optimum:.4f}.")


def setting(run: report.Run, skip=()) -> str:
    """The online controller's setting of a run in words, without the keys in `skip` (short names)
    and without the memory's unused ones (window, forgetting)."""
    unused = {"all": ("window", "forgetting"), "window": ("forgetting",), "exponential": ("window",)}
    skip = set(skip) | set(unused.get(run.get("controller.memory"), ()))
    return ", ".join(f"{k.split('.')[1]} {run.get(k)}" for k in (*SETTING, "controller.method")
                     if k.split(".")[1] not in skip)


def setting_table(runs: list[report.Run], tolerance: float, rate_tolerance: float) -> pd.DataFrame:
    """One row per controller setting: means over its seeds (module docstring)."""
    rows = []
    for r in runs:
        m = r.table("metrics").set_index("experiment")
        t = r.record.timings
        rows.append({**{k.split(".")[1]: str(r.get(k)) for k in SETTING},
                     "offline_rate": m.loc["closed_loop", "rate"], "online_rate": m.loc["online", "rate"],
                     "online_rate_not_diverged": m.loc["online"].get("rate_not_diverged", np.nan),
                     "offline_diverged": m.loc["closed_loop", "failed_fraction"],
                     "online_diverged": m.loc["online", "failed_fraction"],
                     "final_true_rate_median": m.loc["online", "final_rate_plant_median"],
                     "final_stable_fraction": m.loc["online", "final_stable_fraction"],
                     "first_stable_k_median": m.loc["online"].get("first_stable_k_median", np.nan),
                     "adoptions_per_path": m.loc["online", "adoptions_per_path"],
                     "offline_true_rate": m.loc["online", "offline_rate_plant"],
                     "optimal_true_rate": m.loc["online", "optimal_rate_plant"],
                     "time_online_over_offline": t["online"] / t["closed_loop"]})
    frame = pd.DataFrame(rows)
    names = [k.split(".")[1] for k in SETTING]
    keys = [k for k in names if frame[k].nunique() > 1] or names      # the varied ones, else the setting
    frame = frame.drop(columns=[k for k in names if k not in keys])
    table = frame.groupby(keys).mean(numeric_only=True).reset_index()
    table.insert(len(keys), "seeds", frame.groupby(keys).size().to_numpy())
    table["matches"] = matching(table, tolerance, rate_tolerance)
    return table.round(4)


def matching(table: pd.DataFrame, tolerance: float, rate_tolerance: float) -> pd.Series:
    """Settings where online matches or beats offline: final gains, loop rate, diverged paths (module docstring)."""
    no_offline_rate = ~np.isfinite(table["offline_rate"])     # an offline path diverged: the fractions decide
    return ((table["final_true_rate_median"] <= table["offline_true_rate"] + tolerance)
            & ((table["online_rate_not_diverged"] <= table["offline_rate"] + rate_tolerance) | no_offline_rate)
            & (table["online_diverged"] <= table["offline_diverged"] + 0.01))


def verdict(table: pd.DataFrame, keys: list[str], tolerance: float, rate_tolerance: float) -> str:
    """Where online matches offline and what it costs, else the closest setting."""
    def name(row) -> str:
        return ", ".join(f"{k} {row[k]}" for k in keys)

    def numbers(row) -> str:
        offline_loop = f"{row.offline_rate:.4f}" if np.isfinite(row.offline_rate) else "none (a path diverged)"
        return (f"median final true rate {row.final_true_rate_median:.4f} vs offline {row.offline_true_rate:.4f}, "
                f"loop rate {row.online_rate_not_diverged:.4f} vs {offline_loop}, "
                f"diverged {row.online_diverged:.1%} vs {row.offline_diverged:.1%}, "
                f"time x{row.time_online_over_offline:.2f} of the offline closed loop")
    criterion = (f"its final gains' median exact rate on the true plant within {tolerance} of the offline "
                 f"gain's, its loop's k-window rate (paths not diverged) within {rate_tolerance} of the offline "
                 f"loop's, or the diverged fractions alone where an offline path diverged, and at most 1% more "
                 f"paths diverged, means over seeds")
    match = table[table["matches"]].sort_values("time_online_over_offline")
    if len(match):
        shown = match.iloc[:3]
        more = f"; {len(match) - 3} more in the table" if len(match) > 3 else ""
        return (f"Online matches or beats offline ({criterion}) at {len(match)} of {len(table)} settings"
                + (", the cheapest: " if more else ": ")
                + "; ".join(f"{name(r)} ({numbers(r)})" for _, r in shown.iterrows()) + more + ".")
    closest = []
    for what, excess in (("final gains", table["final_true_rate_median"] - table["offline_true_rate"]),
                         ("loop rate", table["online_rate_not_diverged"] - table["offline_rate"])):
        if excess.notna().any():           # the offline loop rate is NaN where an offline path diverged
            row = table.loc[excess.idxmin()]
            closest.append(f"closest in the {what}: {name(row)} ({numbers(row)})")
    return (f"Online matches or beats offline ({criterion}) at none of {len(table)} settings"
            + "".join(f"; {c}" for c in closest) + ".")


def main(argv=None):
    parser = report.parser(__doc__.splitlines()[0])
    parser.add_argument("--tolerance", type=float, default=0.005,
                        help="largest excess of the online final gains' median true rate over the offline one")
    parser.add_argument("--rate-tolerance", type=float, default=0.02,
                        help="largest excess of the online loop's k-window rate over the offline loop's")
    args = parser.parse_args(argv)
    stored = report.load_runs(args.root)
    outputs, written = [], 0
    for plant, runs in sorted(report.latest_per_plant(stored, "controllers", (*SETTING, "seed")).items()):
        report.check_versions(runs, args.allow_mixed)
        latest = max(str(r.record.sweep.dir) for r in runs)          # the figure: the latest sweep's setting
        shown = [r for r in runs if str(r.record.sweep.dir) == latest]
        fig, (left, right) = report.figure(report.PAGE_WIDTH, 2.6, 1, 2)
        decay(left, min(shown, key=lambda r: r.get("seed")))
        text = distribution(right, shown)
        name = f"online_{plant}"
        outputs += report.save_figure(fig, args.out, name, shown, __file__,
                                      f"Plant {plant}: offline vs online (learning-type) control, same plant "
                                      f"samples; online {setting(shown[0])}. {text}")
        report.write_table(setting_table(runs, args.tolerance, args.rate_tolerance), args.out, name, runs, __file__)
        written += 1
    for plant, runs in sorted(report.latest_per_plant(stored, "online", (*SETTING, "seed")).items()):
        report.check_versions(runs, args.allow_mixed)
        table = setting_table(runs, args.tolerance, args.rate_tolerance)
        keys = list(table.columns[:list(table.columns).index("seeds")])
        sentence = f"Plant {plant} ({setting(runs[0], keys)}): " + verdict(table, keys, args.tolerance,
                                                                           args.rate_tolerance)
        name = f"online_settings_{plant}"
        report.write_table(table, args.out, name, runs, __file__)
        report.write_caption(args.out, name, sentence)
        files.atomic_write_bytes(args.out / f"{name}.txt", (sentence + "\n").encode())
        print(sentence)
        written += 1
    if not written:
        raise SystemExit(f"no stored `controllers` or `online` sweep under {args.root}: run "
                         "`python -m rdsexp +sweep=controllers` or `+sweep=online` first")
    return outputs


if __name__ == "__main__":
    report.script(main)
