"""Speed of the online (learning-type) controller against the offline closed loop, side by side.

    python experiments/benchmark_online.py [--paths 200] [--ensemble-size 300] [--horizon 100]
                                           [--period 10] [--lag 1] [--repeats 1]

The paper's closed loop (P paths x M members, k = 0..horizon, u_k = F x_{k|k-1} with the fixed
proposed gain) against the online controller on the same plant samples and EnKF noise (initial gain
zero, warm-up 20, memory all, re-design every `period` steps by batched policy iteration; its EnKF keeps
`lag` past draws of xi, controller.lag's default on this plant). Target online / offline <= 3. Also
prints the time spent inside the controller's updates.
"""
from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

import rdsexp as rx
from rdsexp.numerics.enkf import EnKF
from rdsexp.numerics.online import OnlineController, OnlineSettings
from rdsexp.numerics.simulation import simulate


class Timed(OnlineController):
    """The online controller, accumulating the seconds spent in its updates."""

    seconds = 0.0

    def update(self, k, psi_filt_mean, alive, xi_filt_cov=None):
        start = time.perf_counter()
        try:
            return super().update(k, psi_filt_mean, alive, xi_filt_cov)
        finally:
            self.seconds += time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--paths", type=int, default=200)
    parser.add_argument("--ensemble-size", type=int, default=300)
    parser.add_argument("--horizon", type=int, default=100)
    parser.add_argument("--period", type=int, default=10)
    parser.add_argument("--lag", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=1)
    args = parser.parse_args()
    paper = rx.paper
    model, K, P = paper.model(), args.horizon, args.paths
    d, enkf = paper.disturbance(K), EnKF(model, paper.Q, paper.R)
    settings = OnlineSettings(warmup=20, period=args.period, memory="all")
    common = dict(d=d, q0=paper.q0, psi0=paper.psi0, ensemble_size=args.ensemble_size, paths=P, seed=0,
                  filter_sees_d=False)
    offline, online, inside, adopted = [], [], [], 0
    for _ in range(args.repeats):                     # alternate, so both see the same machine load
        start = time.perf_counter()
        simulate(paper.plant(), enkf, F=paper.F_proposed, **common)
        offline.append(time.perf_counter() - start)
        controller = Timed(model, settings, np.zeros((model.m, model.n)), paths=P, horizon=K)
        start = time.perf_counter()
        simulate(paper.plant(), dataclasses.replace(enkf, lag=args.lag), F=np.zeros((model.m, model.n)),
                 controller=controller, **common)
        online.append(time.perf_counter() - start)
        inside.append(controller.seconds)
        adopted = int(controller.decisions().adopted.sum())
    off, on = min(offline), min(online)
    updates = settings.updates(K).size
    print(f"online vs offline closed loop: {P} paths x M = {args.ensemble_size} x {K + 1} steps, "
          f"{updates} re-designs per path (policy iteration, batched over paths), lag {args.lag}, "
          f"best of {args.repeats}")
    print(f"  offline closed loop (fixed F)     {off:8.2f} s")
    print(f"  online closed loop                {on:8.2f} s")
    print(f"    of which controller updates     {min(inside):8.2f} s  ({updates * P} designs, {adopted} adopted)")
    print(f"  online / offline                  {on / off:8.2f}    (target <= 3)")


if __name__ == "__main__":
    main()
