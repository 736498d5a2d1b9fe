"""Speed of the EnKF variants side by side on the paper's closed loop (Sec. V-B).

    python experiments/benchmark_filters.py [--paths 200] [--ensemble-size 300] [--repeats 3]

For each variant (stochastic: the paper's perturbed-output EnKF; etkf: the ensemble transform
filter), the closed-loop Monte Carlo wall time (P paths x M members x 101 steps) and the time numpy
takes merely to draw the standard normals that variant uses (stochastic: n+p + ny per member and
step; etkf: n+p, no output perturbations), in per-step chunks into one reused array. Targets:
etkf / stochastic <= 1.5; each variant / its normals as in benchmark_core.py (<= 1.5).
Runs alternate between the variants so that load from other processes hits both alike. Both the
wall time and the process CPU time are reported (best of the repeats): on a loaded machine the CPU
time of this single-threaded process (run it with OMP_NUM_THREADS=1) is the steadier measure.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
from benchmark_core import show, threads

import rdsexp as rx
from rdsexp.numerics.enkf import VARIANTS, EnKF
from rdsexp.numerics.simulation import simulate


def timed(f) -> tuple[float, float]:
    """(wall, CPU) seconds of one call of f()."""
    wall, cpu = time.perf_counter(), time.process_time()
    f()
    return time.perf_counter() - wall, time.process_time() - cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--paths", type=int, default=rx.paper.paths)
    parser.add_argument("--ensemble-size", type=int, default=rx.paper.ensemble_size)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    threads()
    paper, P, M = rx.paper, args.paths, args.ensemble_size
    d = paper.disturbance()
    steps = len(d)
    filters = {v: EnKF(paper.model(), paper.Q, paper.R, variant=v) for v in VARIANTS}
    run = {v: (lambda f=f: simulate(paper.plant(), f, F=paper.F_proposed, d=d, q0=paper.q0, psi0=paper.psi0,
                                    ensemble_size=M, paths=P, seed=0, filter_sees_d=False))
           for v, f in filters.items()}

    def normals(width: int) -> None:
        out, rng = np.empty((P, M, width)), np.random.default_rng(0)
        for _ in range(steps):
            rng.standard_normal(out=out)

    sim = {v: [] for v in VARIANTS}
    draw = {v: [] for v in VARIANTS}
    for _ in range(args.repeats):                       # interleaved: the same background load for both
        for v, f in filters.items():
            sim[v].append(timed(run[v]))
            draw[v].append(timed(lambda f=f: normals(f.dim + f.output_noise_dim)))
    print(f"closed-loop Monte Carlo, paper's example: {P} paths x M = {M} x {steps} steps (best of {args.repeats})")
    for i, clock in enumerate(("wall", "CPU")):
        best = {v: min(t[i] for t in sim[v]) for v in VARIANTS}
        normal = {v: min(t[i] for t in draw[v]) for v in VARIANTS}
        print(f"{clock} time")
        for v, f in filters.items():
            width = f.dim + f.output_noise_dim
            show(f"{v}: simulate", best[v], "s")
            show(f"{v}: numpy normals ({width} per member)", normal[v], "s",
                 f"{steps * P * M * width / 1e6:.1f} M normals")
            show(f"{v}: simulate / its normals", best[v] / normal[v], "", "target <= 1.5")
        show("etkf / stochastic (simulate)", best["etkf"] / best["stochastic"], "", "target <= 1.5")
        show("etkf / stochastic (normals)", normal["etkf"] / normal["stochastic"], "")


if __name__ == "__main__":
    main()
