"""Calibration of rdsexp's rate intervals and verdicts against exact truths (simulation-based calibration).

The open loop is the one loop whose truth is exact: its observer does not act on the plant, so its
paths are the plant's own (x_{k+1} = A(xi_k) x_k + B(xi_k) d_k) and the exact rate over the rate
window, (E||x_k_to||^2 / E||x_k_from||^2)^(1/(2 (k_to - k_from))) from the exact second moments
(`analysis.second_moments`), is what its Monte Carlo estimates. Per plant and path count, over
--seeds seeds, the open loop's paths are simulated (`simulation.simulate_state_feedback`, F = 0: the
same plant samples the EnKF loop would see) and judged by the verdict rdsexp gives a run
(`verdict.judge_loop`, no floor, the exact curve beside it); printed:

- coverage: the fraction of decisive intervals (the verdict stable or unstable) that hold the exact
  rate, with its binomial standard error;
- wrong: the fraction of decisive verdicts on the wrong side of 1 (truth: the exact rate);
- undetermined: the fraction of verdicts that are neither (failed counts here too);
- decisive: how many verdicts were decisive;
- heavy: the fraction of decisive runs whose paths' ||q_k_to||^2 have a Pareto k-hat above 0.7
  (`verdict.tail_index`: a few paths carry the mean square), and the coverage among those runs: whether the
  tail diagnostic tells the intervals that miss (issue 66 asks a decisive word to need more paths there).

Plants: the library's (`paper`, `dropout`, `cart_pole`, `two_carts`, `multiplicative`), `unst3` (3
states, a Bernoulli actuator dropout and a uniform parameter on A[0, 0], exact open-loop rate 1.064;
written below) and --random random plants of `experiments/random_plants.py`'s draw (half of them
mean-square unstable in open loop). The window is the library plant's configured one, else from the
end of the disturbance to the horizon, as `closed_loop.rate_window=auto` starts it.

    python experiments/coverage.py [--seeds 50] [--paths 30 100 300 auto] [--random 10] [--plants a,b]

auto: closed_loop.paths auto, its looks (50, 200, 800, 2000) each at 1 - 5% / 4, stopping where no verdict asks for
more paths (`verdict.asks_for_paths`); the last columns give the median and 95th percentile of the paths used.

--closed N adds, for the library plants and `unst3`, N seeded runs of the whole experiment per path
count (identification, design, EnKF closed loop with its floor) and counts the closed loops called
`stable` beside an ideal-loop exact rate >= 1 (rdsexp never says so) and the verdicts' spread.

--near-truth N judges closed loops, whose truth no formula gives, against a near-truth (with auto, --truth-paths
above its budget of 2000, e.g. 4000): per plant (library,
`unst3` and the --random plants) and seed, the same run with --truth-paths paths (same identification, gain and
first paths: every path has its own streams), its rate over the steps the smaller run's verdict was decided on
(with the floor's mean square subtracted where the verdict subtracted it). Per path count: how many verdicts were
decisive on the loop's own rate, the coverage of their intervals, the wrong words, the share undetermined, the
share of decisive runs with a heavy tail (k-hat > 0.7) with their coverage, how many were decided by the loop
at rest (its growth or failure: the same in both runs, not counted above), and how many had no loop (no model
or no gain).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from rdsexp.numerics.analysis import second_moments
from rdsexp.numerics.simulation import simulate_state_feedback
from rdsexp.numerics.verdict import HEAVY_TAIL, judge_at_looks, tail_index, window_start

sys.path.insert(0, str(Path(__file__).resolve().parent))
import random_plants  # noqa: E402  (the random plants' draw)

LIBRARY = ("paper", "dropout", "cart_pole", "two_carts", "multiplicative")
UNST3 = {"name": "unst3",
         "A": [[[1.05, 0.2, 0.0], [0.0, 0.95, 0.1], [0.0, 0.0, 0.9]], [[0, 0, 0]] * 3,
               [[0.3, 0, 0], [0, 0, 0], [0, 0, 0]]],
         "B": [[[0], [0], [0]], [[0], [0], [1]], [[0], [0], [0]]],
         "C": [[[1, 0, 0]]],
         "xi": {"family": "independent", "components": [{"family": "bernoulli", "prob": 0.8},
                                                         {"family": "uniform", "low": -1.0, "high": 1.0}]}}


def experiment(plant: str, config_dir: Path | None, overrides=()):
    """The validated Experiment of `plant` with the default configuration (a --config-dir plant
    file is identified with its own structure, `model=plant`)."""
    from hydra import compose, initialize_config_dir, initialize_config_module

    from rdsexp.experiment.config import build
    extra = [f"plant={plant}"] + ([] if plant in LIBRARY else ["model=plant"]) + list(overrides)
    if config_dir is None:
        with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
            return build(compose("config", overrides=extra))
    import rdsexp.conf
    with initialize_config_dir(config_dir=str(Path(rdsexp.conf.__file__).parent), version_base="1.3"):
        cfg = compose("config", overrides=[f"hydra.searchpath=[file://{config_dir}]", *extra])
    return build(cfg)


def open_loop_calibration(exp, paths, seeds: int) -> dict:
    """Coverage, wrong and undetermined fractions of the open loop's verdict over `seeds` seeds; paths: a count, or
    "auto": the looks of closed_loop.paths auto (`verdict.judge_at_looks`, the open loop's rule), with the median and
    95th percentile of the paths they stopped at."""
    looks = exp.loop.looks if paths == "auto" else (paths,)
    d, plant = exp.loop.disturbance, exp.plant
    K = d.shape[0] - 1
    window = exp.loop.rate_window or (window_start(d, exp.model.n), K)
    F0 = np.zeros((plant.m, plant.n))
    with np.errstate(all="ignore"):
        _, second = second_moments(plant, None, F0, exp.q0, d)
    exact_rms = np.sqrt(np.trace(second, axis1=1, axis2=2))
    truth = (exact_rms[window[1]] / exact_rms[window[0]]) ** (1 / (window[1] - window[0]))
    decisive = covered = wrong = heavy = heavy_covered = 0
    used = []
    for seed in range(seeds):
        with np.errstate(all="ignore"):
            x = simulate_state_feedback(plant, F0, d=d, x0=exp.q0, paths=looks[-1], seed=seed)
        sq = np.sum(x ** 2, axis=-1)
        grown = ~np.all(np.isfinite(sq) & (sq < 1e12), axis=0)         # the pipeline's divergence bound 1e6 on |q|
        failed_at = np.where(grown, np.argmax(~(np.isfinite(sq) & (sq < 1e12)), axis=0), -1)
        sq = np.where(np.arange(K + 1)[:, None] >= np.where(grown, failed_at, K + 1), np.nan, sq)
        v, P = judge_at_looks(sq, looks, False, failed_at=failed_at,
                              failure=np.where(grown, "diverged", "").astype(object), window=window,
                              exact_rms=exact_rms, floor=None, open_loop=True)
        used.append(P)
        if v.word in ("stable", "unstable"):
            decisive += 1
            wrong += (v.word == "stable") != (truth < 1)
            if np.isfinite(v.low):                 # an interval beside the word (a diverged loop has none)
                hit = v.low <= truth <= v.high
            else:
                hit = v.word == "unstable" and truth >= 1
            covered += hit
            if tail_index(sq[window[1], :P]) > HEAVY_TAIL:
                heavy, heavy_covered = heavy + 1, heavy_covered + hit
    share = (lambda count: count / decisive) if decisive else (lambda count: np.nan)
    return {"truth": truth, "window": window, "decisive": decisive, "coverage": share(covered), "wrong": share(wrong),
            "undetermined": 1 - decisive / seeds, "heavy": share(heavy),
            "heavy_coverage": heavy_covered / heavy if heavy else np.nan, "used": np.percentile(used, [50, 95])}


def closed_loop_contradictions(plant: str, config_dir: Path | None, paths: int, runs: int) -> dict:
    """Whole runs: how often the closed loop is called stable beside an ideal-loop exact rate >= 1."""
    from rdsexp.experiment.pipeline import run_experiment
    words, contradictions = {}, 0
    for seed in range(runs):
        exp = experiment(plant, config_dir, [f"seed={seed}", f"closed_loop.paths={paths}", "tracking=summary"])
        metrics = run_experiment(exp).tables["metrics"].set_index("experiment")
        if "closed_loop" not in metrics.index:
            words["no loop"] = words.get("no loop", 0) + 1
            continue
        row = metrics.loc["closed_loop"]
        words[row["verdict"]] = words.get(row["verdict"], 0) + 1
        contradictions += row["verdict"] == "stable" and row["exact_rate"] >= 1
    return {"verdicts": words, "stable_beside_exact_above_1": contradictions}


def closed_loop_near_truth(plant: str, config_dir: Path | None, paths: list, seeds: int,
                           truth_paths: int) -> dict:
    """Per path count (or auto): the closed loop's decisive intervals against the same run at truth_paths paths, and
    the paths each run was judged on."""
    from rdsexp.experiment.pipeline import run_experiment
    from rdsexp.experiment.store.stages import StageCache
    counts = {P: {"decisive": 0, "covered": 0, "wrong": 0, "undetermined": 0, "heavy": 0, "heavy_covered": 0,
                  "by_floor": 0, "no_loop": 0, "used": []} for P in paths}
    common = ["tracking=summary", "closed_loop.open_loop=false"]
    for seed in range(seeds):
        cache = StageCache.in_process()             # one identification and design for every path count
        run = lambda P, seed=seed, cache=cache: run_experiment(
            experiment(plant, config_dir, [f"seed={seed}", f"closed_loop.paths={P}", *common]), cache=cache)
        truth = run(truth_paths)
        if "closed_loop" not in truth.squares:      # no model or no gain: no loop to judge
            for c in counts.values():
                c["no_loop"] += 1
            continue
        sq = truth.squares["closed_loop"]
        floor = truth.tables["metrics"].set_index("experiment").loc["closed_loop", "floor_rms"]
        for P in paths:
            row = run(P).tables["metrics"].set_index("experiment").loc["closed_loop"]
            c = counts[P]
            c["used"].append(int(row["paths"]))
            if row["verdict"] not in ("stable", "unstable") or not np.isfinite(row["verdict_rate_low"]):
                c["undetermined"] += 1
                continue
            k_from, k_end = int(row["k_from"]), int(row["k_end"])
            if k_end < 0:                   # decided by the loop at rest (its growth), which both runs share
                c["by_floor"] += 1
                continue
            f = floor ** 2 if "floor's mean square subtracted" in row["verdict_reason"] else 0.0
            with np.errstate(all="ignore"):
                near = ((np.nanmean(sq[k_end]) - f) / (np.nanmean(sq[k_from]) - f)) ** (1 / (2 * (k_end - k_from)))
            hit = row["verdict_rate_low"] <= near <= row["verdict_rate_high"]
            c["decisive"] += 1
            c["covered"] += hit
            c["wrong"] += (row["verdict"] == "stable") != (near < 1)
            if row["tail_khat"] > HEAVY_TAIL:
                c["heavy"], c["heavy_covered"] = c["heavy"] + 1, c["heavy_covered"] + hit
    return counts


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=50)
    parser.add_argument("--paths", type=lambda v: v if v == "auto" else int(v), nargs="+", default=[30, 100, 300],
                        help="path counts, or auto (closed_loop.paths auto's looks)")
    parser.add_argument("--random", type=int, default=10, help="random plants (random_plants.py's draw, seed 0)")
    parser.add_argument("--plants", default=",".join(LIBRARY + ("unst3",)))
    parser.add_argument("--closed", type=int, default=0, help="whole runs per plant and path count (0: none)")
    parser.add_argument("--near-truth", type=int, default=0, help="seeds of closed loops against near-truths")
    parser.add_argument("--truth-paths", type=int, default=2000)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        config_dir = Path(tmp)
        (config_dir / "plant").mkdir()
        (config_dir / "plant" / "unst3.yaml").write_text(yaml.safe_dump(UNST3))
        names = [p for p in args.plants.split(",") if p]
        if args.random:
            for plant in random_plants.draw_plants(args.random, 0):
                random_plants.write_plant(plant, config_dir, "# coverage.py")
                names.append(plant.name)
        print(f"{'plant':16s} {'paths':>5s} {'window':>9s} {'exact':>7s} {'decisive':>8s} {'coverage':>14s} "
              f"{'wrong':>6s} {'undet.':>6s} {'heavy':>6s} {'cover|heavy':>11s} {'used (median, 95%)':>18s}")
        start = time.time()
        for name in names:
            exp = experiment(name, config_dir)
            for paths in args.paths:
                r = open_loop_calibration(exp, paths, args.seeds)
                se = np.sqrt(r["coverage"] * (1 - r["coverage"]) / r["decisive"]) if r["decisive"] else np.nan
                print(f"{name:16s} {paths!s:>5s} {str(r['window']):>9s} {r['truth']:7.4f} {r['decisive']:8d} "
                      f"{r['coverage']:7.2f} +-{se:4.2f} {r['wrong']:6.2f} {r['undetermined']:6.2f} {r['heavy']:6.2f} "
                      f"{r['heavy_coverage']:11.2f} {r['used'][0]:9.0f} {r['used'][1]:8.0f}", flush=True)
        if args.closed:
            for name in [n for n in names if n in LIBRARY + ("unst3",)]:
                for paths in args.paths:
                    r = closed_loop_contradictions(name, config_dir, paths, args.closed)
                    print(f"closed loop {name:16s} {paths!s:>5s}: {r}", flush=True)
        if args.near_truth:
            print(f"\nclosed loops against the same run at {args.truth_paths} paths ({args.near_truth} seeds)")
            print(f"{'plant':16s} {'paths':>5s} {'decisive':>8s} {'coverage':>8s} {'wrong':>5s} {'undet.':>6s} "
                  f"{'heavy':>5s} {'cover|heavy':>11s} {'by floor':>8s} {'no loop':>7s} {'used (median, 95%)':>18s}")
            for name in names:
                for P, c in closed_loop_near_truth(name, config_dir, args.paths, args.near_truth,
                                                   args.truth_paths).items():
                    d = c["decisive"]
                    share = lambda count, of=d: f"{count / of:.2f}" if of else "-"
                    used = np.percentile(c["used"], [50, 95]) if c["used"] else (np.nan, np.nan)
                    print(f"{name:16s} {P!s:>5s} {d:8d} {share(c['covered']):>8s} {c['wrong']:5d} "
                          f"{c['undetermined'] / args.near_truth:6.2f} {share(c['heavy']):>5s} "
                          f"{share(c['heavy_covered'], c['heavy']):>11s} {c['by_floor']:8d} {c['no_loop']:7d} "
                          f"{used[0]:9.0f} {used[1]:8.0f}", flush=True)
        print(f"{time.time() - start:.0f} s")


if __name__ == "__main__":
    main()
