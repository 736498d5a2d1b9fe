"""Tracking overhead of rdsexp runs and per-job overhead of sweeps.

    python experiments/benchmark_tracking.py [--repeats 3] [--jobs 4]

1. The default run (the paper's experiment) in-process: compute time (identification .. metrics)
   against tracking time (provenance + parquet tables + Rerun summary recording); target <= 15%.
2. A sweep of --jobs tiny jobs with the basic and the joblib launcher (subprocesses): wall time
   per job minus the compute each job reports, i.e. what Hydra, process start and tracking cost.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from hydra import compose, initialize_config_module

from rdsexp.experiment import pipeline, runner
from rdsexp.experiment.config import build
from rdsexp.experiment.store import RunStore

COMPUTE = ("identification", "modeling", "synthesis", "closed_loop", "open_loop", "metrics")
TRACKING = ("provenance", "tables", "recording")
TINY = ["closed_loop.paths=2", "enkf.ensemble_size=10", "closed_loop.horizon=20", "closed_loop.rate_window=[5,10]",
        "identification.horizon=20", "identification.K0=5", "identification.K1=10"]


def tracking_overhead(repeats: int) -> None:
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        cfg = compose("config")
    best = None
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as tmp:
            info = runner.execute(cfg, Path(tmp))
        t = info["timings"]
        compute, track = sum(t[k] for k in COMPUTE if k in t), sum(t[k] for k in TRACKING)
        if best is None or compute + track < best[0] + best[1]:
            best = (compute, track, t)
    compute, track, t = best
    stages = ", ".join(f"{k} {t[k]:.3f}" for k in COMPUTE if k in t)
    print(f"default run, compute             {compute:8.3f} s  ({stages})")
    print(f"default run, tracking            {track:8.3f} s  ({', '.join(f'{k} {t[k]:.3f}' for k in TRACKING)})")
    print(f"tracking / compute               {track / compute:8.1%}   (target <= 15%)")
    off = build(cfg)
    start = time.perf_counter()
    pipeline.run_experiment(off)
    print(f"same run with tracking off       {time.perf_counter() - start:8.3f} s  (wall, in-process)")


def sweep_overhead(jobs: int) -> None:
    for name, launcher in (("basic", []), ("joblib n_jobs=2", ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"])):
        with tempfile.TemporaryDirectory() as tmp:
            start = time.perf_counter()
            subprocess.run([sys.executable, "-m", "rdsexp", "+sweep=seeds", f"seed=range(0,{jobs})", *TINY, *launcher],
                           cwd=tmp, check=True, capture_output=True)
            wall = time.perf_counter() - start
            (sweep,) = (Path(tmp) / "outputs" / "sweeps").iterdir()
            seconds = [run.record.timings for run in RunStore(sweep).runs()]
            compute = sum(sum(t[k] for k in COMPUTE if k in t) for t in seconds)
        print(f"sweep, {name:16s} {jobs} jobs: wall {wall:6.2f} s, compute {compute:5.2f} s, "
              f"overhead per job {(wall - compute) / jobs:5.2f} s (includes interpreter start and imports)")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--jobs", type=int, default=4)
    args = parser.parse_args()
    tracking_overhead(args.repeats)
    sweep_overhead(args.jobs)
