"""Run records: the run directory, run.json and its provenance, atomic writes of tables, hashing.

A run directory holds Hydra's `.hydra/`, `run.json` (status, timings, seeds, code version,
environment, table hashes), parquet tables, `recording.rrd` and, when the working tree was dirty,
`uncommitted.diff`. Every file is written to a temporary name and renamed, so a killed run leaves
either a complete file or none; `run.json` says "incomplete" until the last table is in place.
"""
from __future__ import annotations

import datetime as dt
import hashlib
import io
import json
import os
import platform
import shutil
import socket
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import numpy as np
import pandas as pd

from .. import __version__

PACKAGES = ("rdsexp", "numpy", "scipy", "cvxpy", "clarabel", "pandas", "pyarrow", "hydra-core",
            "omegaconf", "rerun-sdk", "matplotlib", "tqdm")
PACKAGE = Path(__file__).resolve().parents[1]
REPO = PACKAGE.parent          # the repository root when rdsexp runs from a checkout


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write `data` to `path` via a temporary file in the same directory and an atomic rename."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def write_json(path: Path, obj) -> None:
    atomic_write_bytes(path, (json.dumps(obj, indent=1, sort_keys=False, default=_json_default) + "\n").encode())


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def write_table(path: Path, table: pd.DataFrame) -> str:
    """Write a parquet table atomically; returns the sha256 of its content (see `table_hash`)."""
    buffer = io.BytesIO()
    table.to_parquet(buffer, index=False)
    atomic_write_bytes(path, buffer.getvalue())
    return table_hash(table)


def table_hash(table: pd.DataFrame) -> str:
    """sha256 over column names, dtypes and values: equal for equal tables, whatever the file bytes."""
    return _hash_columns((name, table[name]) for name in table.columns)


def file_hash(path: Path) -> str:
    """`table_hash` of a stored parquet table, read one column at a time (bounded memory)."""
    import pyarrow.parquet as pq
    source = pq.ParquetFile(path)
    return _hash_columns((name, source.read(columns=[name]).to_pandas()[name]) for name in source.schema_arrow.names)


def _hash_columns(columns) -> str:
    h = hashlib.sha256()
    for name, column in columns:
        h.update(f"{name}:{column.dtype}".encode())
        values = column.to_numpy()
        h.update(values.tobytes() if values.dtype.kind in "biuf" else "\x1f".join(map(str, values)).encode())
    return h.hexdigest()


class ParquetSink:
    """Streams tables into DIR/NAME.parquet, one row group per `append`, under a temporary name until
    `close` renames them (a killed run leaves no table that looks complete).

    Every append of a table must have the same columns and dtypes (the chunks of one table do)."""

    def __init__(self, directory: Path):
        self.directory, self.writers, self.rows = Path(directory), {}, {}

    def append(self, name: str, rows: pd.DataFrame) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq
        table = pa.Table.from_pandas(rows, preserve_index=False)
        if name not in self.writers:
            self.writers[name] = pq.ParquetWriter(self.directory / f".{name}.parquet.{os.getpid()}.tmp", table.schema)
            self.rows[name] = 0
        self.writers[name].write_table(table)
        self.rows[name] += len(rows)

    def close(self) -> dict:
        """Finish every table; returns {name: {"file", "rows", "sha256"}} as run.json's `tables`."""
        out = {}
        for name, writer in self.writers.items():
            writer.close()
            tmp, final = self.directory / f".{name}.parquet.{os.getpid()}.tmp", self.directory / f"{name}.parquet"
            with open(tmp, "rb") as fh:
                os.fsync(fh.fileno())
            os.replace(tmp, final)
            out[name] = {"file": final.name, "rows": self.rows[name], "sha256": file_hash(final)}
        self.writers = {}
        return out


def config_hash(job_config: dict) -> str:
    """sha256 of the resolved job config (canonical JSON), the identity of what a run computes."""
    return hashlib.sha256(json.dumps(job_config, sort_keys=True, default=str).encode()).hexdigest()


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(["git", "-C", str(REPO), *args], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout if out.returncode == 0 else None


def code_version() -> dict:
    """Git commit of the rdsexp source, dirty flag, the uncommitted diff and a version string.

    version = commit, plus "+" and a hash of the diff when dirty, so two runs share a version
    exactly when they ran the same code (untracked files under outputs/ are ignored by git).
    An installed copy (not a checkout, e.g. `pip install .`) has version "rdsexp==<__version__>".
    """
    top = (_git("rev-parse", "--show-toplevel") or "").strip()
    if not top or Path(top).resolve() != REPO:        # installed: the enclosing repository, if any, is not ours
        return {"commit": None, "dirty": False, "version": f"rdsexp=={__version__}", "diff": ""}
    commit = (_git("rev-parse", "HEAD") or "").strip() or None
    status = _git("status", "--porcelain", "--untracked-files=no")
    diff = _git("diff", "HEAD") or ""
    dirty = bool(status and status.strip())
    version = (commit or "unknown") + ("+" + hashlib.sha256(diff.encode()).hexdigest()[:12] if dirty else "")
    return {"commit": commit, "dirty": dirty, "version": version, "diff": diff if dirty else ""}


def environment() -> dict:
    """Python, host, package versions and BLAS threading of this process."""
    versions = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    try:
        from threadpoolctl import threadpool_info
        blas = [{k: info.get(k) for k in ("internal_api", "num_threads", "version")} for info in threadpool_info()]
    except ImportError:
        blas = None
    threads = {v: os.environ.get(v) for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    return {"python": sys.version.split()[0], "platform": platform.platform(), "host": socket.gethostname(),
            "cpu_count": os.cpu_count(), "packages": versions, "blas": blas, "thread_env": threads}


def read_json(path: Path) -> dict:
    with open(path) as fh:
        return json.load(fh)


def now() -> str:
    """UTC time stamp of run.json, to the millisecond."""
    return dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds")


def link_or_copy(source: Path, target: Path) -> None:
    """Hard-link source to target (a reused run shares its files), copying where links are not possible."""
    try:
        os.link(source, target)
    except OSError:
        shutil.copy2(source, target)
