"""Online (learning-type) vs offline control (issue 9): figure "online" and table "online".

Figure, from the latest `controllers` sweep (each run holds the offline closed loop and the online
loop of the same seed on the same plant samples): (left) sqrt(E||q_k||^2) of both loops with 95%
bands over paths, first seed; (right) the distribution over paths and seeds of the exact rate on the
true plant of each online path's final gain, against the offline gains' rates and the optimum.
Table, from the latest `online` sweep (period x window x warm-up): mean over seeds of the k-window
closed-loop rates (offline, online), the median final true rate, the fraction of paths whose final
gain is stable on the true plant, adoptions per path, and the online loop's time relative to the
offline closed loop's (run.json timings).

    python experiments/fig_online.py [--root outputs] [--out outputs/report]
"""
import numpy as np
import pandas as pd

from rdsexp import report

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


def online_table(runs: list[report.Run]) -> pd.DataFrame:
    rows = []
    for r in runs:
        m = r.table("metrics").set_index("experiment")
        t = r.info["timings"]
        rows.append({"period": r.get("controller.period"), "window": r.get("controller.window"),
                     "warmup": r.get("controller.warmup"), "offline_rate": m.loc["closed_loop", "rate"],
                     "online_rate": m.loc["online", "rate"],
                     "online_rate_not_diverged": m.loc["online"].get("rate_not_diverged", np.nan),
                     "online_failed": m.loc["online", "failed_fraction"],
                     "final_true_rate_median": m.loc["online", "final_rate_plant_median"],
                     "final_stable_fraction": m.loc["online", "final_stable_fraction"],
                     "adoptions_per_path": m.loc["online", "adoptions_per_path"],
                     "offline_true_rate": m.loc["online", "offline_rate_plant"],
                     "time_online_over_offline": t["online"] / t["closed_loop"]})
    frame = pd.DataFrame(rows)
    table = frame.groupby(["period", "window", "warmup"]).mean().reset_index()
    table.insert(3, "seeds", frame.groupby(["period", "window", "warmup"]).size().to_numpy())
    return table.round(4)


def main(argv=None):
    args = report.arguments(__doc__.splitlines()[0], argv)
    outputs = []
    runs = report.load_runs(args.root, "controllers")
    if runs:
        report.check_versions(runs, args.allow_mixed)
        fig, (left, right) = report.figure(report.PAGE_WIDTH, 2.6, 1, 2)
        decay(left, min(runs, key=lambda r: r.get("seed")))
        text = distribution(right, runs)
        outputs += report.save_figure(fig, args.out, "online", runs, __file__,
                                      "Offline vs online (learning-type) control, same plant samples. " + text)
    sweep = report.load_runs(args.root, "online")
    if sweep:
        report.check_versions(sweep, args.allow_mixed)
        report.write_table(online_table(sweep), args.out, "online", sweep, __file__)
    if not outputs and not sweep:
        raise SystemExit("no stored `controllers` or `online` sweep under " + str(args.root))
    return outputs


if __name__ == "__main__":
    main()
