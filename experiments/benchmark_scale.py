"""Scale of a whole run: wall time, paths per second, peak memory and bytes on disk against the paths.

    python experiments/benchmark_scale.py [--paths 200 1000 10000] [--huge] [--workers 1] [--tracking summary]

Each size runs `python -m rdsexp closed_loop.paths=N` (the paper's experiment, closed and open loop,
tracking summary: parquet tables and recording) in a fresh process in a temporary directory and
reports: wall time of the whole command, the Monte Carlo stages' time (closed_loop + open_loop from
run.json's timings), paths per second, the peak resident memory of the run (RUSAGE_CHILDREN of a
wrapper process, so each size is measured alone), the bytes the run directory holds, and the ratio of
the Monte Carlo time to the time numpy needs merely to draw the same standard normals (target <= 1.3).
--huge adds 100,000 paths.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from rdsexp import runs

WRAPPER = """
import resource, subprocess, sys
proc = subprocess.run(sys.argv[1:])
print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, file=sys.stderr)
sys.exit(proc.returncode)
"""


def draw_seconds(normals: int, block: int = 16 * 300 * 12) -> float:
    """Seconds numpy takes to draw `normals` standard normals into a reused buffer."""
    rng, out = np.random.default_rng(0), np.empty(block)
    start = time.perf_counter()
    for _ in range(normals // block):
        rng.standard_normal(out=out)
    rng.standard_normal(normals % block)
    return time.perf_counter() - start


def run(paths: int, workers: int, tracking: str) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, "-c", WRAPPER, sys.executable, "-m", "rdsexp",
                               f"closed_loop.paths={paths}", f"closed_loop.workers={workers}", f"tracking={tracking}"],
                              cwd=tmp, capture_output=True, text=True)
        wall = time.perf_counter() - start
        if proc.returncode != 0:
            raise SystemExit(f"paths={paths}: exit {proc.returncode}\n{proc.stderr[-2000:]}")
        rss_kib = int(proc.stderr.strip().splitlines()[-1])
        (run_dir,) = (Path(tmp) / "outputs" / "runs").iterdir()
        timings = runs.record(run_dir).timings
        on_disk = sum(f.stat().st_size for f in run_dir.rglob("*") if f.is_file())
        mc = timings["closed_loop"] + timings.get("open_loop", 0.0)
        return {"wall": wall, "mc": mc, "rss_mib": rss_kib / 1024, "disk_mib": on_disk / 2 ** 20,
                "recording_mib": (run_dir / "recording.rrd").stat().st_size / 2 ** 20
                if (run_dir / "recording.rrd").exists() else 0.0}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--paths", type=int, nargs="+", default=[200, 1000, 10000])
    parser.add_argument("--huge", action="store_true", help="also 100,000 paths")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--tracking", default="summary")
    args = parser.parse_args()
    sizes = args.paths + ([100_000] if args.huge else [])
    M, steps, per_member = 300, 101, 12            # the paper: 300 members, k = 0..100, 9 + 3 normals each
    print(f"{'paths':>7} {'wall s':>8} {'MC s':>8} {'paths/s':>8} {'peak MiB':>9} {'disk MiB':>9} "
          f"{'rrd MiB':>8} {'MC/draw':>8}")
    for paths in sizes:
        r = run(paths, args.workers, args.tracking)
        draw = draw_seconds(2 * paths * steps * M * per_member)        # closed and open loop
        print(f"{paths:7d} {r['wall']:8.1f} {r['mc']:8.1f} {2 * paths / r['mc']:8.1f} {r['rss_mib']:9.0f} "
              f"{r['disk_mib']:9.1f} {r['recording_mib']:8.1f} {r['mc'] / draw:8.2f}", flush=True)


if __name__ == "__main__":
    main()
