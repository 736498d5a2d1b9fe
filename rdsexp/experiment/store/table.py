"""The runs table: one row per stored run, built in one place for the catalog, search and sweep summaries.

Columns: the run's identity (IDENTITY), then `metrics.<name>` (the key numbers and statuses of
run.json's summary, flattened) and, on request, `params.<dotted.key>` (every resolved scalar of its
composed config).
"""
from __future__ import annotations

import fcntl
import json
from pathlib import Path

import numpy as np
import pandas as pd

from ...errors import WriteError
from . import files
from .layout import SUMMARY, SUMMARY_CSV, SUMMARY_LOCK
from .run import MATRIX, read_runs, scalar_config, scalars_only

IDENTITY = ["id", "sweep", "sweep_id", "job", "status", "plant", "model", "method", "overrides",
            "reused_from", "created", "code", "config_hash", "dir"]
# summary entries that are settings or nested records rather than numbers of the run
NOT_METRICS = ("plant", "model", "gain_method", "rate_window", "reference", "designs", "identification_feedback")


def identity(run_dir: Path, info: dict) -> dict:
    """The identity columns of a run (IDENTITY) from its run.json."""
    sweep, s = info.get("sweep") or {}, info.get("summary") or {}
    job = sweep.get("job")
    return {"id": info.get("id"), "sweep": sweep.get("name"),
            "sweep_id": Path(sweep["dir"]).name if sweep.get("dir") else None,
            "job": job if isinstance(job, int) else None, "status": info.get("status"),
            "plant": s.get("plant"), "model": s.get("model"), "method": s.get("gain_method"),
            "overrides": " ".join(o for o in info.get("overrides", []) if not o.startswith("+sweep=")),
            "reused_from": info.get("reused_from"), "created": info.get("created"),
            "code": (info.get("code") or {}).get("version"), "config_hash": info.get("config_hash"),
            "dir": str(run_dir)}


def run_metrics(info: dict) -> dict:
    """{"metrics.<name>": value}: the key numbers and statuses of run.json's summary, flattened
    (closed_loop_rate, _low, _high; xi_mean[i]; closed_loop_failed_fraction, ...) and seconds."""
    s = info.get("summary") or {}
    out = {}
    for name, value in s.items():
        if name in NOT_METRICS:
            continue
        if name.endswith("_rate") and isinstance(value, list) and len(value) == 3:
            out[name], out[f"{name}_low"], out[f"{name}_high"] = value
        elif isinstance(value, dict):
            out |= {f"{name}_{k}": v for k, v in value.items()}
        elif isinstance(value, list):
            out |= {f"{name}[{i}]": v for i, v in enumerate(value)}
        else:
            out[name] = value
    for loop in ("closed_loop", "open_loop"):
        if f"{loop}_status" in s:
            out.setdefault(f"{loop}_failed_fraction", 0.0)
    out["seconds"] = info.get("seconds")
    return {f"metrics.{k}": (np.nan if v is None else v) for k, v in out.items()}


def run_params(run_dir: Path, info: dict | None = None) -> dict:
    """{"params.<dotted.key>": value} for every resolved scalar of the run's config: run.json's
    `params` (written with the run), else from .hydra/config.yaml (`run.scalar_config`)."""
    params = (info or {}).get("params")
    if not isinstance(params, dict):
        params = flat_params(scalar_config(run_dir))
    return {f"params.{k}": v for k, v in params.items()}


def flat_params(config: dict) -> dict:
    """{dotted.key: value} for every scalar of a resolved config; a flat list of at most 8 scalars
    (rate_window) as its JSON text; matrices left out."""
    out = {}

    def walk(tree: dict, prefix: str) -> None:
        for name, value in tree.items():
            if isinstance(value, dict):
                walk(value, f"{prefix}{name}.")
            elif isinstance(value, list):
                out[f"{prefix}{name}"] = json.dumps(value)
            elif value != MATRIX:
                out[f"{prefix}{name}"] = value
    walk(scalars_only(config), "")
    return out


def changed_params(table: pd.DataFrame) -> list[str]:
    """The params columns whose value is not the same in every row (like `dvc exp show`)."""
    return [c for c in table.columns if c.startswith("params.") and table[c].astype(str).nunique() > 1]


def runs_table(runs: list[tuple[Path, dict]], params: bool = False) -> pd.DataFrame:
    """One row per (run directory, run.json), in the given order: IDENTITY, metrics.* and, with
    `params`, params.* (sorted)."""
    rows = [identity(d, info) | run_metrics(info) | (run_params(d, info) if params else {}) for d, info in runs]
    table = pd.DataFrame(rows, columns=IDENTITY if not rows else None)
    if len(table):
        metrics = [c for c in table.columns if c.startswith("metrics.")]
        table = table[IDENTITY + metrics + sorted(c for c in table.columns if c.startswith("params."))]
    table["job"] = table["job"].astype("Int64")
    return table


def write_sweep_summary(sweep_dir: Path) -> Path:
    """Rebuild <sweep>/summary.parquet (and .csv) from the jobs' run.json files on disk: the runs
    table of the sweep's jobs, by job.

    Jobs finishing at once (joblib, Ray, Slurm workers) rebuild one after the other under a lock on
    <sweep>/.summary.lock, so the last rebuild has seen every job that finished before it: without
    it a slow rebuild could overwrite a newer one with fewer jobs."""
    path = Path(sweep_dir) / SUMMARY
    with SweepLock(sweep_dir):
        table = runs_table(read_runs(sweep_dir)[0]).sort_values("job", ignore_index=True, kind="stable")
        for name in (c for c in table.columns if table[c].dtype.kind == "O"):
            kinds = {type(v) for v in table[name] if v is not None and not (isinstance(v, float) and np.isnan(v))}
            if len(kinds) > 1:              # e.g. a metric that is a number in one job, a word in another
                table[name] = [None if pd.isna(v) else str(v) for v in table[name]]
        files.write_table(path, table)
        files.atomic_write_bytes(path.with_name(SUMMARY_CSV), table.to_csv(index=False).encode())
    return path


class SweepLock:
    """An exclusive lock on <sweep>/.summary.lock (WriteError if the file cannot be opened)."""

    def __init__(self, sweep_dir: Path):
        self.path = Path(sweep_dir) / SUMMARY_LOCK

    def __enter__(self):
        try:
            self.fh = open(self.path, "a")
        except OSError as err:
            raise WriteError(self.path.with_name(SUMMARY), err) from err
        fcntl.flock(self.fh, fcntl.LOCK_EX)
        return self

    def __exit__(self, *exc) -> None:
        self.fh.close()
