"""What each module-level cache of rdsexp saves, on the call pattern it serves (docs/design.md, "Module-level caches").

Every cache is timed on its pattern twice in this process: as shipped, and with that one cache disabled
(a functools cache replaced by the function it wraps, a dict or set by one that never holds anything).
Patterns:

- store: a store of 50 runs (one tiny run copied, 5 sweeps of 10 jobs: 3 of the shipped sweep `paper`, 2
  launched with `-m` and no name), read as `rdsexp-runs list --changed` reads it, and as the report reads it
  (`experiments/paper.py` draws its figures in one process: 6 scripts each load the sweep's runs, check
  them, read two tables of each and write a lineage record);
- stage memory: a sweep of 4 jobs in one process that share their identification and designs (they differ in
  closed_loop.paths only), without a store (tracking=off) and with the store's stage cache.

    python experiments/benchmark_caches.py [--repeat 3]

Prints one line per cache: its hits in one pattern, the pattern's time with and without it (alternately, the
minimum of --repeat each), and whether
the results are the same (they must be: a cache that changed a result would be a bug). Times are CPU
seconds of this process (all threads), which other processes on the machine disturb less than wall time.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections import OrderedDict
from pathlib import Path

import numpy as np

from rdsexp import report
from rdsexp.experiment import runs as runs_cli
from rdsexp.experiment.store import files, run, stages

TINY = ["closed_loop.paths=4", "enkf.ensemble_size=20", "closed_loop.horizon=30", "closed_loop.rate_window=[10,20]",
        "closed_loop.disturbance.until=10", "identification.horizon=30", "identification.K0=5",
        "identification.K1=20", "tracking.level=summary", "tracking.recording=false"]


CACHES = [(report, "swept_keys"), (report, "drawing_code"), (files, "_FILE_HASHES"), (run, "_CONFIGS"),
          (stages, "_MEMORY")]


class Forgetful(OrderedDict):
    """A dict cache that holds nothing: every lookup misses (a value just stored can still be read back once)."""

    def __contains__(self, key):
        return False

    def get(self, key, default=None):
        return default


class Empty(set):
    """A set cache that holds nothing."""

    def __contains__(self, key):
        return False


class Counted(OrderedDict):
    """A dict cache that counts its hits (a lookup of a key it holds)."""
    hits = 0

    def __contains__(self, key):
        found = super().__contains__(key)
        type(self).hits += found
        return found

    def get(self, key, default=None):
        found = super().get(key, default)
        type(self).hits += found is not default
        return found


class CountedSet(set):
    hits = 0

    def __contains__(self, key):
        found = super().__contains__(key)
        type(self).hits += found
        return found


@contextlib.contextmanager
def swapped(module, name: str, replacement):
    original = getattr(module, name)
    setattr(module, name, replacement)
    try:
        yield
    finally:
        setattr(module, name, original)


def disabled(module, name: str):
    """Module attribute `name` without its caching: a functools cache's wrapped function, an empty dict or
    set that never holds anything."""
    original = getattr(module, name)
    replacement = original.__wrapped__ if hasattr(original, "__wrapped__") else \
        Empty() if isinstance(original, set) else Forgetful()
    return swapped(module, name, replacement)


def counted(module, name: str):
    """Module attribute `name` as shipped (a functools cache counts its own hits), a dict or set counting them."""
    original = getattr(module, name)
    if hasattr(original, "cache_info"):
        return contextlib.nullcontext()
    Counted.hits = CountedSet.hits = 0
    return swapped(module, name, CountedSet() if isinstance(original, set) else Counted())


def hits(module, name: str) -> int:
    holder = getattr(module, name)
    return holder.cache_info().hits if hasattr(holder, "cache_info") else type(holder).hits


def clear_all() -> None:
    """Every module-level cache empty: the state of a fresh process."""
    for module, name in CACHES:
        holder = getattr(module, name)
        if hasattr(holder, "cache_clear"):
            holder.cache_clear()
        elif hasattr(holder, "clear"):
            holder.clear()


def timed(pattern):
    """(CPU seconds of this process, all threads: less disturbed by other processes than wall time; result)."""
    clear_all()
    start = time.process_time()
    result = pattern()
    return time.process_time() - start, result


def compare(label: str, key: str, module, name: str, pattern, repeat: int) -> None:
    """The pattern with the cache and without it, alternately `repeat` times each (the minimum of each), the
    cache's hits in one pattern, and whether the results are equal."""
    with_cache, without, same, found = [], [], True, 0
    for _ in range(repeat):
        with counted(module, name):
            seconds, a = timed(pattern)
            found = hits(module, name)
        with_cache.append(seconds)
        with disabled(module, name):
            seconds, b = timed(pattern)
        without.append(seconds)
        same &= a == b
    w, wo = min(with_cache), min(without)
    print(f"{label:38s} {key:22s} hits {found:5d}  with {1e3 * w:8.0f} ms  without {1e3 * wo:8.0f} ms  "
          f"saves {1e3 * (wo - w):7.0f} ms ({100 * (wo - w) / wo:4.0f}%)  {'same results' if same else 'DIFFER'}",
          flush=True)


# ---------------------------------------------------------------------------------- store and report
def make_store(tmp: Path) -> Path:
    """50 runs in 5 sweeps under tmp/store, copies of one tiny run (files hard-linked)."""
    subprocess.run([sys.executable, "-m", "rdsexp", *TINY, f"store={tmp / 'seed'}"], cwd=tmp, check=True,
                   capture_output=True)
    (template,) = (tmp / "seed" / "runs").iterdir()
    root = tmp / "store"
    base = json.loads((template / "run.json").read_text())
    for s in range(5):
        sweep = root / "sweeps" / f"2024-01-0{s + 1}_00-00-00-000000_bench{s}"
        named = s < 3
        sweep.mkdir(parents=True)
        (sweep / "multirun.yaml").write_text(
            "hydra:\n  overrides:\n    task:\n    - closed_loop.paths=4\n    - seed=range(10)\n")
        for j in range(10):
            target = sweep / str(j)
            shutil.copytree(template, target, copy_function=os.link)
            info = dict(base, id=f"{sweep.name}/{j}", config_hash=f"{s:02d}{j:02d}" + base["config_hash"][4:],
                        created=f"2024-01-0{s + 1}T00:00:{j:02d}",
                        sweep={"dir": str(sweep), "job": j, "name": "paper" if named else None},
                        overrides=["+sweep=paper", f"seed={j}"] if named else [f"seed={j}"])
            (target / "run.json").unlink()
            (target / "run.json").write_text(json.dumps(info))
    return root


def list_changed(root: Path):
    """`rdsexp-runs list --changed DIR`: its printed table."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        runs_cli.main(["list", "--changed", str(root)])
    return out.getvalue()


def report_reads(root: Path):
    """What the report's scripts read in one process: 6 scripts each load the sweep's runs, read two tables
    of every run and record a lineage (the tables' hashes, the code version)."""
    lineages = []
    for script in range(6):
        runs = report.sweep_runs(root, "paper")
        for r in runs:
            r.table("metrics")
            r.table("gains")
            r.get("closed_loop.paths")
        lineages.append(report.lineage(runs, f"script{script}"))
    return json.dumps(lineages, sort_keys=True, default=str)


def hash_rate() -> float:
    """MB/s of `files.file_hash` on an 8 MB file (the size of a run's tables and recording at the defaults)."""
    with tempfile.NamedTemporaryFile() as fh:
        fh.write(np.random.default_rng(0).bytes(8 << 20))
        fh.flush()
        start = time.process_time()
        for _ in range(5):
            files.file_hash(Path(fh.name))
        return 5 * 8 * 1.048576 / (time.process_time() - start)


# ---------------------------------------------------------------------------------- stage memory
def stage_sweep(tmp: Path | None):
    """4 jobs in one process that differ in closed_loop.paths only (`pipeline.run_experiment` with the
    cache the runner gives a job: this process's memory without a store, the store's with one); their
    gains and identification tables."""
    from hydra import compose, initialize_config_module

    from rdsexp.experiment import pipeline
    from rdsexp.experiment.config import build
    small = [o for o in TINY if not o.startswith(("closed_loop.paths", "tracking"))]
    out = []
    root = None if tmp is None else Path(tempfile.mkdtemp(dir=tmp))
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        for j, paths in enumerate((4, 6, 8, 10)):
            exp = build(compose("config", overrides=[*small, f"closed_loop.paths={paths}", "tracking=summary"]))
            cache = stages.StageCache.in_process() if root is None else stages.StageCache(root, "bench", f"job{j}")
            outcome = pipeline.run_experiment(exp, cache=cache)
            out.append(tuple(outcome.tables[name].to_json() for name in ("gains", "identification")))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        root = make_store(tmp)
        listing = lambda: list_changed(root)
        reading = lambda: report_reads(root)
        compare("rdsexp-runs list --changed (50 runs)", "run._CONFIGS", run, "_CONFIGS", listing, args.repeat)
        for key, module, name in [("files._FILE_HASHES", files, "_FILE_HASHES"), ("run._CONFIGS", run, "_CONFIGS"),
                                  ("report.swept_keys", report, "swept_keys"),
                                  ("report.drawing_code", report, "drawing_code")]:
            compare("report: 6 scripts, sweep paper", key, module, name, reading, args.repeat)
        print(f"hashing a stored file (what files._FILE_HASHES saves on each later read): "
              f"{hash_rate():.0f} MB/s", flush=True)
        compare("sweep of 4 jobs, tracking=off", "stages._MEMORY", stages, "_MEMORY", lambda: stage_sweep(None),
                args.repeat)
        compare("sweep of 4 jobs, store's stage cache", "stages._MEMORY", stages, "_MEMORY",
                lambda: stage_sweep(tmp), args.repeat)


if __name__ == "__main__":
    main()
