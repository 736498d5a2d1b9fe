"""Speed of the mean-square LQ and robust box designs on the paper's model (Sec. V) against their targets.

1. ms_lqr (generalized Riccati equation by Newton), paper model and modeled distribution:
   median of `repeats` calls, target < 10 ms.
2. robust_box with p = 3 (8 vertex LMIs), box mean +- 1 std: first call (compiles the problem for
   this size) and median of warm calls, target < 1 s.
3. Exact costs per gain: the five numbers the gains table holds per design (LQ cost from q0 and
   averaged over x0 on the plant, H2 norm on the plant, LQ cost and H2 norm on the model: `exact_costs`
   on each distribution, one cost matrix each), median over the gains of every method, target < 5 ms
   per gain; also a single lq_cost / h2_norm call.

    python experiments/benchmark_designs.py [--repeats 20] [--cpu]
Ratios are printed as "x of target" (below 1: within target).
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

import rdsexp as rx
from rdsexp.numerics.analysis import exact_costs, h2_norm, lq_cost
from rdsexp.numerics.synthesis import METHODS

CLOCK = time.perf_counter              # --cpu: time.process_time (this process only, for a busy machine)


def timings(f, repeats: int) -> list[float]:
    """Times (CLOCK) of `repeats` calls of f()."""
    out = []
    for _ in range(repeats):
        start = CLOCK()
        f()
        out.append(CLOCK() - start)
    return out


def show(label: str, seconds: float, target: float | None = None, note: str = "") -> None:
    text = f"  {label:<44}{seconds * 1e3:10.3f} ms"
    if target is not None:
        text += f"  target < {target * 1e3:g} ms: {seconds / target:.3f} x of target"
    print(text + (f"  ({note})" if note else ""))


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--cpu", action="store_true", help="CPU time of this process instead of wall time "
                        "(a machine shared with other jobs inflates wall times)")
    args = parser.parse_args(argv)
    global CLOCK
    CLOCK = time.process_time if args.cpu else time.perf_counter
    print(f"clock: {'CPU time of this process' if args.cpu else 'wall time'}; "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    env = ", ".join(f"{k}={os.environ[k]}" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS") if k in os.environ)
    print(f"threads: os.cpu_count() = {os.cpu_count()}; {env or 'OMP_NUM_THREADS not set'}")
    model, plant, dist = rx.paper.model(), rx.paper.plant(), rx.paper.modeled_distribution()
    out = {}

    print("ms_lqr, paper model (n = 6, m = 1, p = 3), modeled distribution")
    res = rx.synthesize(model, dist, "ms_lqr")
    out["ms_lqr"] = statistics.median(timings(lambda: rx.synthesize(model, dist, "ms_lqr"), args.repeats))
    show(f"median of {args.repeats} (status {res.status}, rate {res.lam:.4f})", out["ms_lqr"], 0.010)

    print("robust_box, p = 3: 8 vertex LMIs, box mean +- 1 std")
    first = timings(lambda: rx.synthesize(model, dist, "robust_box", width=1.0), 1)[0]
    warm_repeats = max(3, args.repeats // 4)
    res = rx.synthesize(model, dist, "robust_box", width=1.0)
    out["robust_box"] = statistics.median(timings(lambda: rx.synthesize(model, dist, "robust_box", width=1.0),
                                                  warm_repeats))
    show("first call (compiles for this size)", first, 1.0)
    show(f"median of {warm_repeats} (status {res.status}, {res.info['solves']} solves)", out["robust_box"], 1.0,
         f"lam_box {res.info['lam_box']:.4f}, exact rate {res.lam:.4f}")

    print("exact costs per gain (the gains table's five numbers), gains of every method on the modeled moments")
    gains = {m: rx.synthesize(model, dist, m, **({"poles": rx.paper.poles} if m == "pole_placement" else {})).F
             for m in METHODS}
    gains = {m: F for m, F in gains.items() if F is not None}

    def five(F):                      # as the pipeline's gains table: one cost matrix per distribution
        return exact_costs(plant, None, F, rx.paper.q0), exact_costs(model, dist, F)
    per_gain = {m: statistics.median(timings(lambda F=F: five(F), args.repeats)) for m, F in gains.items()}
    out["costs_per_gain"] = statistics.median(per_gain.values())
    show(f"median over {len(per_gain)} gains, five numbers", out["costs_per_gain"], 0.005)
    show("slowest gain, five numbers", max(per_gain.values()), 0.005, max(per_gain, key=per_gain.get))
    F = gains["proposed"]
    show("one lq_cost (model, averaged over x0)",
         statistics.median(timings(lambda: lq_cost(model, dist, F), args.repeats)))
    show("one h2_norm (model)", statistics.median(timings(lambda: h2_norm(model, dist, F), args.repeats)))
    return out


if __name__ == "__main__":
    main()
