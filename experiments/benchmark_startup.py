"""Start-up of the command line: `rdsexp --help`, one bash-completion request and `rdsexp-runs list` on a
store of 20 runs, each a fresh process as a user starts it (wall clock, median of --repeat).

The store is one tiny run copied 20 times (files hard-linked, run.json with its own id and config
hash, see benchmark_store.py). Budget: each under 1 s.

    python experiments/benchmark_startup.py [--repeat 7] [--runs 20]
"""
from __future__ import annotations

import argparse
import hashlib
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmark_store import fabricate, template_run

SCRIPTS = Path(sys.executable).parent
BUDGET = 1.0


def seconds(command: list[str], repeat: int, env=None, cwd=None) -> float:
    """Median wall-clock seconds of a fresh process running `command`."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        subprocess.run(command, check=True, capture_output=True, env=env, cwd=cwd)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--runs", type=int, default=20)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        template = template_run(tmp)
        store = tmp / "store"
        for i in range(args.runs):
            fabricate(template, store / "runs" / f"r{i:05d}", f"r{i:05d}", hashlib.sha256(f"{i}".encode()).hexdigest())
        line = "rdsexp gain="
        completion = dict(os.environ, COMP_LINE=line, COMP_POINT=str(len(line)))
        rows = [("rdsexp --help", seconds([str(SCRIPTS / "rdsexp"), "--help"], args.repeat, cwd=tmp)),
                ("bash completion (gain=)", seconds([str(SCRIPTS / "rdsexp"), "-sc", "query=bash"], args.repeat,
                                                    env=completion, cwd=tmp)),
                (f"rdsexp-runs list ({args.runs} runs)", seconds([str(SCRIPTS / "rdsexp-runs"), "list", str(store)],
                                                                 args.repeat, cwd=tmp)),
                ("python -c 'import rdsexp'", seconds([sys.executable, "-c", "import rdsexp"], args.repeat))]
    print(f"{'command':32s} {'median s':>9s} {'/ budget':>9s}   (median of {args.repeat}, budget {BUDGET:g} s)")
    for name, s in rows:
        print(f"{name:32s} {s:9.3f} {s / BUDGET:9.2f}")


if __name__ == "__main__":
    main()
