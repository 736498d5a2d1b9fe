"""Where a modeled mean's bias comes from: the simulator, the data, or the simulated estimator itself.

For a plant at its true law theta* = (the plant file's means, stds), with the identification as a
default run makes it (`identification.paths` runs, open loop or its feedback):

1. the simulator: `--reps` replicate paths at theta* against as many runs of the plant (seeds 0, 1, ... of
   `identification.paths` paths each); per summary statistic, both means and the two-sample Kolmogorov-Smirnov
   p-value (the replicates draw theta*'s moments in the laws `identification.replicate_laws` says: random shapes
   by default, normal with `--override identification.replicate_laws=normal`; a law beyond them may give other
   summaries); and the same
   runs under other laws of the same means and stds (`same_moments`: the normal with the law's correlations,
   uniform and symmetric two-point components), each statistic's shift from the replicates' in their sds:
   which of correlation and shape moves the summary;
2. the estimator on noiseless data: `posterior_rounds` (the rounds a run makes) given s* = the mean summary at
   theta* (no data noise), with the prior box the run would take about s* and with that box centred on theta*'s
   means; a consistent estimator reads theta* there, up to its Monte Carlo error;
3. plain rejection: the 1%, 3% and 10% of `--reps` replicates from the run's last box nearest s* (each summary
   scaled by its spread), their mean theta (no likelihood); and the synthetic likelihood's regression
   (`indirect.emulator`) fitted on those replicates: how far s* lies from its fit at theta* (a regression that
   cannot follow the summary's expectation moves the likelihood's maximum off theta*), and the law whose fitted
   summary is nearest s* (the maximum given s*, without the prior box's volume);
4. one bias correction by simulation, a candidate (not in rdsexp): the estimate theta^ given s* and given three
   noisy summaries at theta* (identification.paths paths each), the estimate theta^^ given the noiseless summary
   at theta^, and 2 theta^ - theta^^.

    python experiments/model_bias.py [--plant multiplicative] [--reps 1600] [--override KEY=VALUE ...]

--plant takes a library plant or a random plant of model_calibration.py (rp0, rp1, ...).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.optimize import minimize
from scipy.stats import ks_2samp

from rdsexp.experiment.montecarlo import Simulation
from rdsexp.experiment.pipeline import identification as ident
from rdsexp.numerics import indirect
from rdsexp.numerics.distributions import Discrete, Independent, Uniform
from rdsexp.numerics.systems import AffineRandomSystem, MomentModel

sys.path.insert(0, str(Path(__file__).resolve().parent))
from model_calibration import FAST, experiment, write_random_plants  # noqa: E402


def finite(s: np.ndarray) -> np.ndarray:
    return s[np.all(np.isfinite(s), axis=1)]


def same_moments(law, ends: np.ndarray, low: np.ndarray, high: np.ndarray) -> dict:
    """Laws of xi with the law's means and stds (a two-point component its own law): the normal with the law's
    correlations (where it has some and no two-point component), and independent uniform and symmetric two-point
    components. Which of correlation and shape moves the summary."""
    mean, std = law.mean, np.sqrt(np.diag(law.cov))

    def components(shape: str) -> Independent:
        out = []
        for m, s, two, lo, hi in zip(mean, std, ends, low, high):
            if two:
                q = (m - lo) / (hi - lo)
                out.append(Discrete([[lo], [hi]], [1 - q, q]))
            elif shape == "uniform":
                out.append(Uniform([m - np.sqrt(3) * s], [m + np.sqrt(3) * s]))
            else:
                out.append(Discrete([[m - s], [m + s]], [0.5, 0.5]))
        return Independent(out)
    laws = {"uniform": components("uniform"), "two-point": components("two_point")}
    correlated = np.abs(law.cov - np.diag(np.diag(law.cov))).max() > 0
    if correlated and not ends.any():
        laws = {"correlated normal": MomentModel(mean, law.cov)} | laws
    return laws


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--plant", default="multiplicative")
    parser.add_argument("--reps", type=int, default=1600)
    parser.add_argument("--override", nargs="*", default=[], metavar="KEY=VALUE")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    config_dir = None
    if args.plant.startswith("rp"):         # a random plant of model_calibration.py's
        config_dir = Path(tempfile.mkdtemp())
        write_random_plants(config_dir, int(args.plant[2:]) + 1, int(args.plant[2:]))
    exp = experiment(args.plant, config_dir, ["seed=0", *FAST, *args.override])
    ends, low, high = ident.two_point_ends(exp)
    law = exp.plant.check_distribution(None)
    std = np.sqrt(np.diag(law.cov))
    corr = law.cov / np.outer(std, std) + np.diag(std == 0)          # (a constant component: uncorrelated)
    truth = np.concatenate([law.mean, std[~ends], indirect.partial_correlations(corr)])
    F_id, _ = ident.identification_feedback(exp)
    paths = exp.identification.paths
    replay = ident.Replay(exp.identification.input, F_id, exp.q0, paths=paths)
    names = ident.summary_names(exp.model)
    at = lambda theta, count, stream, runs=replay: finite(ident.replicate_summaries(
        exp, exp.filter.enkf, runs, np.repeat(theta[None], count, 0), ends, low, high, stream))

    one = ident.Replay(exp.identification.input, F_id, exp.q0, paths=1)
    replicates = at(truth, args.reps, 1001, one)
    laws = {"plant": None} | same_moments(law, ends, low, high)        # None: the plant file's own law
    def identification_runs(seed: int) -> dict[str, np.ndarray]:   # a default run's identification, each law
        e = experiment(args.plant, config_dir, [f"seed={seed}", *FAST, *args.override])
        out = {}
        for label, dist in laws.items():
            plant = e.plant if dist is None else AffineRandomSystem(e.plant.A, e.plant.B, e.plant.C, e.plant.D,
                                                                     xi_dist=dist)
            sim = Simulation.of(e, e.filter.enkf, F_id, np.random.SeedSequence(e.seed, spawn_key=(0,)), plant=plant,
                                d=e.identification.input, paths=paths, filter_sees_d=True)
            out[label] = ident.summary_statistics(e, sim.run(keep_xi_cov=True))
        return out
    runs = [identification_runs(seed) for seed in range(args.reps // paths)]
    under = {label: finite(np.concatenate([r[label] for r in runs])) for label in laws}
    plant = under["plant"]
    print(f"1. the simulator at the true law ({len(replicates)} replicate paths, {len(plant)} plant paths)")
    for j, name in enumerate(names):
        print(f"   {name:36s} replicates {replicates[:, j].mean():8.3f}  plant {plant[:, j].mean():8.3f}  "
              f"KS p {ks_2samp(replicates[:, j], plant[:, j]).pvalue:.3f}")
    print("   the same means and stds under other laws: (mean summary - replicates') / replicates' sd")
    print(f"   {'':36s} " + "".join(f"{label:>20s}" for label in under))
    for j, name in enumerate(names):
        shift = [(u[:, j].mean() - replicates[:, j].mean()) / replicates[:, j].std() for u in under.values()]
        print(f"   {name:36s} " + "".join(f"{v:20.2f}" for v in shift))

    s_star = at(truth, 400, 1002).mean(axis=0)
    p = ends.size
    print(f"2. the estimator given the noiseless summary s* (true means {np.round(truth[:p], 3).tolist()})")
    box = indirect.prior_box(s_star[:2 * p], ends, low, high, exp.identification.prior_width)
    centred = indirect.prior_box(np.concatenate([truth[:p], s_star[p:2 * p]]), ends, low, high,
                                 exp.identification.prior_width)
    fit = lambda prior: ident.fitted(prior, ends, exp.identification.replicates)
    last = None
    for label, prior in (("the run's prior box", box), ("the box centred on the true means", centred)):
        (draws, w), usable, _ = ident.posterior_rounds(exp, exp.filter.enkf, replay, s_star, paths, prior,
                                                       (ends, low, high), fit(prior))
        mean = w @ draws / w.sum()
        sd = np.sqrt(w @ (draws - mean) ** 2 / w.sum())
        print(f"   {label:36s} means {np.round(mean[:p], 3).tolist()} (sd {np.round(sd[:p], 3).tolist()}), "
              f"stds {np.round(mean[p:], 3).tolist()}; identified {usable}")
        last = indirect.posterior_box(draws, w, *prior) if last is None else last     # the run's last box

    theta = indirect.uniform_draws(*last, args.reps, 1003)
    s = ident.replicate_summaries(exp, exp.filter.enkf, replay, theta, ends, low, high, 1003)
    ok = np.all(np.isfinite(s), axis=1)
    theta, s = theta[ok], s[ok]
    distance = np.sqrt((((s - s_star) / s.std(axis=0)) ** 2).sum(axis=1))
    print(f"3. plain rejection: of {len(s)} replicates from the last box, the nearest to s*")
    for share in (0.01, 0.03, 0.1):
        near = distance <= np.quantile(distance, share)
        print(f"   {share:4.0%} ({near.sum():4d}): means {np.round(theta[near, :p].mean(axis=0), 3).tolist()}, "
              f"stds {np.round(theta[near, p:].mean(axis=0), 3).tolist()}")
    mu, _, W = indirect.emulator(theta, s, *last)
    sd = np.sqrt(np.diag(np.linalg.pinv(W @ W.T)))
    misfit = (s_star - mu(truth[None])[0]) / sd
    worst = np.argsort(-np.abs(misfit))[:3]
    fit = minimize(lambda t: (((s_star - mu(t[None])[0]) @ W) ** 2).sum(), truth, method="L-BFGS-B",
                   bounds=list(zip(*last)))
    print("   the emulator fitted on them (indirect.emulator) at theta*: s* - fit in residual sds, largest "
          + ", ".join(f"{names[j]} {misfit[j]:+.2f}" for j in worst)
          + f"; the fit's nearest law to s*: means {np.round(fit.x[:p], 3).tolist()}, stds "
          f"{np.round(fit.x[p:], 3).tolist()}")

    def estimate(summary: np.ndarray) -> np.ndarray:            # the posterior mean from the run's prior box
        prior = indirect.prior_box(summary[:2 * p], ends, low, high, exp.identification.prior_width)
        (draws, w), _, _ = ident.posterior_rounds(exp, exp.filter.enkf, replay, summary, paths, prior,
                                                  (ends, low, high), fit(prior))
        return w @ draws / w.sum()
    noisy = at(truth, 3, 1004)
    print("4. one bias correction by simulation at the estimate: theta^ -> 2 theta^ - theta^^ (means | stds)")
    for label, summary in (("noiseless s*", s_star), *((f"noisy summary {i}", noisy[i]) for i in range(3))):
        first = estimate(summary)
        corrected = 2 * first - estimate(at(first, 400, 1005).mean(axis=0))
        print(f"   {label:18s} {np.round(first[:p], 3).tolist()} -> {np.round(corrected[:p], 3).tolist()} | "
              f"{np.round(first[p:], 3).tolist()} -> {np.round(corrected[p:], 3).tolist()}")
    print(f"\n{time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
