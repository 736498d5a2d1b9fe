"""Time of one LMI solve of Theorem 2 under Clarabel settings.

One solve of (lmi-syn) at lambda just above policy iteration's optimum, on the seeded random systems
of benchmark_synthesis.py, for each Clarabel setting below; the settings are interleaved round-robin
over the repeats so that machine drift hits them alike. Prints per n and setting the median CPU
seconds of the solve (cvxpy + Clarabel), Clarabel's own solve time, its iterations, the margin t
(all must agree in sign to be usable for the certified bisection) and the ratio to today's setting.

    OMP_NUM_THREADS=1 python experiments/benchmark_lmi_solve.py [--sizes 8 12 16] [--repeats 5]
"""
from __future__ import annotations

import argparse
import statistics
import time
import warnings

import cvxpy as cp
import numpy as np
from benchmark_synthesis import random_system

import rdsexp as rx
from rdsexp.numerics.synthesis import lmi

SETTINGS = {"today (defaults)": {}, "no equilibration": {"equilibrate_enable": False},
            "no presolve": {"presolve_enable": False}, "faer KKT solver": {"direct_solve_method": "faer"},
            "smaller static regularization": {"static_regularization_constant": 1e-9}}


def prepared(n: int, seed: int = 0):
    """The compiled LMI with a seeded random system's moments, at lambda = its optimum * (1 + 3e-8)."""
    system, dist = random_system(np.random.default_rng(seed + n), n)
    Abar, Bbar = system.moment_factors(dist)
    problem, lam2, pA, pB, _, _, t = lmi._lmi_problem(n, system.m, Abar.shape[0])
    for r in range(Abar.shape[0]):
        pA[r].value, pB[r].value = Abar[r], Bbar[r]
    lam2.value = (rx.synthesize(system, dist, "policy_iteration").lam * (1 + 3e-8)) ** 2
    return problem, t, system.m, Abar.shape[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[8, 12, 16])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    for n in args.sizes:
        problem, t, m, nbar = prepared(n)
        times = {name: [] for name in SETTINGS}
        stats = {}
        for _ in range(args.repeats):
            for name, settings in SETTINGS.items():
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    start = time.process_time()
                    problem.solve(solver=cp.CLARABEL, warm_start=False, **settings)
                    times[name].append(time.process_time() - start)
                stats[name] = (problem.solver_stats.solve_time, problem.solver_stats.num_iters, t.value,
                               problem.status)
        base = statistics.median(times["today (defaults)"])
        print(f"n = {n} (m = {m}, nbar = {nbar}, PSD block {(nbar + 1) * n})")
        for name in SETTINGS:
            cpu = statistics.median(times[name])
            solve, iters, margin, status = stats[name]
            print(f"  {name:32s} {cpu * 1e3:8.1f} ms  clarabel {solve * 1e3:8.1f} ms  {iters:3d} iters  "
                  f"t {margin:+.1e} {status:8s} x{cpu / base:.2f}", flush=True)


if __name__ == "__main__":
    main()
