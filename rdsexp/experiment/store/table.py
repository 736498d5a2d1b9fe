"""The runs table: one row per stored run, built in one place for the catalog, search and sweep summaries.

Columns: the run's identity (IDENTITY), then `metrics.<name>` (the key numbers and statuses of
run.json's summary, flattened as the metric registry `rdsexp.experiment.metrics` says) and, on
request, `params.<dotted.key>` (every resolved scalar of its composed config).
"""
from __future__ import annotations

import fcntl
import json
from pathlib import Path

import numpy as np
import pandas as pd

from ...errors import WriteError
from ..metrics import per_job
from . import files
from .layout import SUMMARY, SUMMARY_CSV, SUMMARY_LOCK
from .record import RunRecord
from .run import MATRIX, read_runs, scalar_config, scalars_only

IDENTITY = ["id", "sweep", "sweep_id", "resumes", "job", "objective_role", "seed", "status", "plant", "plant_hash",
            "model", "method", "overrides", "reused_from", "created", "code", "config_hash", "dir"]
MISSING = "-"       # how every view shows a missing value, e.g. the sweep of a run that is no sweep's job (None)


def identity(run_dir: Path, record: RunRecord) -> dict:
    """The identity columns of a run (IDENTITY) from its typed run.json (`record.RunRecord`): sweep is the
    `+sweep=NAME` config, else the command-line overrides of the `-m` run (`sweep_name`); plant is the plant
    file's `name:`, else its file name (the runner records it so; from the config where a run ended before
    its summary), plant_hash the first 12 hex digits of run.json's `plant_hash` (the plant's content: two
    files of one name that differ have different hashes). A data run has no plant: its identity is its data
    file, shown as plant `data:NAME` and the first 12 hex digits of the file's sha256 as plant_hash."""
    sweep, s = record.sweep, record.summary
    if record.data is not None:
        plant, plant_hash = f"data:{record.data.get('name')}", str(record.data.get("sha256") or "")[:12] or None
    else:
        plant = s.plant or (record.params or {}).get("plant.name")
        plant_hash = (record.plant_hash or "")[:12] or None
    return {"id": record.id, "sweep": sweep and sweep.name, "sweep_id": sweep and sweep.id,
            "resumes": sweep and sweep.resumes, "job": sweep and sweep.job,
            "objective_role": record.objective.role if record.objective else None, "seed": record.seed,
            "status": record.status, "plant": plant, "plant_hash": plant_hash, "model": s.model,
            "method": s.gain_method,
            "overrides": " ".join(o for o in record.overrides if not o.startswith("+sweep=")),
            "reused_from": record.reused_from, "created": record.created, "code": record.code_version,
            "config_hash": record.config_hash, "dir": str(run_dir)}


def run_params(run_dir: Path, params: dict | None = None) -> dict:
    """{"params.<dotted.key>": value} for every resolved scalar of the run's config: run.json's
    `params` (written with the run, `RunRecord.params`), else from .hydra/config.yaml (`run.scalar_config`)."""
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


def sweep_results(table: pd.DataFrame) -> pd.DataFrame:
    """A sweep's results from its runs table (with params): per job, the swept values (the params that
    vary), the status, the metrics shown per job (`metrics.per_job`) and the run it reused, if any."""
    shown = [m.column for m in per_job() if m.column in table.columns]
    cols = ["job", *changed_params(table), "status", *shown, "reused_from"]
    return table.sort_values("job", kind="stable")[[c for c in dict.fromkeys(cols) if c in table.columns]]


def as_text(table: pd.DataFrame, max_rows: int | None = None) -> str:
    """A runs table as text: short column names (no params./metrics.), 4 significant digits, "-" for
    missing; at most max_rows rows, with a last line saying how many were left out."""
    short = {c: c.split(".", 1)[1] if c.startswith(("params.", "metrics.")) else c for c in table.columns}
    shown = table if max_rows is None else table.head(max_rows)
    # None in a column of objects (the sweep of a run that is no sweep's job) prints as "None" otherwise, a
    # missing whole number (the job of a held-out run) as "<NA>"
    shown = shown.apply(lambda col: col.astype(object).where(col.notna(), MISSING)
                        if col.dtype == object or pd.api.types.is_extension_array_dtype(col) else col)
    text = shown.rename(columns=short).to_string(index=False, float_format=lambda v: f"{v:.4g}", na_rep=MISSING)
    return text + (f"\n... {len(table) - len(shown)} more rows" if len(shown) < len(table) else "")


def changed_params(table: pd.DataFrame) -> list[str]:
    """The params columns whose value is not the same in every row (like `dvc exp show`)."""
    return [c for c in table.columns if c.startswith("params.") and table[c].astype(str).nunique() > 1]


def runs_table(runs: list[tuple[Path, dict]], params: bool = False) -> pd.DataFrame:
    """One row per (run directory, run.json), in the given order: IDENTITY, metrics.* and, with
    `params`, params.* (sorted)."""
    records = [(d, RunRecord.parse(info)) for d, info in runs]
    rows = [identity(d, r) | r.metrics | (run_params(d, r.params) if params else {}) for d, r in records]
    table = pd.DataFrame(rows, columns=IDENTITY if not rows else None)
    if len(table):
        metrics = [c for c in table.columns if c.startswith("metrics.")]
        table = table[IDENTITY + metrics + sorted(c for c in table.columns if c.startswith("params."))]
        if "params.plant.name" in table.columns:      # a plant file without `name:` is named by its file
            table["params.plant.name"] = table["params.plant.name"].fillna(table["plant"])
        if "params.seed" in table.columns:            # a record without run.json's seed: the config's
            table["seed"] = table["seed"].fillna(table["params.seed"])
    for name in ("job", "seed"):
        table[name] = table[name].astype("Int64")
    return table


def one_row_per_run(table: pd.DataFrame) -> pd.DataFrame:
    """The rows of a runs table with each computation once: a reused job (reused_from set) is a copy
    of an earlier run, so where that run, or an earlier copy of it, is among the rows, it is left out.
    Rows are oldest first, so the original is the row kept when present."""
    computation = table["reused_from"].where(table["reused_from"].notna(), table["id"])
    return table[~computation.duplicated(keep="first")].reset_index(drop=True)


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
