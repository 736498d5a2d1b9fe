"""Per-job bookkeeping of a sweep against the number of runs already stored.

A sweep job's bookkeeping is the reuse lookup (rdsexp.experiment.store.find_reusable: one index
entry and the named run's files), indexing its own run (store.index_add) and rebuilding its sweep's
summary (store.write_sweep_summary). This script stores one tiny run (tracking summary), fabricates
stores of 10, 100 and 1,000 runs by copying it (files hard-linked, run.json rewritten with a
distinct config hash), puts a 5-job sweep in each and times that bookkeeping, beside the lookup
rdsexp used before the index (reading every run.json under the store).

    python experiments/benchmark_store.py [--sizes 10 100 1000] [--repeat 20]
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rdsexp.experiment import store

TINY = ["closed_loop.paths=4", "enkf.ensemble_size=20", "closed_loop.horizon=30", "closed_loop.rate_window=[10,20]",
        "closed_loop.disturbance.until=10", "identification.horizon=30", "identification.K0=5",
        "identification.K1=20", "model.reported=null", "tracking.level=summary", "tracking.recording=false"]
SWEEP_JOBS = 5


def fabricate(template: Path, target: Path, run_id: str, config_hash: str, sweep: dict | None = None) -> dict:
    """A copy of the template run (files hard-linked) whose run.json has its own id and config hash."""
    shutil.copytree(template, target, copy_function=os.link)
    info = json.loads((template / "run.json").read_text())
    info.update(id=run_id, config_hash=config_hash, sweep=sweep)
    (target / "run.json").unlink()                       # a fresh file, not the template's inode
    (target / "run.json").write_text(json.dumps(info))
    return info


def template_run(tmp: Path) -> Path:
    """One tiny stored run (tracking summary, no recording) under tmp/seed; its directory."""
    subprocess.run([sys.executable, "-m", "rdsexp", *TINY, f"store={tmp / 'seed'}"], cwd=tmp, check=True,
                   capture_output=True)
    (template,) = (tmp / "seed" / "runs").iterdir()
    return template


def legacy_lookup(root: Path, config_hash: str, version: str) -> Path | None:
    """The lookup before the index: read every run.json under the store."""
    for path in sorted(root.rglob("run.json")):
        info = json.loads(path.read_text())
        if info.get("status") == "complete" and info.get("config_hash") == config_hash \
                and info["code"]["version"] == version and not info.get("reused_from"):
            return path.parent
    return None


def median_ms(repeat: int, fn, *args) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn(*args)
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10, 100, 1000])
    parser.add_argument("--repeat", type=int, default=20)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        template = template_run(tmp)
        version = json.loads((template / "run.json").read_text())["code"]["version"]
        size = sum(p.stat().st_size for p in template.rglob("*") if p.is_file())
        print(f"template run: {template.name}, {size / 1e3:.0f} kB; per-job bookkeeping, median of {args.repeat}")
        print(f"{'stored':>7s} {'lookup hit':>11s} {'lookup miss':>12s} {'index_add':>10s} {'summary':>9s} "
              f"{'per job':>9s} {'full scan (before)':>19s} {'index build (once)':>19s}")
        rows = []
        for n in args.sizes:
            root = tmp / f"store{n}"
            hashes = [hashlib.sha256(f"run {i}".encode()).hexdigest() for i in range(n)]
            for i, h in enumerate(hashes):
                fabricate(template, root / "runs" / f"r{i:05d}", f"r{i:05d}", h)
            sweep = root / "sweeps" / "sweep"
            for j in range(SWEEP_JOBS):
                fabricate(template, sweep / str(j), f"sweep/{j}", hashlib.sha256(f"job {j}".encode()).hexdigest(),
                          sweep={"dir": str(sweep), "job": j, "name": "bench"})
            start = time.perf_counter()
            store.rebuild_index(root)
            build = 1e3 * (time.perf_counter() - start)
            target = hashes[n // 2]
            assert store.find_reusable(root, target, version) == (root / "runs" / f"r{n // 2:05d}").resolve()
            job = sweep / "0"
            job_info = json.loads((job / "run.json").read_text())
            hit = median_ms(args.repeat, store.find_reusable, root, target, version)
            miss = median_ms(args.repeat, store.find_reusable, root, "0" * 64, version)
            add = median_ms(args.repeat, store.index_add, root, job, job_info)
            summary = median_ms(args.repeat, store.write_sweep_summary, sweep)
            scan = median_ms(max(3, args.repeat // 5), legacy_lookup, root, target, version)
            per_job = hit + add + summary
            rows.append((n, per_job, scan))
            print(f"{n:7d} {hit:9.2f}ms {miss:10.2f}ms {add:8.2f}ms {summary:7.2f}ms {per_job:7.2f}ms "
                  f"{scan:17.2f}ms {build:17.2f}ms")
        (n0, j0, s0), (n1, j1, s1) = rows[0], rows[-1]
        print(f"per-job bookkeeping, {n1} vs {n0} stored runs: x{j1 / j0:.2f} "
              f"(the full scan it replaces: x{s1 / s0:.1f}); at {n1} runs the index lookup + summary is "
              f"{s1 / j1:.0f}x cheaper than the scan")


if __name__ == "__main__":
    main()
