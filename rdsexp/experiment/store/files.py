"""Files of the run store: atomic writes, read-only stored tables and recordings, content hashes.

Every file is written to a temporary name (".<name>.<pid>.tmp") and renamed, so a killed run leaves
either a complete file or none. Writing fails loudly: an `OSError` on the way becomes `WriteError`
(one line), the temporary file is removed, nothing partial is left under a final name. Tables and
recordings are stored read-only with the sha256 of their bytes (and of their content) in run.json;
reused runs share them by hard link (`link_or_copy`).
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pandas as pd

from ...errors import WriteError

READ_ONLY = 0o444
TMP_SUFFIX = ".tmp"                 # temporary files are ".<name>.<pid>.tmp", renamed when complete


def tmp_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}{TMP_SUFFIX}")


def atomic_write_bytes(path: Path, data: bytes, read_only: bool = False) -> None:
    """Write `data` to `path` via a temporary file in the same directory and an atomic rename.

    WriteError (and no file under either name) if any step fails; `read_only` stores it mode 0444."""
    path = Path(path)
    tmp = tmp_name(path)
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
            if read_only:
                os.fchmod(fh.fileno(), READ_ONLY)
        os.replace(tmp, path)
    except OSError as err:
        _discard(tmp)
        raise WriteError(path, err) from err


def _discard(tmp: Path) -> None:
    try:
        tmp.unlink(missing_ok=True)
    except OSError:
        pass


def write_json(path: Path, obj) -> None:
    atomic_write_bytes(path, (json.dumps(obj, indent=1, sort_keys=False, default=_json_default) + "\n").encode())


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def write_table(path: Path, table: pd.DataFrame, read_only: bool = False) -> str:
    """Write a parquet table atomically; returns the sha256 of its content (see `table_hash`)."""
    buffer = io.BytesIO()
    table.to_parquet(buffer, index=False)
    atomic_write_bytes(path, buffer.getvalue(), read_only=read_only)
    return table_hash(table)


def store_table(path: Path, table: pd.DataFrame) -> dict:
    """A run's table, stored read-only; its run.json entry (file, rows, content and file sha256)."""
    buffer = io.BytesIO()
    table.to_parquet(buffer, index=False)
    atomic_write_bytes(path, buffer.getvalue(), read_only=True)
    return {"file": Path(path).name, "rows": len(table), "sha256": table_hash(table),
            "file_sha256": hashlib.sha256(buffer.getvalue()).hexdigest()}


def store_file(tmp: Path, path: Path) -> dict:
    """Move a complete file written at `tmp` to `path`, read-only; its run.json entry (file, sha256
    of its bytes). WriteError (and nothing under `path`) if that fails."""
    try:
        os.chmod(tmp, READ_ONLY)
        digest = file_hash(tmp)
        os.replace(tmp, path)
    except OSError as err:
        _discard(tmp)
        raise WriteError(path, err) from err
    return {"file": Path(path).name, "file_sha256": digest}


def file_hash(path: Path) -> str:
    """sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


_FILE_HASHES: dict[tuple, str] = {}


def unchanged_key(path: Path) -> tuple:
    """What identifies a file while it is unchanged: its path, inode, size, modification and change
    times (an edit, a chmod or a replacement changes the change time, which no user can set back).
    The key of the checks a process does once per stored file."""
    stat = os.stat(path)
    return str(path), stat.st_ino, stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns


def stored_file_hash(path: Path) -> str:
    """`file_hash` of a stored (read-only) file, computed once per process while the file is unchanged
    (`unchanged_key`). What a report reading the same runs many times uses."""
    key = unchanged_key(path)
    if key not in _FILE_HASHES:
        _FILE_HASHES[key] = file_hash(path)
    return _FILE_HASHES[key]


def table_hash(table: pd.DataFrame) -> str:
    """sha256 over column names, dtypes and values: equal for equal tables, whatever the file bytes."""
    if table.attrs:               # pandas deep-copies attrs (a stored table's schema) into every column taken
        table = table.copy(deep=False)
        table.attrs = {}
    return _hash_columns((name, table[name]) for name in table.columns)


def stored_table_hash(path: Path) -> str:
    """`table_hash` of a stored parquet table, read one column at a time (bounded memory)."""
    import pyarrow.parquet as pq
    source = pq.ParquetFile(path)
    return _hash_columns((name, source.read(columns=[name]).to_pandas()[name]) for name in source.schema_arrow.names)


def _hash_columns(columns) -> str:
    h = hashlib.sha256()
    for name, column in columns:
        h.update(f"{name}:{column.dtype}".encode())
        values = column.to_numpy()
        if values.dtype.kind == "f":     # every NaN as one: parquet stores NaN as null and reads back the
            values = np.where(np.isnan(values), np.nan, values)   # canonical NaN, whatever bits it had (inf - inf)
        h.update(values.tobytes() if values.dtype.kind in "biuf" else "\x1f".join(map(str, values)).encode())
    return h.hexdigest()


class ParquetSink:
    """Streams tables into DIR/NAME.parquet, one row group per `append`, under a temporary name until
    `close` stores them read-only (a killed run leaves no table that looks complete).

    Every append of a table must have the same columns and dtypes (the chunks of one table do).
    A failed write raises WriteError and leaves no file under the final name."""

    def __init__(self, directory: Path):
        self.directory, self.writers, self.rows = Path(directory), {}, {}

    def append(self, name: str, rows: pd.DataFrame) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq
        table = pa.Table.from_pandas(rows, preserve_index=False)
        if rows.attrs:        # schema metadata (rdsexp.experiment.schema), where pandas' to_parquet puts it
            table = table.replace_schema_metadata({**table.schema.metadata,
                                                   b"PANDAS_ATTRS": json.dumps(rows.attrs).encode()})
        tmp = tmp_name(self.directory / f"{name}.parquet")
        try:
            if name not in self.writers:
                self.writers[name], self.rows[name] = pq.ParquetWriter(tmp, table.schema), 0
            self.writers[name].write_table(table)
        except OSError as err:
            self.abort()
            raise WriteError(self.directory / f"{name}.parquet", err) from err
        self.rows[name] += len(rows)

    def close(self) -> dict:
        """Store every table; returns {name: run.json entry} as `store_table` does."""
        out = {}
        for name in list(self.writers):
            final = self.directory / f"{name}.parquet"
            tmp = tmp_name(final)
            try:
                self.writers.pop(name).close()
                with open(tmp, "rb") as fh:
                    os.fsync(fh.fileno())
            except OSError as err:
                self.abort()
                _discard(tmp)
                raise WriteError(final, err) from err
            content = stored_table_hash(tmp)
            out[name] = {"rows": self.rows[name], "sha256": content, **store_file(tmp, final)}
        return out

    def abort(self) -> None:
        """Drop every table still being written (their temporary files)."""
        for name, writer in list(self.writers.items()):
            try:
                writer.close()
            except OSError:
                pass
            _discard(tmp_name(self.directory / f"{name}.parquet"))
        self.writers = {}


def read_json(path: Path) -> dict:
    with open(path) as fh:
        return json.load(fh)


def link_or_copy(source: Path, target: Path) -> None:
    """Hard-link a read-only stored file to target (a reused run shares it); copy it (stored
    read-only) where links are not possible, the source is writable, or this process runs as root
    (modes do not stop root), so that an edit of one run's file can never change another's.
    `verify` and `check` catch an edit either way (file hashes in run.json)."""
    source, target = Path(source), Path(target)
    if not os.stat(source).st_mode & 0o222 and os.geteuid() != 0:
        try:
            os.link(source, target)
            return
        except OSError:
            pass
    tmp = tmp_name(target)
    try:
        shutil.copyfile(source, tmp)
        os.chmod(tmp, READ_ONLY)
        os.replace(tmp, target)
    except OSError as err:
        _discard(tmp)
        raise WriteError(target, err) from err
