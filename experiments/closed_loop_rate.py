"""The closed-loop rate k = 60..80 (paper 0.8473) by gain source and by whether the EnKF sees d_k.

From the latest `closed_loop_rate` sweep: the closed loop with the proposed gain designed from the
identified moments (gain.source = identified: identification noise and closed-loop noise together),
from the paper's printed moments (reported) and the paper's own F (fixed): the same gain in every
seed, so only closed-loop noise remains; each with the EnKF told d_k and not told (the paper does
not say). Per group, over its seeds:
- the paper's two-point ratio per seed: mean with a 95% t-interval over seeds, and its range;
- the ratio pooled over all seeds' paths with a studentised bootstrap interval resampling seeds,
  then paths (and the path-only bootstrap interval of the first seed);
- the largest path's share of the sample mean of ||q_80||^2 (median and max over seeds);
- a robust estimate (median over 10 path groups of the least-squares log-slope over k = 60..80);
- the exact rate of the gain on the true plant and the exact two-point ratio of the ideal loop
  (state feedback, same d_k): what the Monte Carlo estimates would approach without the EnKF.

    python experiments/closed_loop_rate.py [--root outputs] [--out outputs/report]
"""
import numpy as np
import pandas as pd

from rdsexp import report
from rdsexp.numerics.analysis import bootstrap_rate, largest_path_share, robust_rate

NAME = "closed_loop_rate"
SWEEP = "closed_loop_rate"
SOURCES = {"identified": "designed from identified moments", "reported": "designed from the paper's moments",
           "fixed": "the paper's F"}


def _ideal_two_point(run: report.Run, k_from: int, k_to: int) -> float:
    """(rms_k_to / rms_k_from)^(1/(k_to - k_from)) of the run's exact ideal closed loop."""
    exact = run.table("exact")
    rms = exact[exact["experiment"] == "closed_loop"].set_index("k")["rms"]
    return float((rms[k_to] / rms[k_from]) ** (1 / (k_to - k_from)))


def group_rows(runs: list[report.Run]) -> pd.DataFrame:
    rows = []
    keys = sorted({(r.get("gain.source") or "identified", bool(r.get("closed_loop.filter_sees_disturbance")))
                   for r in runs}, key=lambda t: (list(SOURCES).index(t[0]) if t[0] in SOURCES else 9, t[1]))
    for source, told in keys:
        chosen = sorted([r for r in runs if (r.get("gain.source") or "identified") == source
                         and bool(r.get("closed_loop.filter_sees_disturbance")) == told], key=lambda r: r.get("seed"))
        k_from, k_to = chosen[0].rate_window
        qs = [report.trajectory_array(r.table("trajectories"), "closed_loop", "q") for r in chosen]
        per_seed = np.array([r.table("metrics").set_index("experiment").loc["closed_loop", "rate"] for r in chosen])
        mean, lo, hi, n = report.seed_interval(per_seed)
        sq = [np.sum(q[[k_from, k_to]] ** 2, axis=-1) for q in qs]
        P = min(s.shape[1] for s in sq)
        pooled = bootstrap_rate(np.stack([s[0, :P] for s in sq]), np.stack([s[1, :P] for s in sq]), k_to - k_from)
        first = bootstrap_rate(sq[0][0][None], sq[0][1][None], k_to - k_from)
        share = np.array([largest_path_share(q, k_to) for q in qs])
        robust = np.array([robust_rate(q, k_from, k_to, groups=min(10, q.shape[1])) for q in qs])
        r_mean, r_lo, r_hi, _ = report.seed_interval(robust)
        gains = pd.concat([r.table("gains") for r in chosen])
        ideal_two_point = [_ideal_two_point(r, k_from, k_to) for r in chosen]
        paper = report.reference()["closed_loop"]["rate_k60_k80"]
        finite = per_seed[np.isfinite(per_seed)]
        rows.append({
            "gain": SOURCES.get(source, source), "source": source, "filter_sees_d": told, "seeds": len(chosen),
            "paths": P, "two_point_over_seeds": report.interval(mean, lo, hi),
            "seed_range": f"[{finite.min():.4f}, {finite.max():.4f}]" if finite.size else "",
            "pooled_bootstrap_seeds_paths": report.interval(*pooled),
            "first_seed_bootstrap_paths": report.interval(*first),
            "largest_path_share_median": float(np.nanmedian(share)), "largest_path_share_max": float(np.nanmax(share)),
            "robust_over_seeds": report.interval(r_mean, r_lo, r_hi),
            "exact_rate_true_plant": float(gains[gains["selected"]]["rate_plant"].mean()),
            "ideal_two_point_exact": float(np.mean(ideal_two_point)),
            "paper_in_seed_range": bool(finite.size >= 2 and finite.min() <= paper <= finite.max()),
            "paper_in_pooled_interval": bool(pooled[1] <= paper <= pooled[2]),
            "rate_mean": mean, "rate_low": lo, "rate_high": hi,
            "pooled_rate": pooled[0], "pooled_low": pooled[1], "pooled_high": pooled[2]})
    return pd.DataFrame(rows)


def caption(table: pd.DataFrame) -> str:
    """What the table shows, and per group the pooled rate against the paper's."""
    paper = report.reference()["closed_loop"]["rate_k60_k80"]
    text = (f"Paper: {paper} (one run, 200 paths). Two-point ratio k = 60..80 per seed (mean, 95% t-interval "
            "over seeds, range); pooled over all seeds' paths with a 95% studentised bootstrap interval "
            "resampling seeds then paths; the largest path's share of the sample mean of ||q_80||^2; a robust "
            "median-of-means log-slope; the exact rate of the gain on the true plant and the exact two-point "
            "ratio of the ideal loop (state feedback) it would approach without the EnKF. ")
    for row in table.itertuples():
        told = "told d_k" if row.filter_sees_d else "not told d_k"
        inside = "contains" if row.paper_in_pooled_interval else "excludes"
        text += (f"{row.gain}, EnKF {told}: pooled {row.pooled_bootstrap_seeds_paths} ({inside} the paper's "
                 f"value), largest path up to {row.largest_path_share_max:.0%} of the mean square. ")
    return text


def main(argv=None):
    args = report.arguments(__doc__.splitlines()[0], argv)
    runs = report.sweep_runs(args.root, SWEEP, args.allow_mixed)
    table = group_rows(runs)
    report.write_table(table, args.out, NAME, runs, __file__)
    report.write_caption(args.out, NAME, caption(table))
    return table


if __name__ == "__main__":
    report.script(main)
