"""Identification from recorded data against the same identification simulated (README "Your own data").

    python experiments/benchmark_data.py [--paths 1000] [--steps 200] [--members 300]

The paper's model and EnKF (M = members), P = paths identification paths of `steps` steps (k = 0..steps-1,
the M-sequence input, open loop). `simulated`: `simulate` with the paper's plant (what a simulated
identification runs). `recorded`: the same paths' (u, y) written as the data format (CSV), read and checked
(`data.load`) and filtered by `simulate(recorded=...)`. Each mode runs in a fresh process; reported: seconds
(reading the file separately), peak resident memory, and the ratio recorded / simulated (target <= 2), and
that both give the same filtered xi (the replay is exact).
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def run(mode: str, paths: int, steps: int, members: int, csv: str) -> dict:
    import rdsexp as rx
    from rdsexp.experiment.data import load, write
    from rdsexp.numerics.enkf import EnKF
    from rdsexp.numerics.modeling import mls_input
    from rdsexp.numerics.simulation import simulate
    paper = rx.paper
    enkf, d = EnKF(paper.model(), paper.Q, paper.R), mls_input(steps - 1, 1, 7, 10.0, levels="unipolar")
    settings = dict(ensemble_size=members, paths=paths, seed=0, q0=paper.q0, psi0=np.zeros(enkf.dim))
    out = {"mode": mode}
    if mode == "write":                           # the data file, from the simulated identification
        tr = simulate(paper.plant(), enkf, d=d, **settings)
        out["rows"] = write(csv, tr.u, tr.y)
        np.save(csv + ".xi.npy", tr.psi_filt_mean[..., -3:])
        return out
    start = time.perf_counter()
    if mode == "simulated":
        tr = simulate(paper.plant(), enkf, d=d, **settings)
    else:
        data = load(csv, m=1, ny=3, min_steps=steps)
        out["read_seconds"] = time.perf_counter() - start
        tr = simulate(None, enkf, d=np.zeros_like(d), recorded=data.recorded, **settings)
    out["seconds"] = time.perf_counter() - start
    out["max_xi_difference"] = float(np.nanmax(np.abs(tr.psi_filt_mean[..., -3:] - np.load(csv + ".xi.npy"))))
    out["peak_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--paths", type=int, default=1000)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--members", type=int, default=300)
    parser.add_argument("--mode", help=argparse.SUPPRESS)
    parser.add_argument("--csv", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.mode:
        print(json.dumps(run(args.mode, args.paths, args.steps, args.members, args.csv)))
        return
    with tempfile.TemporaryDirectory() as tmp:
        csv = str(Path(tmp) / "data.csv")
        results = {}
        for mode in ("write", "simulated", "recorded"):
            proc = subprocess.run([sys.executable, __file__, "--mode", mode, "--csv", csv, "--paths", str(args.paths),
                                   "--steps", str(args.steps), "--members", str(args.members)],
                                  capture_output=True, text=True, check=True)
            results[mode] = json.loads(proc.stdout.strip().splitlines()[-1])
        size = Path(csv).stat().st_size / 2 ** 20
    sim, rec = results["simulated"], results["recorded"]
    print(f"{args.paths} paths x {args.steps} steps, M = {args.members}; data file {results['write']['rows']} rows, "
          f"{size:.1f} MiB")
    print(f"simulated identification: {sim['seconds']:.2f} s, peak {sim['peak_mib']:.0f} MiB")
    print(f"recorded identification:  {rec['seconds']:.2f} s (reading and checking the file "
          f"{rec['read_seconds']:.2f} s), peak {rec['peak_mib']:.0f} MiB")
    print(f"ratio recorded / simulated: {rec['seconds'] / sim['seconds']:.2f} (target <= 2); filtered xi max "
          f"difference from the simulated run: {rec['max_xi_difference']:.3g}")


if __name__ == "__main__":
    main()
