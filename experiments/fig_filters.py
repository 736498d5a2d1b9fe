"""EnKF variants against ensemble size M: closed-loop rate, diverged fraction, xi RMSE and the model's CRPS.

From the `filters` sweeps (conf/sweep/filters.yaml) of each plant (files filters_<plant>.*; the latest
run of each point), per filter (variant, inflation rho, relaxation alpha, the unknown-disturbance estimate d
of `enkf.disturbance`) and M, over seeds: the empirical
closed-loop rate (mean with a 95% t-interval over the seeds whose loop kept every path; an open
marker where some seed diverged), the fraction of closed-loop paths that diverged (mean over
seeds), the RMSE of the filtered xi against the true xi, and the expected CRPS of the modeled
distribution of xi against the plant's (summary xi_crps, a proper score: it rewards the right mean
and the right spread). Tables: filters_<plant>_summary (every filter and M), filters_<plant>_best
(each variant at each M with its best knob, as DAPPER draws a frontier: the setting with the fewest
diverged paths, then the lowest CRPS) and filters_<plant>_frontier with its sentence: the smallest M
at which each filter's rate is within 0.01 of the stochastic EnKF at M = 300 (no inflation, no
relaxation, no d) with no path diverged in any seed.

    python experiments/fig_filters.py [--root outputs] [--out outputs/report]
"""
import numpy as np
import pandas as pd

from rdsexp import report
from rdsexp.experiment.store import files

NAME = "filters"
SWEEP = "filters"
TOLERANCE = 0.01
KEYS = ("enkf.variant", "enkf.inflation", "enkf.relaxation", "enkf.disturbance", "enkf.ensemble_size", "seed")
FILTER = ["variant", "inflation", "relaxation", "disturbance"]      # a filter: its variant and knobs
KNOBS = FILTER[1:]


def points(runs: list[report.Run]) -> pd.DataFrame:
    """One row per run: the filter settings, M, seed and the closed loop's metrics."""
    rows = []
    for r in runs:
        m = r.table("metrics").set_index("experiment")
        loop = m.loc["closed_loop"] if "closed_loop" in m.index else None
        rows.append({"variant": r.get("enkf.variant"), "inflation": inflation(r.get("enkf.inflation")),
                     "relaxation": float(r.get("enkf.relaxation")),
                     "disturbance": disturbance(r.get("enkf.disturbance")), "M": int(r.get("enkf.ensemble_size")),
                     "seed": r.get("seed"), "xi_crps": r.record.summary.xi_crps,
                     # no closed loop (no gain from the identified model) counts as diverged
                     **{c: (loop[c] if loop is not None else (1.0 if c == "failed_fraction" else np.nan))
                        for c in ("rate", "failed_fraction", "xi_rmse", "x_rmse", "xi_spread_error")}})
    return pd.DataFrame(rows)


def inflation(value) -> str:
    """enkf.inflation as text, one type for grouping: "1", "1.1", or "adaptive"."""
    return value if isinstance(value, str) else f"{float(value):g}"


def disturbance(value) -> str:
    """enkf.disturbance as text: "off" (None), or its scale / entries."""
    return "off" if value is None else (f"{float(value):g}" if isinstance(value, (int, float)) else str(value))


def label(variant, rho: str, relaxation, d: str = "off") -> str:
    extra = ([f"$\\rho$={rho}"] * (rho != "1") + [f"$\\alpha$={relaxation:g}"] * (relaxation != 0)
             + [f"d={d}"] * (d != "off"))
    return " ".join([variant, *extra])


def summary(frame: pd.DataFrame) -> pd.DataFrame:
    """Per (filter, M): rate mean and interval over seeds without divergence, diverged fractions, RMSE."""
    rows = []
    for (v, rho, a, d, M), g in frame.groupby([*FILTER, "M"]):
        ok = g["failed_fraction"] == 0
        mean, lo, hi, n = report.seed_interval(g.loc[ok, "rate"])
        rows.append({"variant": v, "inflation": rho, "relaxation": a, "disturbance": d, "M": M, "seeds": len(g),
                     "seeds_diverged": int((~ok).sum()), "diverged_fraction": float(g["failed_fraction"].mean()),
                     "rate": mean, "rate_low": lo, "rate_high": hi,
                     "xi_rmse": float(g.loc[ok, "xi_rmse"].mean()) if ok.any() else np.nan,
                     "xi_spread_error": float(g.loc[ok, "xi_spread_error"].mean()) if ok.any() else np.nan,
                     # the model is scored in every seed that has one (a diverged loop does not undo it)
                     "xi_crps": float(g["xi_crps"].mean())})
    return pd.DataFrame(rows)


def best_tuned(stats: pd.DataFrame, ref: float) -> pd.DataFrame:
    """Each variant at each M with its best knobs (inflation, relaxation, d): the fewest diverged paths, then
    the lowest CRPS of the modeled xi (a variant without knobs, enkf_n, is its own best)."""
    order = stats.assign(crps_rank=stats["xi_crps"].fillna(np.inf)).sort_values(
        ["variant", "M", "diverged_fraction", "crps_rank"])
    best = order.groupby(["variant", "M"], as_index=False).first().drop(columns="crps_rank")
    knobs = stats.groupby("variant").apply(lambda g: g[KNOBS].drop_duplicates().shape[0], include_groups=False)
    best["knobs_tried"] = best["variant"].map(knobs)
    best["rate_minus_reference"] = best["rate"] - ref
    return best


def frontier(stats: pd.DataFrame) -> tuple[pd.DataFrame, float, str]:
    """Smallest M per filter with |rate - reference| <= TOLERANCE and no divergence in any seed."""
    ref_rows = stats[(stats["variant"] == "stochastic") & (stats["inflation"] == "1") & (stats["relaxation"] == 0)
                     & (stats["disturbance"] == "off") & (stats["M"] == stats["M"].max())]
    ref = float(ref_rows["rate"].iloc[0]) if len(ref_rows) else np.nan
    Mref = int(stats["M"].max())
    rows = []
    for (v, rho, a, d), g in stats.groupby(FILTER):
        good = g[(g["seeds_diverged"] == 0) & (np.abs(g["rate"] - ref) <= TOLERANCE)].sort_values("M")
        best = good.iloc[0] if len(good) else None
        rows.append({"variant": v, "inflation": rho, "relaxation": a, "disturbance": d,
                     "measured_M": ", ".join(map(str, sorted(g["M"]))),
                     "smallest_M": int(best["M"]) if best is not None else None,
                     "rate_at_smallest_M": float(best["rate"]) if best is not None else np.nan})
    table = pd.DataFrame(rows)
    parts = [f"{label(r.variant, r.inflation, r.relaxation, r.disturbance).replace('$', '').replace(chr(92), '')}: "
             + (f"M = {int(r.smallest_M)}" if pd.notna(r.smallest_M) else f"none of M = {r.measured_M}")
             for r in table.itertuples()]
    sentence = (f"Smallest ensemble size M at which the closed-loop rate is within {TOLERANCE} of the stochastic "
                f"EnKF at M = {Mref} ({resolution(ref_rows)}) with no path diverged in any seed: "
                + "; ".join(parts) + ".")
    return table, ref, sentence


def resolution(ref_rows: pd.DataFrame) -> str:
    """The reference rate with its 95% interval over seeds: how finely the study resolves a rate."""
    if not len(ref_rows):
        return "not measured"
    r = ref_rows.iloc[0]
    if "rate_low" not in r or not np.isfinite(r["rate_low"]):
        return f"{r['rate']:.4f}"
    return f"{r['rate']:.4f}, 95% interval over {int(r['seeds'] - r['seeds_diverged'])} seeds [{r['rate_low']:.4f}, " \
           f"{r['rate_high']:.4f}]"


STYLE = {"stochastic": "black", "etkf": "0.5"}
MARKERS = ["o", "s", "^", "D", "v", "x"]        # one per (inflation, relaxation)
LINES = {"off": "-"}                            # the d estimate off: solid; on: dashed


def draw(stats: pd.DataFrame, ref: float, plant: str):
    fig, axes = report.figure(report.PAGE_WIDTH, 4.6, 2, 2)
    axes = axes.ravel()
    options = sorted({tuple(r) for r in stats[["inflation", "relaxation"]].itertuples(index=False)})
    for (v, *knobs), g in stats.groupby(FILTER):
        g = g.sort_values("M")
        marker, ls = MARKERS[options.index(tuple(knobs[:2])) % len(MARKERS)], LINES.get(knobs[2], "--")
        kw = dict(color=STYLE.get(v, "0.3"), ls=ls, marker=marker, ms=3, label=label(v, *knobs))
        clean = g["seeds_diverged"] == 0
        axes[0].errorbar(g["M"], g["rate"], yerr=[g["rate"] - g["rate_low"], g["rate_high"] - g["rate"]],
                         capsize=2, **kw)
        axes[0].plot(g.loc[~clean, "M"], g.loc[~clean, "rate"], ls="none", marker=marker, ms=6, mfc="white",
                     color=kw["color"])
        axes[1].plot(g["M"], g["diverged_fraction"], **kw)
        axes[2].plot(g["M"], g["xi_rmse"], **kw)
        axes[3].plot(g["M"], g["xi_crps"], **kw)
    if np.isfinite(ref):
        axes[0].axhspan(ref - TOLERANCE, ref + TOLERANCE, color="0.9", zorder=0,
                        label=f"stochastic M=300 $\\pm${TOLERANCE}")
    titles = ("closed-loop rate (open marker: some seed\ndiverged, rate over the others)",
              "diverged fraction of paths\n(mean over seeds)", "RMSE of $\\xi_{k|k}$\n(seeds without divergence)",
              "CRPS of the modeled $\\xi$ against the plant's\n(mean over seeds, lower is better)")
    sizes = sorted(stats["M"].unique())
    for ax, title in zip(axes, titles):
        ax.set_xscale("log")
        ax.set_xticks(sizes, [str(M) for M in sizes])
        ax.minorticks_off()
        ax.set_xlim(sizes[0] / 1.3, sizes[-1] * 1.3)
        ax.set_xlabel("ensemble size M")
        ax.set_title(title)
    axes[1].set_ylim(-0.02, 1.02)
    crps = stats["xi_crps"].to_numpy(float)
    crps = crps[np.isfinite(crps) & (crps > 0)]
    if len(crps) and crps.max() > 10 * crps.min():         # from the true spread up to a model far off
        axes[3].set_yscale("log")
    rates = stats["rate"].to_numpy(float)
    if np.isfinite(rates).any():        # the means in view; t-intervals over a few seeds may leave the frame
        lo, hi = np.nanmin(np.append(rates, ref)), np.nanmax(np.append(rates, ref))
        axes[0].set_ylim(lo - 0.1, hi + 0.1)
    handles, labels = axes[0].get_legend_handles_labels()       # below the panels, clear of every curve
    fig.legend(handles, labels, frameon=False, fontsize=6, loc="outside lower center", ncol=4)
    fig.suptitle(f"plant {plant}", fontsize=8)
    return fig


def main(argv=None):
    args = report.arguments(__doc__.splitlines()[0], argv)
    by_plant = latest_per_plant(report.load_runs(args.root))
    if not by_plant:
        raise SystemExit(f"no stored `{SWEEP}` sweep under {args.root}: run `rdsexp +sweep={SWEEP}` first")
    paths = []
    for plant, runs in sorted(by_plant.items()):
        report.check_versions(runs, args.allow_mixed)
        stats = summary(points(runs))
        table, ref, sentence = frontier(stats)
        name = f"{NAME}_{plant}"
        sentence = f"Plant {plant}: {sentence}"
        paths += report.save_figure(draw(stats, ref, plant), args.out, name, runs, __file__, caption=sentence)
        report.write_table(stats, args.out, f"{name}_summary", runs, __file__)
        report.write_table(table, args.out, f"{name}_frontier", runs, __file__)
        report.write_table(best_tuned(stats, ref), args.out, f"{name}_best", runs, __file__)
        files.atomic_write_bytes(args.out / f"{name}_frontier.txt", (sentence + "\n").encode())
        print(sentence)
    return paths


def latest_per_plant(runs: list[report.Run]) -> dict[str, list[report.Run]]:
    """plant name -> the latest run of each point (filter settings, M, seed) of the `filters` sweeps."""
    return report.latest_per_plant(runs, SWEEP, KEYS)


if __name__ == "__main__":
    report.script(main)
