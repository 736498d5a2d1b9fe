"""Rerun recordings (.rrd) of trajectory tables, for viewing in the Rerun Viewer.

The trajectories table stays the source of truth; the recording mirrors it as

* ``/{experiment}/{QUANTITY}/{i}``: one entity per value column ``QUANTITY[i]``, a
  ``Scalars`` batch of P instances per step on the sequence timeline ``k``
  (instance = sample path);
* ``/{experiment}/members/{QUANTITY}/{i}``: optional ensemble members, P*M instances per
  step (instance = path * M + member);
* recording property ``rdsexp``: experiment and value-column order, so that
  :func:`read_recording` can rebuild the table exactly.

NaN values are stored as ordinary float64 NaNs inside the batches and read back as such.
"""

from __future__ import annotations

import re
from collections import defaultdict
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import rerun as rr
import rerun.blueprint as rrb

KEYS = ["experiment", "k", "path"]
MEMBER_KEYS = ["experiment", "k", "path", "member"]

_COLUMN = re.compile(r"^(?P<quantity>.+)\[(?P<index>\d+)\]$")
_SCALARS = rr.Scalars.descriptor_scalars().component
_PROPERTY = "rdsexp"
# View group of a quantity, by the prefix before its first "_" (x_pred_mean -> x).
_GROUPS = {"q": "state", "x": "state", "xi": "xi", "u": "input"}


def _split(column: str) -> tuple[str, int]:
    """``"x_pred_mean[3]"`` -> ``("x_pred_mean", 3)``."""
    match = _COLUMN.match(column)
    if match is None:
        raise ValueError(f"value column {column!r} is not named QUANTITY[i]")
    return match["quantity"], int(match["index"])


def _entity(experiment: str, *parts: str | int) -> str:
    """Entity path ``/{experiment}/{parts...}``: "/" in `experiment` nests, anything else is escaped."""
    # Escaping makes the path canonical, so the reader's schema finds it under the same string.
    return "/" + "/".join(rr.escape_entity_path_part(str(p)) for p in (*experiment.split("/"), *parts))


def _steps(frame: pd.DataFrame, instance: np.ndarray, what: str) -> np.ndarray:
    """Steps ``ks`` (K,) of one experiment, checking the rows are the complete grid in
    (k, instance) order with instances 0..W-1, so its values reshape to (K, W)."""
    ks = frame["k"].unique()
    width, rest = divmod(len(frame), len(ks))
    if rest or not (
        np.array_equal(frame["k"].to_numpy(), np.repeat(ks, width))
        and np.array_equal(instance, np.tile(np.arange(width), len(ks)))
    ):
        raise ValueError(f"{what} rows are not a complete grid sorted by k, then path (from 0)")
    return ks.astype(np.int64)


def _send(rec: rr.RecordingStream, entity: str, ks: np.ndarray, values: np.ndarray) -> None:
    """One columnar send of `values` (K, W): step j carries the W scalars ``values[j]``."""
    steps, width = values.shape
    rec.send_columns(
        entity,
        indexes=[rr.TimeColumn("k", sequence=ks)],
        columns=rr.Scalars.columns(scalars=values.ravel()).partition(np.full(steps, width)),
    )


def _blueprint(experiments: list[str], quantities: list[str]) -> rrb.Blueprint:
    """One tab per experiment holding a grid of time-series views: state (q with EnKF x means),
    xi estimates, input u, and one view per spread group (``*_std``)."""
    groups: dict[str, list[str]] = defaultdict(list)
    for quantity in quantities:
        group = _GROUPS.get(quantity.split("_")[0], quantity)
        groups[f"{group} std" if quantity.endswith("_std") else group].append(quantity)
    return rrb.Blueprint(
        rrb.Tabs(*(
            rrb.Grid(
                *(
                    rrb.TimeSeriesView(
                        name=group,
                        origin=_entity(experiment),
                        contents=[f"$origin/{rr.escape_entity_path_part(q)}/**" for q in group_quantities],
                        # P lines per entity would drown a legend.
                        plot_legend=rrb.PlotLegend(visible=False),
                    )
                    for group, group_quantities in groups.items()
                ),
                name=experiment,
            )
            for experiment in experiments
        ))
    )


def write_recording(
    path,
    trajectories: pd.DataFrame,
    *,
    recording_id: str,
    application_id: str = "rdsexp",
    members: pd.DataFrame | None = None,
) -> None:
    """Write `trajectories` (rows: (experiment, k, path) grid, P paths per step) and optionally
    `members` (rows: (experiment, k, path, member) grid, M members per path) to the .rrd `path`,
    with a default blueprint. The file is complete when this returns; with ``RERUN=off`` in the
    environment rerun disables the stream and nothing is written."""
    columns = [c for c in trajectories.columns if c not in KEYS]
    split = [_split(c) for c in columns]
    experiments = list(trajectories["experiment"].unique())
    blueprint = _blueprint(experiments, list(dict.fromkeys(q for q, _ in split)))

    # A private stream (not the global one) so repeated calls never share state, and leaving the
    # `with` block flushes and finalizes the file sink (footer written, file closed).
    with rr.RecordingStream(application_id, recording_id=recording_id) as rec:
        rec.save(Path(path), default_blueprint=blueprint)
        rec.send_property(_PROPERTY, rr.AnyValues(experiments=experiments, columns=columns))
        for experiment, frame in trajectories.groupby("experiment", sort=False):
            frame = frame.sort_values(["k", "path"], kind="stable")       # tables are stored path-major
            ks = _steps(frame, frame["path"].to_numpy(), f"trajectories[{experiment!r}]")
            values = frame[columns].to_numpy(np.float64)
            for j, (quantity, i) in enumerate(split):
                _send(rec, _entity(experiment, quantity, i), ks, values[:, j].reshape(len(ks), -1))
        if members is not None:
            member_columns = [c for c in members.columns if c not in MEMBER_KEYS]
            n_members = int(members["member"].max()) + 1
            for experiment, frame in members.groupby("experiment", sort=False):
                frame = frame.sort_values(["k", "path", "member"], kind="stable")
                instance = frame["path"].to_numpy() * n_members + frame["member"].to_numpy()
                ks = _steps(frame, instance, f"members[{experiment!r}]")
                values = frame[member_columns].to_numpy(np.float64)
                for j, column in enumerate(member_columns):
                    entity = _entity(experiment, "members", *_split(column))
                    _send(rec, entity, ks, values[:, j].reshape(len(ks), -1))


def _property(store: rr.chunk.LazyStore, name: str) -> list[str]:
    """Value list `name` of the ``rdsexp`` recording property."""
    content = f"/__properties/{_PROPERTY}"
    table = store.stream().filter(content=content).collect().reader(index=None, contents=content).to_arrow_table()
    return table.column(f"property:{_PROPERTY}:{name}")[0].as_py()


def read_recording(path) -> pd.DataFrame:
    """Read an .rrd written by :func:`write_recording` back into the trajectories table
    (same keys, value columns, row order; float64 values, NaN included)."""
    # The lazy store reads only the file's chunk manifest; the filter below then loads just the
    # trajectory chunks, never the (P*M per step) members.
    lazy = rr.chunk.RrdReader(Path(path)).store()
    experiments, columns = _property(lazy, "experiments"), _property(lazy, "columns")
    entities = {(e, c): _entity(e, *_split(c)) for e in experiments for c in columns}
    store = lazy.stream().filter(content=list(entities.values())).collect()
    schema = store.schema()
    # One row per step k; each cell is the list of P path values.
    table = store.reader(index="k").to_arrow_table().sort_by("k")
    ks = table.column("k").to_numpy()

    frames = []
    for experiment in experiments:
        cells: list[pa.ListArray] = [
            table.column(schema.column_for(entities[experiment, c], _SCALARS).name).combine_chunks()
            for c in columns
        ]
        # Steps where only other experiments have data are null rows here; all columns of
        # one experiment share its steps.
        present = cells[0].is_valid().to_numpy(zero_copy_only=False)
        values = [c.filter(present).flatten().to_numpy(zero_copy_only=False) for c in cells]
        steps = ks[present]
        n_paths = len(values[0]) // len(steps)
        keys = {
            "experiment": np.repeat(experiment, len(steps) * n_paths),
            "k": np.repeat(steps, n_paths),
            "path": np.tile(np.arange(n_paths, dtype=np.int64), len(steps)),
        }
        frames.append(pd.DataFrame(keys | dict(zip(columns, values, strict=True))))
    return pd.concat(frames, ignore_index=True)
