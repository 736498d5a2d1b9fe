"""Calibration of the distribution model (the paper's first half) against the laws the plants are simulated from.

In the spirit of simulation-based calibration: per plant, --seeds whole runs with the defaults (blind: the prior
guess is the plant file's `nominal:` or xi = 0, never the law), and per component of xi the modeled mean and
standard deviation against the plant file's law mapped into the model's xi (`plant_xi_mean`, `plant_xi_std`),
with the uncertainty the run states (`modeling_uncertainty`: the sd of each over its draws). Printed
per plant:

- z: (modeled - true) / stated sd, median |z| and max |z| over components and seeds, for the mean and the std;
- cover: the fraction of the 95% intervals (modeled +- 1.96 stated sd) that hold the truth (nominal 0.95);
- err: median |modeled mean - true| / true sd, and median |modeled std / true std - 1|;
- (pooled, p > 1) the correlations of each pair: their 95% intervals' coverage and the median |error|;
- status: the modeling statuses (ok, unsettled, at_prior_edge, weakly_identified, or why no model), and the
  cover over the ok runs;
- e2e: the end-to-end figure of the loop's gain on the true plant against the optimum for the true law (median
  and 90th percentile): for ms_lqr the ratio of exact LQ costs, for the rate designs (proposed,
  policy_iteration) the exact rate's excess over the optimal rate.

Plants: the library's, `unst3` (3 states, a Bernoulli actuator dropout and a uniform parameter on A[0, 0]; nominal
[1, 0]) and --random plants of `random_plants.py`'s draw (seed 0), each stating a nominal one standard deviation
off the law's mean in every component (`random_plants.wrong_guess`). The loops are cut to what the gain needs
(2 paths, no open loop, no floor): only the model and the gain are measured here.

Data runs (--data): recorded data of a researcher's own simulator (`user_data.py`, 80 paths x 101 steps, a new
data set per seed), identified with rdsexp's defaults for a system of one's own: `user` (two outputs, noise sd
0.01 where the EnKF assumes 0.1), `user_matched` (the EnKF told the data's noise), `user_one_output` (the first
state only). Their end-to-end figure is the gain's exact LQ cost on the true law over the optimum's.

Each run's row can be kept (--rows FILE, JSON lines), so that a study split over processes or sessions is pooled
into one table (--pool FILE ...: no run, the table of the rows in those files). The last lines pool over plants:
the intervals' coverage over every modeled component of every run, and every run's end-to-end figure.

    python experiments/model_calibration.py [--seeds 20] [--seed-from 0] [--random 10] [--random-from 0]
        [--plants a,b] [--data a,b] [--override KEY=VALUE ...] [--rows FILE] [--pool FILE ...]
"""
from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from rdsexp.numerics.analysis import exact_costs, ms_rate
from rdsexp.numerics.synthesis import synthesize

sys.path.insert(0, str(Path(__file__).resolve().parent))
import random_plants  # noqa: E402  (the random plants' draw)
import user_data  # noqa: E402  (a researcher's own simulator)
from coverage import LIBRARY, UNST3, experiment  # noqa: E402

DATA_SETS = {"user": ({}, []), "user_matched": ({}, ["enkf.Q.x=1e-4", "enkf.R=1e-4"]),
             "user_one_output": ({"outputs": 1}, [])}     # user_data.write's arguments, the run's overrides

FAST = ["closed_loop.paths=2", "closed_loop.open_loop=false", "closed_loop.floor_paths=0", "tracking=off"]
RATE_DESIGNS = ("proposed", "policy_iteration", "nominal_lmi")


def optimum(exp, method: str) -> float:
    """The optimum for the true law of the method's objective: the LQ cost (ms_lqr) or the rate."""
    truth = exp.plant.check_distribution(None)
    if method in RATE_DESIGNS:
        return min(ms_rate(exp.plant, None, synthesize(exp.plant, truth, method).F)
                   for method in ("proposed", "policy_iteration"))
    return exact_costs(exp.plant, None, synthesize(exp.plant, truth, "ms_lqr").F)["lq_cost"]


def write_random_plants(config_dir: Path, count: int, first: int = 0) -> list[str]:
    """Plant files rp<first>..rp<count - 1> of random_plants.py's draw (seed 0) in config_dir/plant, each with a
    nominal one standard deviation off its law's mean (blind); their names."""
    names = []
    for plant in random_plants.draw_plants(count, 0)[first:]:
        path = random_plants.write_plant(plant, config_dir, "model_calibration.py")
        content = yaml.safe_load(path.read_text())
        content["nominal"] = random_plants.wrong_guess(plant, 0, 1.0).tolist()
        path.write_text(yaml.safe_dump(content, default_flow_style=None, sort_keys=False, width=100))
        names.append(plant.name)
    return names


def one_run(exp) -> dict:
    """The modeled moments against the truth, the stated sds, the status and the end-to-end figure of one run."""
    from rdsexp.experiment.pipeline import run_experiment
    out = run_experiment(exp)
    s = out.summary
    row = {"status": s.get("modeling_status")}
    if "xi_mean" not in s or "plant_xi_mean" not in s:
        return row
    u = s.get("modeling_uncertainty") or {}
    for what in ("mean", "std"):
        row[what] = np.asarray(s[f"xi_{what}"]) - np.asarray(s[f"plant_xi_{what}"])
        row[f"{what}_sd"] = np.asarray(u.get(f"xi_{what}_sd", [np.nan] * len(s["xi_mean"])))
    row["true_std"] = np.asarray(s["plant_xi_std"])
    if "xi_corr" in s:          # p > 1: the modeled correlations against the law's
        row["corr"] = np.asarray(s["xi_corr"]) - np.asarray(s["plant_xi_corr"])
        row["corr_sd"] = np.asarray(u.get("xi_corr_sd", [np.nan] * len(s["xi_corr"])))
    gains = out.tables["gains"]
    chosen = gains[gains["selected"]]
    method = exp.design.method
    if len(chosen) and np.isfinite(chosen["rate_plant"].iloc[0]):
        best = optimum(exp, method)
        row["e2e"] = (chosen["rate_plant"].iloc[0] - best if method in RATE_DESIGNS
                      else chosen["lq_cost_plant"].iloc[0] / best)
        row["e2e_kind"] = "rate +" if method in RATE_DESIGNS else "cost x"
    return row


def one_data_run(name: str, seed: int, where: Path, overrides: list[str]) -> dict:
    """A data run on a new data set of `user_data`'s simulator (DATA_SETS[name]), against its known law."""
    from hydra import compose, initialize_config_dir

    from rdsexp.conf import __path__ as conf_path
    from rdsexp.experiment.config import build
    from rdsexp.experiment.pipeline.run import run_on_data
    from rdsexp.numerics.distributions import from_spec
    from rdsexp.numerics.systems import AffineRandomSystem
    kwargs, extra = DATA_SETS[name]
    model = user_data.write_config(where, kwargs.get("outputs", 2))
    data = user_data.write(where / f"{name}_{seed}.csv", seed, **kwargs)
    with initialize_config_dir(config_dir=str(Path(conf_path[0]).resolve()), version_base="1.3"):
        exp = build(compose("config", overrides=[f"hydra.searchpath=[file://{where}]", f"data.file={data}",
                                                 f"model={model}", "plant=recorded", "tracking=off", f"seed={seed}",
                                                 *extra, *overrides]))
    out = run_on_data(exp)
    s = out.summary
    row = {"status": s.get("modeling_status")}
    if s.get("xi_mean") is None:
        return row
    u = s.get("modeling_uncertainty") or {}
    for what, truth in (("mean", user_data.TRUE_MEAN), ("std", user_data.TRUE_STD)):
        row[what] = np.asarray(s[f"xi_{what}"]) - truth
        row[f"{what}_sd"] = np.asarray(u.get(f"xi_{what}_sd", [np.nan] * 2))
    row["true_std"] = user_data.TRUE_STD
    noise = (s.get("modeling_estimator") or {}).get("noise_scale")
    if noise:           # the estimated noise scale's 95% interval against the data's (sd^2 over what the EnKF assumes)
        row["noise"] = [noise["low"], noise["median"], noise["high"]]
        row["noise_truth"] = user_data.SD ** 2 / exp.filter.enkf.Q[0, 0]
    if "xi_corr" in s:              # the law's components are independent
        row["corr"], row["corr_sd"] = np.asarray(s["xi_corr"]), np.asarray(u.get("xi_corr_sd", [np.nan]))
    truth = AffineRandomSystem(exp.model.A, exp.model.B, exp.model.C, exp.model.D,
                               xi_dist=from_spec(user_data.TRUE_LAW))
    chosen = out.tables["gains"][out.tables["gains"]["selected"]]
    F = np.array([[chosen[f"F[{i},{j}]"].iloc[0] for j in range(exp.model.n)] for i in range(exp.model.m)]) \
        if len(chosen) else np.full((1, 1), np.nan)
    if np.all(np.isfinite(F)):            # the gain's exact LQ cost on the true law over the optimum's
        best = exact_costs(truth, None, synthesize(truth, truth.check_distribution(None), "ms_lqr").F)["lq_cost"]
        row["e2e"], row["e2e_kind"] = exact_costs(truth, None, F)["lq_cost"] / best, "cost x"
    return row


def summarize(rows: list[dict]) -> dict:
    """z-scores, coverage, relative errors, status counts and the end-to-end figure over a plant's runs."""
    statuses = {}
    for r in rows:          # a failure counted by its reason, not by the step and path it stopped at
        status = re.sub(r" at k = \d+ \(path \d+\)", "", str(r["status"]))
        statuses[status] = statuses.get(status, 0) + 1
    out = {"runs": len(rows), "status": statuses}
    modeled = [r for r in rows if "mean" in r]
    ok = [r for r in modeled if r["status"] == "ok"]
    hits = [np.abs(np.concatenate([r[w] for w in ("mean", "std")])) <= 1.96 * np.concatenate([r[f"{w}_sd"] for w in
            ("mean", "std")]) for r in ok]
    known = [np.concatenate([r["true_std"] > 0] * 2) for r in ok]
    out["ok_cover"] = float(np.mean(np.concatenate([h[k] for h, k in zip(hits, known)]))) if ok else np.nan
    out["ok_components"] = int(sum(k.sum() for k in known))
    for what in ("mean", "std"):
        err = np.concatenate([r[what] for r in modeled]) if modeled else np.zeros(0)
        sd = np.concatenate([r[f"{what}_sd"] for r in modeled]) if modeled else np.zeros(0)
        truth_sd = np.concatenate([r["true_std"] for r in modeled]) if modeled else np.zeros(0)
        known = truth_sd > 0                                   # a constant component has no spread to compare
        with np.errstate(all="ignore"):
            z = np.abs(err / sd)
            rel = np.abs(err / truth_sd)            # the mean's error in true sds; the std's relative error
        out[f"{what}_z_median"] = float(np.nanmedian(z[known])) if known.any() else np.nan
        out[f"{what}_z_max"] = float(np.nanmax(z[known])) if known.any() else np.nan
        out[f"{what}_cover"] = float(np.mean(z[known] <= 1.96)) if known.any() else np.nan
        out[f"{what}_err"] = float(np.nanmedian(rel[known])) if known.any() else np.nan
        out[f"{what}_components"] = int(known.sum())
    # the correlations (p > 1): their intervals' coverage and the median |error|
    corr = [(r["corr"], r["corr_sd"]) for r in modeled if "corr" in r]
    err = np.concatenate([e for e, _ in corr]) if corr else np.zeros(0)
    sd = np.concatenate([s for _, s in corr]) if corr else np.zeros(0)
    out["corr_components"] = int(err.size)
    out["corr_cover"] = float(np.mean(np.abs(err) <= 1.96 * sd)) if err.size else np.nan
    out["corr_err"] = float(np.median(np.abs(err))) if err.size else np.nan
    noise = np.array([[*r["noise"], r["noise_truth"]] for r in rows if "noise" in r]).reshape(-1, 4)
    out["noise_runs"] = len(noise)       # (data runs) the noise scale's interval against the data's
    out["noise_hits"] = int(np.sum((noise[:, 0] <= noise[:, 3]) & (noise[:, 3] <= noise[:, 2])))
    out["noise_ratio"] = float(np.median(noise[:, 1] / noise[:, 3])) if len(noise) else np.nan
    e2e = [r["e2e"] for r in rows if "e2e" in r]
    out["e2e_kind"] = next((r["e2e_kind"] for r in rows if "e2e_kind" in r), "")
    out["e2e"] = np.asarray(e2e)
    out["e2e_median"] = float(np.median(e2e)) if e2e else np.nan
    out["e2e_q90"] = float(np.quantile(e2e, 0.9)) if e2e else np.nan
    return out


def print_table(results: dict[str, dict]) -> None:
    print("| plant | runs | mean: median abs z / max / cover / err (true sd) | std: median abs z / max / cover / "
          "err (relative) | status | cover, ok runs | e2e median / q90 |")
    print("|---|---|---|---|---|---|---|")
    f = lambda v, fmt=".2f": "-" if v is None or not np.isfinite(v) else format(v, fmt)
    for name, r in results.items():
        status = ", ".join(f"{k} {v}" for k, v in sorted(r["status"].items(), key=lambda kv: str(kv[0])))
        print(f"| {name} | {r['runs']} | {f(r['mean_z_median'], '.1f')} / {f(r['mean_z_max'], '.0f')} / "
              f"{f(r['mean_cover'])} / {f(r['mean_err'])} | {f(r['std_z_median'], '.1f')} / {f(r['std_z_max'], '.0f')} "
              f"/ {f(r['std_cover'])} / {f(r['std_err'])} | {status} | {f(r['ok_cover'])} | {r['e2e_kind']} "
              f"{f(r['e2e_median'], '.3f')} / "
              f"{f(r['e2e_q90'], '.3f')} |")
    modeled = [r for r in results.values() if r["mean_components"]]
    pooled = lambda key: np.mean([r[key] for r in modeled if np.isfinite(r[key])]) if modeled else np.nan
    print(f"\nmean over plants: mean cover {pooled('mean_cover'):.2f}, std cover {pooled('std_cover'):.2f}; "
          f"ok runs {sum(r['status'].get('ok', 0) for r in results.values())} of "
          f"{sum(r['runs'] for r in results.values())}, their cover {pooled('ok_cover'):.2f}; median error: "
          f"mean {np.median([r['mean_err'] for r in modeled]):.2f} true sds, std "
          f"{np.median([r['std_err'] for r in modeled]):.2f}")
    # the intervals over every modeled component of every run: each plant weighs as many components as it has
    share = lambda key, count: (sum(r[key] * r[count] for r in modeled if r[count]) /
                                max(sum(r[count] for r in modeled), 1))
    print(f"pooled over components: mean cover {share('mean_cover', 'mean_components'):.3f}, std cover "
          f"{share('std_cover', 'std_components'):.3f}; ok runs' cover {share('ok_cover', 'ok_components'):.3f}")
    correlated = [r for r in modeled if r["corr_components"]]
    if correlated:          # (rows kept before the correlations were modeled have none)
        print(f"correlations: cover {share('corr_cover', 'corr_components'):.3f} over "
              f"{sum(r['corr_components'] for r in correlated)} pairs, median |error| "
              f"{np.median([r['corr_err'] for r in correlated]):.3f} over plants")
    for name, r in results.items():
        if r.get("noise_runs"):
            print(f"{name}: the noise scale's 95% interval holds the data's in {r['noise_hits']} of "
                  f"{r['noise_runs']} runs; median estimate / truth {r['noise_ratio']:.2f}")
    for kind in sorted({r["e2e_kind"] for r in results.values()} - {""}):
        e2e = np.concatenate([r["e2e"] for r in results.values() if r["e2e_kind"] == kind])
        print(f"end to end over every run ({kind}): median {np.median(e2e):.3f}, q90 {np.quantile(e2e, 0.9):.3f} "
              f"({e2e.size} runs)")


def save(rows: list[dict], path: Path, plant: str, seeds) -> None:
    """Append a plant's rows to `path`, a JSON line each (arrays as lists, with the plant and the seed)."""
    with open(path, "a") as f:
        for seed, row in zip(seeds, rows):
            f.write(json.dumps({"plant": plant, "seed": seed} | {k: v.tolist() if isinstance(v, np.ndarray) else v
                                                                 for k, v in row.items()}) + "\n")


def pooled(paths: list[str]) -> dict[str, dict]:
    """The table's entries from the rows kept in `paths` (one row per plant and seed: a later file's row wins)."""
    rows = {}
    for path in paths:
        for line in Path(path).read_text().splitlines():
            row = json.loads(line)
            rows[(row.pop("plant"), row.pop("seed"))] = {k: np.asarray(v) if isinstance(v, list) else v
                                                         for k, v in row.items()}
    plants = dict.fromkeys(plant for plant, _ in rows)
    return {plant: summarize([row for (name, _), row in sorted(rows.items()) if name == plant]) for plant in plants}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--seed-from", type=int, default=0, help="skip the seeds before this one")
    parser.add_argument("--random", type=int, default=10, help="random plants (random_plants.py's draw, seed 0)")
    parser.add_argument("--random-from", type=int, default=0, help="skip the random plants before this one")
    parser.add_argument("--plants", default=",".join(LIBRARY + ("unst3",)))
    parser.add_argument("--data", default="", help=f"data runs, of {', '.join(DATA_SETS)}")
    parser.add_argument("--override", nargs="*", default=[], metavar="KEY=VALUE")
    parser.add_argument("--rows", type=Path, help="append each run's row to this file (JSON lines)")
    parser.add_argument("--pool", nargs="+", metavar="FILE", help="no run: the table of the rows in these files")
    args = parser.parse_args(argv)
    if args.pool:
        print_table(pooled(args.pool))
        return
    start = time.perf_counter()
    seeds = range(args.seed_from, args.seeds)
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        config_dir = Path(tmp)
        (config_dir / "plant").mkdir()
        (config_dir / "plant" / "unst3.yaml").write_text(yaml.safe_dump(UNST3 | {"nominal": [1.0, 0.0]}))
        plants = [(name, None if name in LIBRARY else config_dir) for name in args.plants.split(",") if name]
        plants += [(name, config_dir) for name in write_random_plants(config_dir, args.random, args.random_from)]
        for name, where in plants:
            rows = [one_run(experiment(name, where, [f"seed={seed}", *FAST, *args.override])) for seed in seeds]
            results[name] = summarize(rows)
            if args.rows:
                save(rows, args.rows, name, seeds)
            print(f"{name}: {results[name]['runs']} runs", file=sys.stderr)
        for name in filter(None, args.data.split(",")):
            rows = [one_data_run(name, seed, config_dir, args.override) for seed in seeds]
            results[name] = summarize(rows)
            if args.rows:
                save(rows, args.rows, name, seeds)
            print(f"{name}: {results[name]['runs']} runs", file=sys.stderr)
    print_table(results)
    print(f"\n{time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
