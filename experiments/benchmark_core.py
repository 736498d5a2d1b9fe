"""Speed of the numerical core on the paper's example (Sec. V), against simple references.

    python experiments/benchmark_core.py [--paths 200] [--ensemble-size 300] [--repeats 3]

1. Closed-loop Monte Carlo with the EnKF observer (P paths x M members x 101 steps): wall time
   against the time numpy takes merely to draw the same number of standard normals (9 + 3 per member
   and step); target ratio <= 1.5. The paper reports 0.38-0.51 s per path with MATLAB.
2. Gain synthesis: "proposed" (LMI bisection; the first call compiles the problem), target <= 0.3 s;
   "policy_iteration", target <= 10 ms.
3. Threads available (cpu count, OMP_NUM_THREADS / OPENBLAS_NUM_THREADS if set).
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np

import rdsexp as rx
from rdsexp.numerics.enkf import EnKF
from rdsexp.numerics.simulation import simulate

MATLAB_SECONDS_PER_PATH = (0.38, 0.51)      # paper Sec. V-B: one path, k = 0..100


def timings(f, repeats: int) -> list[float]:
    """Wall times of `repeats` calls of f()."""
    out = []
    for _ in range(repeats):
        start = time.perf_counter()
        f()
        out.append(time.perf_counter() - start)
    return out


def show(label: str, value: float, unit: str, note: str = "") -> None:
    print((f"  {label:<34}{value:9.3f} {unit:<3}" + (f"  ({note})" if note else "")).rstrip())


def monte_carlo(paths: int, M: int, repeats: int) -> None:
    paper = rx.paper
    d, enkf = paper.disturbance(), EnKF(paper.model(), paper.Q, paper.R)
    steps, per_step = len(d), (paths, M, enkf.dim + paper.ny)          # e_w and e_v of every member
    run = lambda: simulate(paper.plant(), enkf, F=paper.F_proposed, d=d, q0=paper.q0, psi0=paper.psi0,
                           ensemble_size=M, paths=paths, seed=0, filter_sees_d=False)
    sim = min(timings(run, repeats))

    def chunks(out=None):
        rng = np.random.default_rng(0)
        for _ in range(steps):
            rng.standard_normal(per_step) if out is None else rng.standard_normal(out=out)
    fresh = min(timings(chunks, repeats))
    reused = min(timings(lambda: chunks(np.empty(per_step)), repeats))
    one_call = min(timings(lambda: np.random.default_rng(0).standard_normal((steps,) + per_step), repeats))

    lo, hi = MATLAB_SECONDS_PER_PATH
    print(f"closed-loop Monte Carlo: {paths} paths x M = {M} x {steps} steps, "
          f"{steps * np.prod(per_step) / 1e6:.1f} M normals drawn")
    show(f"simulate, wall (best of {repeats})", sim, "s")
    show("simulate, per path", sim / paths * 1e3, "ms",
         f"paper's MATLAB: {lo * 1e3:.0f}-{hi * 1e3:.0f} ms, {lo * paths / sim:.0f}-{hi * paths / sim:.0f}x this")
    show("numpy normals, per-step chunks", fresh, "s", "a new array per chunk")
    show("numpy normals, per-step chunks", reused, "s", "into one reused array, out=")
    show("numpy normals, one call", one_call, "s")
    show("simulate / chunks (new arrays)", sim / fresh, "", "target <= 1.5")
    show("simulate / chunks (reused array)", sim / reused, "")


def synthesis() -> None:
    model, dist = rx.paper.model(), rx.paper.modeled_distribution()
    design = lambda method: lambda: rx.synthesize(model, dist, method)
    first = timings(design("proposed"), 1)[0]
    proposed = statistics.median(timings(design("proposed"), 5))
    policy = statistics.median(timings(design("policy_iteration"), 20))
    print("gain synthesis (paper model and modeled distribution)")
    show("proposed, first call (compiles)", first, "s")
    show("proposed, median of 5", proposed, "s", f"target <= 0.3 s: {proposed / 0.3:.2f} of it")
    show("policy_iteration, median of 20", policy * 1e3, "ms", f"target <= 10 ms: {policy / 0.01:.2f} of it")


def threads() -> None:
    env = ", ".join(f"{k}={os.environ[k]}" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS") if k in os.environ)
    print(f"threads: os.cpu_count() = {os.cpu_count()}; {env or 'OMP_NUM_THREADS, OPENBLAS_NUM_THREADS not set'}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--paths", type=int, default=rx.paper.paths)
    parser.add_argument("--ensemble-size", type=int, default=rx.paper.ensemble_size)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    threads()
    monte_carlo(args.paths, args.ensemble_size, args.repeats)
    synthesis()


if __name__ == "__main__":
    main()
