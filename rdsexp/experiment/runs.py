"""Run catalog: `rdsexp-runs list [DIR] | show RUN | verify RUN | check [DIR]`.

A run is a directory with a run.json (see `rdsexp.experiment.records`); RUN is its path or its id
(a directory name under outputs/, or SWEEP/JOB for a sweep job). Damaged records are skipped with
one warning line each, or reported as damaged (see `rdsexp.experiment.store`).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from . import records, store

DEFAULT_ROOT = Path("outputs")
__all__ = ["DEFAULT_ROOT", "catalog", "check", "cli", "compare_tables", "find_complete", "find_runs", "main", "resolve",
           "verify", "write_sweep_summary"]


def find_runs(root: Path) -> list[tuple[Path, dict]]:
    """(run directory, its run.json) for every readable run under root, oldest first; each file
    read once, each damaged one named in a warning line and skipped."""
    return store.read_runs(root)[0]


def find_complete(root: Path, config_hash: str, version: str) -> Path | None:
    """An intact, complete, not itself reused run in the store `root` with this config hash and
    code version (through the store's reuse index)."""
    return store.find_reusable(root, config_hash, version)


def resolve(run: str, root: Path = DEFAULT_ROOT) -> Path:
    """A run directory from a path or an id; SystemExit with one line if there is none."""
    path = Path(run)
    if (path / "run.json").exists():
        return path
    matches = [p for p, info in find_runs(root) if info.get("id") == run or p.name == run]
    if len(matches) != 1:
        sys.exit(f"rdsexp.runs: {'no' if not matches else 'more than one'} run {run!r} under {root}")
    return matches[0]


def catalog(root: Path) -> pd.DataFrame:
    """One row per run: id, sweep, overrides, seed, status, key metrics, time."""
    rows = []
    for run_dir, info in find_runs(root):
        s = info.get("summary") or {}
        rate = s.get("closed_loop_rate")
        rate = rate if isinstance(rate, list) and rate else [rate if isinstance(rate, float) else np.nan]
        rows.append({"id": info.get("id"), "sweep": (info.get("sweep") or {}).get("name"),
                     "overrides": " ".join(o for o in info.get("overrides", []) if not o.startswith("+sweep=")),
                     "seed": (info.get("seed") or {}).get("root"), "status": info.get("status"),
                     "method": s.get("gain_method"), "synthesis": s.get("synthesis_status"),
                     "lam": s.get("lam"), "rate": rate[0], "loop": s.get("closed_loop_status"),
                     "seconds": info.get("seconds"),
                     "created": info.get("created"), "config_hash": (info.get("config_hash") or "")[:12],
                     "code": ((info.get("code") or {}).get("version") or "")[:12], "dir": str(run_dir)})
    return pd.DataFrame(rows)


def write_sweep_summary(sweep_dir: Path) -> Path:
    """Rebuild <sweep>/summary.parquet (and .csv) from the jobs' run.json files on disk.

    Jobs finishing at once (joblib, Ray, Slurm workers) rebuild one after the other under a lock on
    <sweep>/.summary.lock, so the last rebuild has seen every job that finished before it: without
    it a slow rebuild could overwrite a newer one with fewer jobs."""
    import fcntl
    path = Path(sweep_dir) / "summary.parquet"
    try:
        lock = open(Path(sweep_dir) / ".summary.lock", "a")
    except OSError as err:
        raise records.WriteError(path, err) from err
    with lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        table = catalog(sweep_dir)
        if len(table):
            table.insert(0, "job", [int(Path(d).name) if Path(d).name.isdigit() else -1 for d in table["dir"]])
            table = table.sort_values("job", ignore_index=True)
        records.write_table(path, table)
        records.atomic_write_bytes(path.with_suffix(".csv"), table.to_csv(index=False).encode())
    return path


def compare_tables(stored: pd.DataFrame, fresh: pd.DataFrame) -> list[str]:
    """Differences between two versions of a table, column by column; [] when identical."""
    problems = []
    if list(stored.columns) != list(fresh.columns) or len(stored) != len(fresh):
        return [f"shape/columns differ: {stored.shape} {list(stored.columns)[:5]}... vs "
                f"{fresh.shape} {list(fresh.columns)[:5]}..."]
    for name in stored.columns:
        a, b = stored[name].to_numpy(), fresh[name].to_numpy()
        if a.dtype.kind in "biuf" and b.dtype.kind in "biuf":
            a, b = a.astype(float), b.astype(float)
            same = (a == b) | (np.isnan(a) & np.isnan(b))
            if not same.all():
                first = int(np.argmax(~same))
                diff = np.nanmax(np.abs(a - b)) if np.isfinite(a - b).any() else np.inf
                problems.append(f"{name}: max |difference| {diff:.3g}, first at row {first}")
        elif not np.array_equal(a.astype(str), b.astype(str)):
            problems.append(f"{name}: values differ, first at row {int(np.argmax(a.astype(str) != b.astype(str)))}")
    return problems


def verify(run_dir: Path) -> bool:
    """Re-execute a stored run from its recorded config and seed; compare every table. A damaged
    file (missing, unreadable, modified after the run) is reported as such and fails verify."""
    from .config import build
    from .pipeline import run_experiment
    info = store.read_run(run_dir)
    damaged = store.run_damage(run_dir, info)
    for problem in damaged:
        print(f"damaged: {run_dir / problem}")
    if not (run_dir / ".hydra" / "config.yaml").is_file():
        print("verify: cannot re-run without .hydra/config.yaml (damaged)")
        return False
    cfg = OmegaConf.load(run_dir / ".hydra" / "config.yaml")
    code = records.code_version()["version"]
    if code != (info.get("code") or {}).get("version"):
        print(f"note: the run was made with code {(info.get('code') or {}).get('version')}, this is {code}")
    outcome = run_experiment(build(cfg))
    ok = not damaged
    for name in (info.get("tables") or {}):
        fresh = outcome.tables.get(name)
        try:
            stored = store.read_table(run_dir, info, name)
        except store.DamagedRecord as err:
            print(f"{name:15s} DAMAGED: {err.path.name}: {err.reason}")
            ok = False
            continue
        problems = compare_tables(stored, fresh) if fresh is not None else ["not produced by the re-run"]
        print(f"{name:15s} {'identical' if not problems else 'DIFFERS'}")
        for p in problems:
            print(f"    {p}")
        ok &= not problems
    print("verify:", "identical" if ok else "differences found")
    return ok


def check(root: Path, move: bool = False) -> int:
    """`rdsexp-runs check [DIR] [--quarantine]`: list every damaged or inconsistent record under a
    store; with `move`, quarantine them and rebuild the summaries concerned. Exit code: 1 when
    something was found and left in place, else 0."""
    findings = store.check(root)
    for finding in findings:
        print(finding.line())
    if not findings:
        print(f"check: {root}: no damaged or inconsistent record")
        return 0
    if not move:
        print(f"check: {root}: {len(findings)} damaged or inconsistent; `--quarantine` moves the damaged records "
              f"to {Path(root) / store.QUARANTINE} and rebuilds the summaries")
        return 1
    moves, rebuilt = store.quarantine(root, findings)
    for source, target in moves:
        print(f"moved {source} -> {target}")
    for path in rebuilt:
        print(f"rebuilt {path}")
    print(f"check: {root}: {len(moves)} moved to quarantine, {len(rebuilt)} summaries rebuilt, index rebuilt")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="rdsexp-runs", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p_list = sub.add_parser("list", help="table of runs under DIR (default outputs/)")
    p_list.add_argument("dir", nargs="?", default=str(DEFAULT_ROOT))
    p_check = sub.add_parser("check", help="list damaged or inconsistent records under DIR (default outputs/)")
    p_check.add_argument("dir", nargs="?", default=str(DEFAULT_ROOT))
    p_check.add_argument("--quarantine", action="store_true",
                         help="move damaged records to DIR/quarantine/ (nothing is deleted), rebuild summaries")
    for name, text in (("show", "run.json and metrics of one run"), ("verify", "re-run and compare tables")):
        p = sub.add_parser(name, help=text)
        p.add_argument("run")
        p.add_argument("--root", default=str(DEFAULT_ROOT))
    args = parser.parse_args(argv)
    if args.command == "list":
        table = catalog(Path(args.dir))
        cols = ["id", "sweep", "overrides", "seed", "status", "method", "synthesis", "lam", "rate", "loop", "seconds"]
        print(table[cols].to_string(index=False) if len(table) else f"no runs under {args.dir}")
        return 0
    if args.command == "check":
        return check(Path(args.dir), move=args.quarantine)
    run_dir = resolve(args.run, Path(args.root))
    try:
        info = store.read_run(run_dir)
    except store.DamagedRecord as err:
        print(f"rdsexp.runs: damaged: {err}", file=sys.stderr)
        return 1
    if args.command == "show":
        print(OmegaConf.to_yaml({k: v for k, v in info.items() if k not in ("environment", "traceback")}))
        for problem in store.run_damage(run_dir, info) if info.get("status") == "complete" else []:
            print(f"damaged: {run_dir / problem}")
        if "metrics" in (info.get("tables") or {}):
            try:
                print(store.read_table(run_dir, info, "metrics").to_string(index=False))
            except store.DamagedRecord:
                pass                                  # named above
        return 0
    return 0 if verify(run_dir) else 1


def cli() -> None:
    """Console entry point `rdsexp-runs`."""
    sys.exit(main())


if __name__ == "__main__":
    cli()
