"""Recorded inputs and outputs: the data file of a data run (`rdsexp data=FILE model=NAME`), read and checked.

The format is long form, one row per (path, k): columns `path`, `k`, `u[0]`..`u[m-1]`, `y[0]`..`y[ny-1]`
and optionally `d[0]`..  (a recorded external input; read, recorded in the column map, not used: the
EnKF is told the applied input u). CSV (`.csv`, `.csv.gz`) or parquet (`.parquet`, `.pq`). Within a
path k runs 0, 1, 2, ... in file order. Paths of different lengths are cut to the shortest (the EnKF
runs them as one batch), which must hold the modeling window k = 0..K0+K1.

Every defect is one DataError line naming the file, the row as a spreadsheet numbers it (the header is row 1,
the first data row row 2) and the column, raised before any compute.
"""
from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import DataError
from ..numerics.simulation import Recorded

SUFFIXES = (".csv", ".csv.gz", ".parquet", ".pq")
INDEXED = re.compile(r"^([a-z]+)\[(\d+)\]$")


@dataclass(frozen=True)
class RecordedData:
    """A checked data file: the recorded (u, y) of its paths (path ids sorted) over the common steps,
    and what run.json records of it (name, sha256, rows, columns, path ids, steps)."""

    file: str
    sha256: str
    rows: int
    columns: dict
    path_ids: list
    recorded: Recorded

    @property
    def info(self) -> dict:
        """run.json's `data` entry: what the run computed from."""
        return {"file": self.file, "name": Path(self.file).name, "sha256": self.sha256, "rows": self.rows,
                "columns": self.columns, "paths": len(self.path_ids), "steps": self.recorded.steps}


def file_sha256(path) -> str:
    """sha256 of the file's bytes, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_table(path: Path) -> pd.DataFrame:
    """The file as a DataFrame (CSV or parquet by its suffix); DataError when it cannot be read."""
    name = str(path)
    if not name.endswith(SUFFIXES):
        raise DataError(f"data.file: {name}: unreadable, expected a {', '.join(SUFFIXES)} file")
    try:
        return pd.read_parquet(path) if name.endswith((".parquet", ".pq")) else pd.read_csv(path)
    except Exception as err:              # noqa: BLE001 -- any reader failure is the same one line
        text = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise DataError(f"data.file: {name}: unreadable ({text})") from None


def load(path, m: int, ny: int, min_steps: int) -> RecordedData:
    """Read and check the data file for a model with m inputs and ny outputs whose window needs
    `min_steps` steps (K0 + K1 + 1) on every path. One-line DataError on any defect."""
    path = Path(path)
    name = str(path)
    if not path.is_file():
        raise DataError(f"data.file: {name}: unreadable (no such file)")
    table = read_table(path)
    where = lambda row, column: f"data.file: {name}, row {row + 2}, column {column}"   # the header is row 1
    indexed = {}
    for column in table.columns:
        match = INDEXED.match(str(column))
        if match:
            indexed.setdefault(match.group(1), []).append(int(match.group(2)))
        elif str(column) not in ("path", "k"):
            raise DataError(f"data.file: {name}, column {column}: unknown, expected path, k, u[i], y[i], d[i]")
    for family, width, what in (("u", m, "inputs m"), ("y", ny, "outputs ny")):
        found = sorted(indexed.get(family, []))
        for column in ("path", "k") if family == "u" else ():
            if column not in table.columns:
                raise DataError(f"data.file: {name}, column {column}: missing")
        for i in range(width):
            if i not in found:
                raise DataError(f"data.file: {name}, column {family}[{i}]: missing (the model has {what} = {width})")
        if found and found[-1] >= width:
            raise DataError(f"data.file: {name}, column {family}[{found[-1]}]: the model has {what} = {width} "
                              f"({family}[0]..{family}[{width - 1}])")
    if set(indexed) - {"u", "y", "d"}:
        extra = sorted(set(indexed) - {"u", "y", "d"})[0]
        raise DataError(f"data.file: {name}, column {extra}[{indexed[extra][0]}]: unknown, expected u[i], y[i], d[i]")
    d_cols = [f"d[{i}]" for i in sorted(indexed.get("d", []))]
    u_cols, y_cols = [f"u[{i}]" for i in range(m)], [f"y[{i}]" for i in range(ny)]
    if not len(table):
        raise DataError(f"data.file: {name}: no rows")
    for column in ["k", *u_cols, *y_cols, *d_cols]:
        values = pd.to_numeric(table[column], errors="coerce").to_numpy(dtype=float)
        bad = ~np.isfinite(values)
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raw = table[column].iloc[row]
            shown = str(raw.item() if hasattr(raw, "item") else raw)
            raise DataError(f"{where(row, column)}: {shown} is not a finite number")
        if column == "k" and not np.all(values == np.round(values)):
            row = int(np.flatnonzero(values != np.round(values))[0])
            raise DataError(f"{where(row, column)}: {values[row]!r} is not an integer step")
    if table["path"].isna().any():
        row = int(np.flatnonzero(table["path"].isna().to_numpy())[0])
        raise DataError(f"{where(row, 'path')}: missing path id")
    # k runs 0, 1, 2, ... within each path, in file order
    k = table["k"].to_numpy(dtype=float).astype(np.int64)
    position = table.groupby("path", sort=False).cumcount().to_numpy()
    wrong = k != position
    if wrong.any():
        row = int(np.flatnonzero(wrong)[0])
        path_id = table["path"].iloc[row]
        expected = int(position[row])
        if row > 0 and table["path"].iloc[row - 1] == path_id and k[row - 1] == k[row]:
            # a row written twice: name the row it repeats, not the step that should follow
            raise DataError(f"{where(row, 'k')}: path {path_id}, k = {k[row]} repeats row {row + 1}")
        raise DataError(f"{where(row, 'k')}: k = {k[row]} in path {path_id}, expected {expected} (k must run "
                          f"0, 1, 2, ... within a path)")
    lengths = table.groupby("path", sort=True).size()
    short = lengths[lengths < min_steps]
    if len(short):
        path_id, steps = short.index[0], int(short.iloc[0])
        row = int(np.flatnonzero((table["path"] == path_id).to_numpy())[-1])
        raise DataError(f"{where(row, 'k')}: path {path_id} has {steps} recorded steps, fewer than the window "
                          f"needs (K0 + K1 + 1 = {min_steps})")
    steps = int(lengths.min())          # ragged paths: every path cut to the shortest (one batch)
    kept = table[k < steps].sort_values(["path", "k"], kind="stable")
    P = len(lengths)
    arrays = {}
    for family, cols in (("u", u_cols), ("y", y_cols)):
        values = kept[cols].to_numpy(dtype=float).reshape(P, steps, len(cols))
        arrays[family] = np.ascontiguousarray(values.transpose(1, 0, 2))        # (K+1, P, width)
    columns = {"path": "path", "k": "k", "u": u_cols, "y": y_cols, "d": d_cols}
    return RecordedData(file=str(path.resolve()), sha256=file_sha256(path), rows=int(len(table)), columns=columns,
                        path_ids=[v.item() if hasattr(v, "item") else v for v in lengths.index],
                        recorded=Recorded(arrays["u"], arrays["y"]))


def write(path, u: np.ndarray, y: np.ndarray, path_ids=None) -> int:
    """Write recorded (u (K+1, P, m), y (K+1, P, ny)) in long form (CSV or parquet by suffix); rows written.

    Steps that are not finite (a path's values after it failed) are left out of that path: a path's
    recorded steps end where its values do."""
    steps, P = u.shape[:2]
    ids = np.arange(P) if path_ids is None else np.asarray(path_ids)
    cols = {"path": np.repeat(ids, steps), "k": np.tile(np.arange(steps), P)}
    for family, values in (("u", u), ("y", y)):
        flat = np.moveaxis(values, 1, 0).reshape(P * steps, -1)
        cols |= {f"{family}[{i}]": flat[:, i] for i in range(flat.shape[1])}
    table = pd.DataFrame(cols)
    finite = np.isfinite(table.drop(columns=["path", "k"]).to_numpy()).all(axis=1)
    # a path keeps its steps up to its first non-finite one
    ends = pd.Series(~finite).groupby(table["path"]).cummax().to_numpy()
    table = table[~ends]
    path = Path(path)
    if str(path).endswith((".parquet", ".pq")):
        table.to_parquet(path, index=False)
    elif str(path).endswith((".csv", ".csv.gz")):
        table.to_csv(path, index=False, float_format="%.17g")
    else:
        raise ValueError(f"out: {path}: expected a {', '.join(SUFFIXES)} file")
    return int(len(table))
