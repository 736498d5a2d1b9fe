"""Online control's defaults against the offline scheme, per plant, start and seed.

`controller=online` runs the online (learning-type) loop beside the offline scheme of the same seed, on
the same plant samples and EnKF noise (a paired comparison). For each library plant (`paper`, `dropout`,
`cart_pole`, `two_carts`, `multiplicative`), each start (`controller.initial=zero` and `nominal`) and
each seed, one in-process run (`pipeline.run_experiment`, tracking off, no open loop: nothing of the
comparison depends on it) gives one row:

- lost_off / lost_on: paths the offline / online loop lost (diverged or failed), of --paths; only_on /
  only_off: the paths one loop alone lost;
- rate_off: the offline gain's exact mean-square rate on the true plant;
- rate_on: the median over paths of the online loop's final gains' exact rate on the true plant;
- gap: rate_on - rate_off (negative: online ends better);
- unstable: final online gains with exact rate >= 1 on the true plant; adopt: adoptions per path;
- first_k: the median step of a path's first adoption (-: none adopted).

Then one summary line per plant and start, over the seeds: lost paths (sum) online against offline,
the paired sign test of online losing more over every seed's paths (`verdict.paired_losses`; the
discordant paths of independent seeds add up), the gap's median and worst seed, the seeds within
0.005 (or better), the pooled gap (median over every path of every seed of its final rate minus its
seed's offline rate) and whether both targets hold:
online loses no more paths than offline in any seed, and the pooled gap is <= 0.005.

    python experiments/online_defaults.py [--seeds 10] [--paths 100] [--plants paper,dropout,...]
        [--starts zero,nominal] [--override controller.KEY=VALUE ...] [--out CSV]

Every run uses the defaults of `controller=online` and nothing else but the seed, the path count, the
start and --override (to measure a candidate setting against the defaults). One process, one core.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from coverage import LIBRARY, experiment  # noqa: E402  (the validated Experiment of a plant)

from rdsexp.numerics.verdict import sign_test  # noqa: E402

TOLERANCE = 0.005        # the final gains' median rate may exceed the offline gain's by this much


def one_run(plant: str, start: str, seed: int, paths: int, overrides=()) -> tuple[dict, np.ndarray]:
    """One paired run: its row (see the module docstring) and the final online gains' rates minus the
    offline gain's rate, per path (NaN for a path that never held a gain)."""
    from rdsexp.experiment.pipeline import run_experiment
    exp = experiment(plant, None, ["controller=online", f"controller.initial={start}", f"seed={seed}",
                                   f"closed_loop.paths={paths}", "closed_loop.open_loop=false", "tracking=off",
                                   *overrides])
    tables = run_experiment(exp).tables
    metrics = tables["metrics"].set_index("experiment")
    ways = tables["paths"]
    lost = {name: int((ways[ways["experiment"] == name]["failed_at"] >= 0).sum()) for name in ("closed_loop", "online")}
    final = ways[ways["experiment"] == "online"]["final_rate_plant"].to_numpy(float)
    online = metrics.loc["online"]
    offline = float(online["offline_rate_plant"])
    control = tables["controller"]
    first = control[(control["k"] >= 0) & control["adopted"]].groupby("path")["k"].min()
    row = {"plant": plant, "start": start, "seed": seed, "lost_off": lost["closed_loop"], "lost_on": lost["online"],
           "rate_off": offline, "rate_on": float(np.nanmedian(final)), "gap": float(np.nanmedian(final)) - offline,
           "only_on": int(online["lost_online_only"]), "only_off": int(online["lost_offline_only"]),
           "unstable": int(np.sum(final >= 1)), "adopt": float(online["adoptions_per_path"]),
           "first_k": float(first.median()) if len(first) else np.nan}
    return row, final - offline


def summarize(rows: pd.DataFrame, gaps: np.ndarray, paths: int) -> dict:
    """One plant and start over its seeds (see the module docstring)."""
    pooled = float(np.nanmedian(gaps))
    no_more_lost = bool((rows["lost_on"] <= rows["lost_off"]).all())
    only_on, only_off = int(rows["only_on"].sum()), int(rows["only_off"].sum())
    return {"seeds": len(rows), "lost_on": int(rows["lost_on"].sum()), "lost_off": int(rows["lost_off"].sum()),
            "of": len(rows) * paths, "seeds_lost_more": int((rows["lost_on"] > rows["lost_off"]).sum()),
            "only_on": only_on, "only_off": only_off,
            "paired_p": sign_test(only_on, only_off),
            "gap_median": float(rows["gap"].median()), "gap_worst": float(rows["gap"].max()),
            "within": int((rows["gap"] <= TOLERANCE).sum()), "gap_pooled": pooled,
            "unstable": int(rows["unstable"].sum()), "adopt": float(rows["adopt"].mean()),
            "first_k": float(rows["first_k"].median()),
            "met": no_more_lost and pooled <= TOLERANCE}


def summary_line(plant: str, start: str, s: dict) -> str:
    return (f"{plant:>14s} {start:>7s}: lost online {s['lost_on']}/{s['of']} vs offline {s['lost_off']}/{s['of']}"
            f" (seeds losing more: {s['seeds_lost_more']}; alone {s['only_on']} vs {s['only_off']}, paired p "
            f"{s['paired_p']:.3g}); gap median {s['gap_median']:+.4f}, worst seed "
            f"{s['gap_worst']:+.4f}, within {TOLERANCE} in {s['within']}/{s['seeds']}, pooled {s['gap_pooled']:+.4f}; "
            f"final gains unstable {s['unstable']}; adoptions/path {s['adopt']:.2f}; first adoption k "
            f"{s['first_k']:.0f}: {'MET' if s['met'] else 'NOT MET'}")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--paths", type=int, default=100)
    parser.add_argument("--plants", default=",".join(LIBRARY))
    parser.add_argument("--starts", default="zero,nominal")
    parser.add_argument("--override", action="append", default=[], metavar="KEY=VALUE",
                        help="extra override for every run (repeatable), e.g. controller.resamples=0")
    parser.add_argument("--out", type=Path, help="CSV of the per-seed table")
    parser.add_argument("--quiet", action="store_true", help="summary lines only")
    args = parser.parse_args(argv)
    plants = [p for p in args.plants.split(",") if p]
    starts = [s for s in args.starts.split(",") if s]
    print(f"online vs offline, {args.seeds} seeds x {args.paths} paths; overrides: {' '.join(args.override) or 'none'}",
          flush=True)
    clock = time.time()
    all_rows, lines, met = [], [], []
    for plant in plants:
        for start in starts:
            rows, gaps = [], []
            for seed in range(args.seeds):
                row, gap = one_run(plant, start, seed, args.paths, args.override)
                rows.append(row)
                gaps.append(gap)
                if not args.quiet:
                    print(f"{plant:>14s} {start:>7s} {seed:3d}  lost {row['lost_on']:3d} vs {row['lost_off']:3d}  "
                          f"rate {row['rate_on']:.4f} vs {row['rate_off']:.4f}  gap {row['gap']:+.4f}  "
                          f"unstable {row['unstable']:3d}  adopt {row['adopt']:.2f}  first_k {row['first_k']:.0f}",
                          flush=True)
            frame = pd.DataFrame(rows)
            s = summarize(frame, np.concatenate(gaps), args.paths)
            all_rows += rows
            met.append(s["met"])
            lines.append(summary_line(plant, start, s))
            print(lines[-1], flush=True)
    table = pd.DataFrame(all_rows)
    print("\nsummary (targets: online loses no more paths than offline in any seed; pooled median gap <= "
          f"{TOLERANCE}):")
    print("\n".join(lines))
    print(f"met in {sum(met)} of {len(met)} plant x start cells; {time.time() - clock:.0f} s")
    if args.out:
        table.to_csv(args.out, index=False)
        print(f"table: {args.out}")
    return table


if __name__ == "__main__":
    main()
