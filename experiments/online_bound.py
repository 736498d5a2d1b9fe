"""How close to the offline gain can a path's own model of xi get? A bound for online control.

The online controller (`controller=online`) models each path's law of xi from that path's estimates and
designs on it. This script asks what such per-path designs can reach at best, with no filter in between:
for each plant of a `random_plants.py` draw and each of P paths, it draws T i.i.d. samples of xi from the
plant's own law, adds Gaussian noise of variance r to each (r = 0: xi itself; r > 0: estimates that carry
xi with that error, unbiased), models the path's moments as the controller does (the samples' mean; their
covariance minus r I, projected onto the positive semidefinite cone, so unbiased before the projection),
designs by policy iteration (`online.policy_iteration_batch`, the controller's default method) and takes
the gain's exact mean-square rate on the true plant. A plant is "no worse" where the median over paths is
at most the offline gain's rate + 0.005, the offline rate read from the draw's table (`random_plants.py
--override controller=online`, column offline_rate_plant), the comparison docs/online.md makes for the
online loop itself.

    python experiments/online_bound.py --csv STORE/random_plants.csv --seed S [--steps 30 60]
        [--noise 0 0.05 0.1] [--paths 100] [--own-noise [--window 21 50]]

--own-noise adds, per plant, the noise its own online loop's estimates carry: from each run's trajectories
(column run_dir of the table), the error variance r = S P / (S - P) that the loop's EnKF implies for a
likelihood of xi with predicted variance S and filtered variance P (per component; infinite where P >= S),
its median over paths, components and the steps of --window (by default k = 21..50: after the controller's
warm-up, while the closed loop's d_k holds the state up).

The same --seed redraws the same plants (`random_plants.draw_plants`); each plant's exact open-loop rate
is checked against the table's, so a table of another seed is refused. Prints, per (T, r), the plants
no worse, and per family the plants worse.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from random_plants import draw_plants, system_of  # noqa: E402

from rdsexp.numerics.online import moment_factors, policy_iteration_batch, rates  # noqa: E402

TOLERANCE = 0.005


def path_models(xi: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray]:
    """Per path the mean (P, p) and the noise-corrected covariance (P, p, p) of samples xi (P, T, p) that
    carry noise of variance r I: the sample covariance minus r I, projected onto the PSD cone."""
    mean = xi.mean(axis=1)
    dev = xi - mean[:, None]
    cov = np.einsum("ptj,ptk->pjk", dev, dev) / (xi.shape[1] - 1) - r * np.eye(xi.shape[2])
    w, V = np.linalg.eigh(cov)
    return mean, np.einsum("pij,pj,pkj->pik", V, np.maximum(w, 0.0), V)


def median_rate(system, dist, rng: np.random.Generator, paths: int, steps: int, r: float) -> float:
    """The median over paths of the exact rate on the true plant of the gain designed on each path's model
    (infinite where r is: estimates that carry nothing of xi give no model)."""
    if not np.isfinite(r):
        return np.inf
    samples = dist.sample(rng, (paths, steps)) + np.sqrt(r) * rng.normal(size=(paths, steps, system.p))
    mean, cov = path_models(samples, r)
    A_true, B_true = moment_factors(system, dist.mean[None], dist.cov[None])          # every family has both
    with np.errstate(all="ignore"):
        F = policy_iteration_batch(*moment_factors(system, mean, cov), np.zeros((paths, system.m, system.n)))
        exact = rates(np.repeat(A_true, paths, axis=0), np.repeat(B_true, paths, axis=0), np.nan_to_num(F))
    return float(np.median(np.where(np.all(np.isfinite(F), axis=(1, 2)), exact, np.inf)))


def own_noise(run_dir: Path, p: int, window: tuple[int, int]) -> float:
    """The median error variance r = S P / (S - P) of a run's online estimates of xi over the steps of window."""
    names = [f"xi_{kind}_std[{j}]" for kind in ("pred", "filt") for j in range(p)]
    table = pd.read_parquet(Path(run_dir) / "trajectories.parquet", columns=["experiment", "k", *names])
    table = table[(table["experiment"] == "online") & table["k"].between(*window)]
    S, P = (table[names[i * p:(i + 1) * p]].to_numpy() ** 2 for i in (0, 1))
    with np.errstate(all="ignore"):
        r = np.where(S > P, S * P / (S - P), np.inf)
    r[np.isnan(S) | np.isnan(P)] = np.nan                           # steps after a path failed
    return float(np.nanmedian(r))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--csv", type=Path, required=True, help="random_plants.py's table with controller=online")
    parser.add_argument("--seed", type=int, required=True, help="the seed of that draw")
    parser.add_argument("--steps", type=int, nargs="+", default=[30, 60], help="samples T per path")
    parser.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.05, 0.1], help="noise variances r")
    parser.add_argument("--paths", type=int, default=100)
    parser.add_argument("--own-noise", action="store_true", help="also each plant's own loop's noise (docstring)")
    parser.add_argument("--window", type=int, nargs=2, default=[21, 50], metavar=("FIRST", "LAST"))
    args = parser.parse_args(argv)
    if min(args.steps) < 2 or min(args.noise) < 0 or args.paths < 1:
        parser.error("--steps must be >= 2, --noise >= 0 and --paths >= 1")
    if not args.csv.is_file():
        parser.error(f"--csv {args.csv}: no such file")
    try:
        table = pd.read_csv(args.csv)
    except (ValueError, UnicodeDecodeError) as err:              # pandas' ParserError is a ValueError
        parser.error(f"--csv {args.csv}: not a table ({str(err).splitlines()[0]})")
    missing = {"plant", "open_loop_rate", "offline_rate_plant", "run_dir"} - set(table.columns)
    if missing:
        parser.error(f"{args.csv}: no {', '.join(sorted(missing))} column (a table of random_plants.py "
                     "--override controller=online)")
    table = table[table["offline_rate_plant"].notna()].set_index("plant")
    drawn = {p.name: p for p in draw_plants(max(int(name[2:]) for name in table.index) + 1, args.seed)}
    rows = []
    for name, row in table.iterrows():
        plant = drawn[name]
        if not np.isclose(plant.open_loop_rate, row["open_loop_rate"], rtol=1e-6):
            parser.error(f"{name}: open-loop rate {plant.open_loop_rate:.6f} here, {row['open_loop_rate']:.6f} "
                         f"in {args.csv}: not the draw of --seed {args.seed}")
        system, dist = system_of(plant.content)
        noises = [(r, f"r {r:g}") for r in args.noise]
        if args.own_noise:
            if not (Path(row["run_dir"]) / "trajectories.parquet").is_file():
                parser.error(f"{name}: no trajectories in {row['run_dir']} (--own-noise reads the plant's run)")
            noises.append((own_noise(row["run_dir"], system.p, tuple(args.window)), "its own r"))
        for T in args.steps:
            for r, label in noises:
                rng = np.random.default_rng([args.seed, plant.index, T, round(min(r, 1e6) * 1e6)])
                rate = median_rate(system, dist, rng, args.paths, T, r)
                rows.append(dict(plant=name, family=plant.family, steps=T, noise=label, r=r, rate=rate,
                                 worse=rate > row["offline_rate_plant"] + TOLERANCE))
    out = pd.DataFrame(rows)
    for (T, label), group in out.groupby(["steps", "noise"], sort=False):
        worse = group[group["worse"]]
        by_family = worse["family"].value_counts().to_dict()
        median = f" (median {group['r'].median():.4g})" if label == "its own r" else ""
        print(f"T {T:3d}, {label}{median}: no worse {len(group) - len(worse)}/{len(group)}"
              + (f"; worse: {', '.join(worse['plant'])} (by family {by_family})" if len(worse) else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
