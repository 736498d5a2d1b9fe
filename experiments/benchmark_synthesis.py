"""Speed of the certified optimal-rate designs against n.

Over seeded random systems (n = 4, 8, 12, 16, 20; m = 1..3; p = 1..4, scaled so that most are
mean-square stabilizable), prints per n: LMI solves per `proposed` design, seconds per design for
`proposed` (seeded by policy iteration) and `policy_iteration`, their bracket widths (lam - lam_lower),
the seconds of one LMI solve at that size, and the ratio of `proposed`'s time to two solves (its limit),
in CPU seconds of this process (wall seconds beside them; on a shared machine they include waiting).
The first design at each size compiles the LMI (cvxpy) once; its wall time is printed separately (1st s).

    OMP_NUM_THREADS=1 python experiments/benchmark_synthesis.py [--sizes 4 8 12] [--systems 3]
Goals: proposed within 1.5x of two solves; proposed < 6 s at n = 16; policy_iteration < 50 ms at n = 20.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

import rdsexp as rx
from rdsexp.numerics.synthesis import lmi


def random_system(rng, n: int):
    m, p = int(rng.integers(1, 4)), int(rng.integers(1, 5))
    A = [0.9 * rng.normal(size=(n, n)) / np.sqrt(n)] + [0.3 * rng.normal(size=(n, n)) / np.sqrt(n) for _ in range(p)]
    B = [rng.normal(size=(n, m))] + [0.3 * rng.normal(size=(n, m)) for _ in range(p)]
    L = rng.normal(size=(p, p)) * 0.5
    return rx.AffineRandomSystem(A=A, B=B), rx.MomentModel(mean=rng.normal(size=p) * 0.3, cov=L @ L.T)


def timed(f, *args, **kwargs):
    """(result, wall seconds, CPU seconds of this process): on a shared machine CPU time is the fair figure."""
    wall, cpu = time.perf_counter(), time.process_time()
    out = f(*args, **kwargs)
    return out, time.perf_counter() - wall, time.process_time() - cpu


def one_solve(system, dist, lam: float) -> tuple[float, float]:
    """(wall, CPU) seconds of one LMI solve of Theorem 2 at this size and lam (compiled problem)."""
    solve = lmi.lmi_solver(system, dist)
    _, wall, cpu = timed(solve, lam)
    return wall, cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[4, 8, 12, 16, 20])
    parser.add_argument("--systems", type=int, default=3, help="random systems per size")
    args = parser.parse_args()
    print(f"{'n':>3} {'sys':>3} {'m':>2} {'p':>2} {'status':>14} {'solves':>6} {'prop s':>7} {'cpu':>6} {'1st s':>6} "
          f"{'PI ms':>7} {'cpu':>6} {'PI width':>8} {'LMI wid':>8} {'solve s':>7} {'cpu':>6} {'/2 solves':>9}")
    for n in args.sizes:
        rng = np.random.default_rng(1000 + n)
        for k in range(args.systems):
            system, dist = random_system(rng, n)
            _, first, _ = timed(rx.synthesize, system, dist, "proposed")      # compiles at a new size
            res, wall, cpu = timed(rx.synthesize, system, dist, "proposed")
            pis = [timed(rx.synthesize, system, dist, "policy_iteration") for _ in range(5)]
            pi = pis[-1][0]
            pi_wall, pi_cpu = (statistics.median(t[i] for t in pis) for i in (1, 2))
            solve_wall, solve_cpu = (statistics.median(v) for v in zip(*(one_solve(system, dist, res.lam)
                                                                         for _ in range(2))))
            print(f"{n:>3} {k:>3} {system.m:>2} {system.p:>2} {res.status:>14} {res.info['solves']:>6} {wall:>7.3f} "
                  f"{cpu:>6.3f} {first:>6.2f} {1e3 * pi_wall:>7.1f} {1e3 * pi_cpu:>6.1f} {pi.lam - pi.lam_lower:>8.1e} "
                  f"{res.lam - res.lam_lower:>8.1e} {solve_wall:>7.3f} {solve_cpu:>6.3f} "
                  f"{cpu / (2 * solve_cpu):>9.2f}", flush=True)


if __name__ == "__main__":
    main()
