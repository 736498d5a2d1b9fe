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
    from rdsexp.experiment.montecarlo import MEMORY_BUDGET
    from rdsexp.numerics.enkf import EnKF
    from rdsexp.numerics.modeling import mls_input
    from rdsexp.numerics.simulation import bytes_per_path, simulate
    paper = rx.paper
    enkf, d = EnKF(paper.model(), paper.Q, paper.R), mls_input(steps - 1, 1, 7, 10.0, levels="unipolar")
    settings = dict(ensemble_size=members, seed=0, q0=paper.q0, psi0=np.zeros(enkf.dim))
    size = max(1, MEMORY_BUDGET // (3 * bytes_per_path(paper.plant(), enkf, ensemble_size=members, horizon=steps - 1)))
    chunks = [(first, min(size, paths - first)) for first in range(0, paths, size)]   # as the pipeline chunks
    out = {"mode": mode, "chunk_paths": size}
    if mode == "write":                           # the data file, from the simulated identification
        parts = [simulate(paper.plant(), enkf, d=d, paths=c, first_path=f, **settings) for f, c in chunks]
        out["rows"] = write(csv, np.concatenate([p.u for p in parts], 1), np.concatenate([p.y for p in parts], 1))
        np.save(csv + ".xi.npy", np.concatenate([p.psi_filt_mean[..., -3:] for p in parts], 1))
        return out
    start = time.perf_counter()
    if mode == "simulated":
        parts = [simulate(paper.plant(), enkf, d=d, paths=c, first_path=f, **settings) for f, c in chunks]
    else:
        data = load(csv, m=1, ny=3, min_steps=steps)
        out["read_seconds"] = time.perf_counter() - start
        parts = [simulate(None, enkf, d=np.zeros_like(d), paths=c, first_path=f,
                          recorded=data.recorded.select(slice(f, f + c)), **settings) for f, c in chunks]
    out["seconds"] = time.perf_counter() - start
    xi = np.concatenate([p.psi_filt_mean[..., -3:] for p in parts], 1)
    out["max_xi_difference"] = float(np.nanmax(np.abs(xi - np.load(csv + ".xi.npy"))))
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
