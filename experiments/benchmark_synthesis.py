"""Speed of the certified optimal-rate designs against n (issue: certified optimal rates in milliseconds).

Over seeded random systems (n = 4, 8, 12, 16, 20; m = 1..3; p = 1..4, scaled so that most are
mean-square stabilizable), prints per n: LMI solves per `proposed` design, seconds per design for
`proposed` (seeded by policy iteration) and `policy_iteration`, their bracket widths (lam - lam_lower),
the seconds of one LMI solve at that size, and the ratio of `proposed`'s time to two solves (its limit).
The first design at each size compiles the LMI (cvxpy) once; its time is printed separately.

    OMP_NUM_THREADS=1 python experiments/benchmark_synthesis.py [--sizes 4 8 12] [--systems 3]
Goals: proposed within 1.5x of two solves; proposed < 6 s at n = 16; policy_iteration < 50 ms at n = 20.
"""
from __future__ import annotations

import argparse
import statistics
import time
import warnings

import cvxpy as cp
import numpy as np

import rdsexp as rx
from rdsexp.numerics.synthesis import lmi


def random_system(rng, n: int):
    m, p = int(rng.integers(1, 4)), int(rng.integers(1, 5))
    A = [0.9 * rng.normal(size=(n, n)) / np.sqrt(n)] + [0.3 * rng.normal(size=(n, n)) / np.sqrt(n) for _ in range(p)]
    B = [rng.normal(size=(n, m))] + [0.3 * rng.normal(size=(n, m)) for _ in range(p)]
    L = rng.normal(size=(p, p)) * 0.5
    return rx.AffineRandomSystem(A=A, B=B), rx.MomentModel(mean=rng.normal(size=p) * 0.3, cov=L @ L.T)


def one_solve(system, dist) -> float:
    """Seconds of one LMI solve of Theorem 2 at this size (compiled problem, at the optimal lambda)."""
    Abar, Bbar = system.moment_factors(dist)
    problem, lam2, pA, pB, *_ = lmi._lmi_problem(system.n, system.m, Abar.shape[0])
    for r in range(Abar.shape[0]):
        pA[r].value, pB[r].value = Abar[r], Bbar[r]
    lam2.value = 0.9 ** 2
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        problem.solve(solver=cp.CLARABEL)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[4, 8, 12, 16, 20])
    parser.add_argument("--systems", type=int, default=3, help="random systems per size")
    args = parser.parse_args()
    print(f"{'n':>3} {'sys':>3} {'status':>20} {'solves':>6} {'proposed s':>10} {'first s':>8} {'PI ms':>7} "
          f"{'PI width':>9} {'LMI width':>9} {'solve s':>8} {'/2 solves':>9}")
    for n in args.sizes:
        rng = np.random.default_rng(1000 + n)
        for k in range(args.systems):
            system, dist = random_system(rng, n)
            first = time.perf_counter()
            rx.synthesize(system, dist, "proposed")          # compiles at a new size (m, nbar)
            first = time.perf_counter() - first
            res = rx.synthesize(system, dist, "proposed")
            pi_times = [rx.synthesize(system, dist, "policy_iteration").seconds for _ in range(5)]
            pi = rx.synthesize(system, dist, "policy_iteration")
            solve = statistics.median(one_solve(system, dist) for _ in range(2))
            print(f"{n:>3} {k:>3} {res.status:>20} {res.info['solves']:>6} {res.seconds:>10.3f} {first:>8.2f} "
                  f"{1e3 * statistics.median(pi_times):>7.1f} {pi.lam - pi.lam_lower:>9.1e} "
                  f"{res.lam - res.lam_lower:>9.1e} {solve:>8.3f} {res.seconds / (2 * solve):>9.2f}", flush=True)


if __name__ == "__main__":
    main()
