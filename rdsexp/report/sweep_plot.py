"""A figure of any sweep from a runs table (`rdsexp.runs.search()` output, filtered by the caller).

    from rdsexp.experiment.catalog import search
    from rdsexp.report import sweep_plot
    table = search("outputs", "sweep == 'ensemble_size'")
    sweep_plot.aggregate(table, "ensemble_size", "closed_loop_rate", hue="enkf.q_scale")   # the points
    sweep_plot.plot(table, "ensemble_size", "closed_loop_rate", hue="enkf.q_scale", logx=True,
                    out=Path("outputs/report"))

One key x: at each value of x (and of `hue`, one line per hue value), the mean of the metric y over
the runs at that point (typically seeds) with a 95% t-interval over runs (`report.seed_interval`)
and the number of runs n; below, the fraction of runs without a value (status not complete, or y
not finite: left out of the mean) and the mean fraction of failed closed-loop paths
(metrics.closed_loop_failed_fraction) where the table has it. Two keys: a heatmap of the mean of y
over their grid, each cell annotated with its mean and n.

Keys and metrics are named as `rdsexp.runs.column` resolves them (ensemble_size,
enkf.ensemble_size, params.enkf.ensemble_size). The figure is saved as PNG and PDF (deterministic
bytes, `report.save_figure`), with name.caption.md and name.csv (the points) and name.json: the
lineage, naming every run drawn with the sha256 of its run.json and of its metrics table as
recorded in run.json. A run without a value of a key (or of hue) cannot be placed: it is left out
with one warning line and named under `left_out` in the lineage.
"""
from __future__ import annotations

import hashlib
import itertools
import re
import textwrap
import warnings
from dataclasses import dataclass
from pathlib import Path

import matplotlib
import matplotlib.colors
import matplotlib.ticker
import numpy as np
import pandas as pd
from matplotlib.lines import Line2D
from matplotlib.ticker import PercentFormatter
from matplotlib.transforms import ScaledTranslation, blended_transform_factory

from .. import report
from ..errors import LineageError, RecordWarning
from ..experiment.catalog import column
from ..experiment.store import Run, files, layout
from ..experiment.store.table import MISSING

SCRIPT = "rdsexp.report.sweep_plot"
FAILED_PATHS = "metrics.closed_loop_failed_fraction"
POINT_COLUMNS = ["mean", "low", "high", "n", "runs", "failed_runs", "failed_paths"]
NEEDED = ("id", "dir", "status")                 # identity columns the figure and its lineage read
COLORS, LINES, MARKERS = ("black", "0.45", "0.7"), ("-", "--", ":"), ("o", "s", "^", "D", "v")
DODGE = 3.0                                      # points between the markers of neighbouring hue values
LABEL = 5.5                                      # font size of the n= labels (points)


@dataclass
class Spec:
    """A validated request: the resolved columns, their short names, the rows that can be placed
    (and those left out), and the order of each key's values."""
    keys: list[str]                 # the one or two x columns
    y: str
    hue: str | None
    rows: pd.DataFrame              # runs with a value of every key (and hue)
    left_out: pd.DataFrame          # runs without
    values: np.ndarray              # y of rows as floats (NaN: no value)
    order: dict                     # column -> its values in drawing order
    numeric: dict                   # column -> whether its values are numbers

    def short(self, name: str) -> str:
        return name.split(".", 1)[1] if name.startswith(("params.", "metrics.")) else name


def aggregate(table: pd.DataFrame, x, y: str, hue: str | None = None) -> pd.DataFrame:
    """The points of a sweep figure, one row per (hue value, x value(s)) with runs, in drawing order.

    Columns: the x key(s) and hue (named without their params./metrics. prefix), then `mean`, `low`,
    `high` (95% t-interval of the mean over runs; NaN with fewer than two values), `n` (runs with a
    value: status complete and y finite), `runs` (all runs at the point), `failed_runs` (fraction
    without a value) and `failed_paths` (mean of metrics.closed_loop_failed_fraction over the runs at
    the point; NaN when the table has no such column). ValueError (one line) for an empty table, a
    key or metric that names no column, or a metric that is not a number."""
    return _points(_spec(table, x, y, hue))


def plot(table: pd.DataFrame, x, y: str, *, hue: str | None = None, logx: bool = False, logy: bool = False,
         out: Path | None = None, name: str | None = None) -> list[Path]:
    """Draw a sweep from a runs table (see the module's text) and save it under `out` (default
    outputs/report, as the report scripts) as NAME.png, .pdf, .caption.md, .csv (the `aggregate`
    points) and .json (lineage); NAME defaults to "{y}_vs_{x}". Returns the paths written.

    x: one key, or a list/tuple of two (heatmap of the mean of y; logy then scales the colours).
    ValueError (one line, before any drawing) for an empty table, a key or metric that names no
    column, a metric that is not a number, logx on keys that are not positive numbers, logy with a
    mean that is not positive, and hue or logx with a heatmap; DamagedRecord or LineageError when a
    run's run.json cannot be read or names another run."""
    spec = _spec(table, x, y, hue)
    points = _points(spec)
    _check_scales(spec, points, logx, logy)
    drawn = [_lineage_entry(row.id, row.dir) for row in spec.rows[["id", "dir"]].itertuples(index=False)]
    out = Path(layout.DEFAULT_ROOT) / "report" if out is None else Path(out)
    keys = [x] if isinstance(x, str) else list(x)
    name = re.sub(r"[^\w.\-]+", "_", name or f"{y}_vs_{'_and_'.join(keys)}")
    fig = _heatmap(spec, points, logy) if len(spec.keys) == 2 else _lines(spec, points, logx, logy)
    # save_figure's lineage (runs with a metrics table) is replaced below by the one of every run drawn
    runs = [report.Run(Path(entry["dir"]), {"id": entry["id"], "code": {"version": entry["code"]}}) for entry in drawn]
    for run, entry in zip(runs, drawn):
        run.used = dict(entry["tables"])
    paths = report.save_figure(fig, out, name, runs, SCRIPT, caption=_caption(spec, points))
    files.atomic_write_bytes(out / f"{name}.csv", points.to_csv(index=False).encode())
    paths += [out / f"{name}.csv", out / f"{name}.json"]
    versions = sorted({entry.pop("code") or "unknown" for entry in drawn})
    files.write_json(paths[-1], {
        "script": SCRIPT, "code_version": versions[0] if len(versions) == 1 else "mixed:" + ",".join(versions),
        "runs": drawn, "outputs": [p.name for p in paths[:-1]],
        "call": {"x": keys, "y": y, "hue": hue, "logx": logx, "logy": logy},
        "columns": {"x": spec.keys, "y": spec.y, "hue": spec.hue},
        "left_out": [{"id": r.id, "dir": r.dir} for r in spec.left_out[["id", "dir"]].itertuples(index=False)]})
    return paths


# --- the request and its points

def _spec(table: pd.DataFrame, x, y: str, hue: str | None) -> Spec:
    """Check the request against the table (ValueError, one line) and resolve its columns."""
    if not isinstance(table, pd.DataFrame) or not len(table):
        raise ValueError("the runs table is empty: nothing to plot")
    missing = [c for c in NEEDED if c not in table.columns]
    if missing:
        raise ValueError(f"the runs table has no {', '.join(missing)} column (pass rdsexp.runs.search() output)")
    if isinstance(x, str):
        keys = [x]
    elif isinstance(x, (list, tuple)) and len(x) in (1, 2) and all(isinstance(k, str) for k in x):
        keys = list(x)
    else:
        raise ValueError(f"x must be a key or a list of two keys, not {x!r}")
    keys = [_resolve(table, k, "x") for k in keys]
    if len(keys) == 2 and keys[0] == keys[1]:
        raise ValueError(f"x names the same column twice ({keys[0]})")
    ycol = _resolve(table, y, "y")
    hcol = _resolve(table, hue, "hue") if hue is not None else None
    if hcol is not None and len(keys) == 2:
        raise ValueError("hue does not apply to a heatmap (two x keys): filter the table per hue value")
    values = _numbers(table[ycol], y)
    placed = np.ones(len(table), dtype=bool)
    for col in [*keys, *([hcol] if hcol else [])]:
        placed &= ~table[col].isna().to_numpy()
    rows, left_out = table[placed], table[~placed]
    if not len(rows):
        raise ValueError(f"no run has a value of {' and '.join(keys + ([hcol] if hcol else []))}")
    if len(left_out):
        ids = ", ".join(str(i) for i in left_out["id"][:3]) + (", ..." if len(left_out) > 3 else "")
        lacking = [c for c in [*keys, *([hcol] if hcol else [])] if left_out[c].isna().any()]
        warnings.warn(f"{len(left_out)} run(s) without a value of {' or '.join(lacking)} left out of {y}: {ids}",
                      RecordWarning, stacklevel=3)
    _check_pooling(rows, [*keys, *([hcol] if hcol else [])])
    order, numeric = {}, {}
    for col in [*keys, *([hcol] if hcol else [])]:
        numeric[col] = all(_is_number(v) for v in rows[col])
        unique = list(dict.fromkeys(rows[col].tolist()))
        order[col] = sorted(unique) if numeric[col] else unique
    return Spec(keys, ycol, hcol, rows, left_out, values[placed], order, numeric)


# what must be one value within a line's point or a heatmap's cell: runs of other plants (their content) or any
# other setting are other experiments, not seeds of one. Settings that do not change a run's numbers are pooled:
# the seed (what a point averages over), where and how the run was stored, its chunks and workers (the same
# bytes), what it tracked, a tuning objective's own settings.
NOT_POOLED = {"plant_hash": "plants"}
POOLED = ("params.seed", "params.store", "params.reuse", "params.cache", "params.closed_loop.workers",
          "params.closed_loop.chunk_paths", "params.tracking.", "params.objective", "params.hydra.")


def _check_pooling(rows: pd.DataFrame, group: list[str]) -> None:
    """ValueError (one line) when a point of `group` would pool runs of different plants or settings (any config
    value but those in POOLED and the swept keys): the line names the key and its values."""
    settings = [c for c in rows.columns if c.startswith("params.") and not c.startswith(POOLED)]
    for col in [*NOT_POOLED, *settings]:
        if col not in rows.columns or col in group:
            continue
        for point, members in rows.groupby(group, dropna=False, sort=False):
            values = sorted(set(map(str, members[col])))
            if len(values) > 1:
                what = NOT_POOLED.get(col, "settings")
                at = ", ".join(f"{g}={v}" for g, v in zip(group, point if isinstance(point, tuple) else (point,)))
                raise ValueError(f"{what} differ within the point {at}: {col} is {', '.join(values)}; select one "
                                 f"with where, or split them with hue={col}")


def _resolve(table: pd.DataFrame, name, role: str) -> str:
    if not isinstance(name, str):
        raise ValueError(f"{role} must be a column name, not {name!r}")
    try:
        return column(table, name)
    except ValueError as err:
        raise ValueError(f"{role}: {err} of the runs table") from None


def _is_number(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def _numbers(series: pd.Series, name: str) -> np.ndarray:
    """The metric as floats (None, NaN: NaN); ValueError if a value is not a number."""
    out = np.full(len(series), np.nan)
    for i, v in enumerate(series.tolist()):
        if v is None or (isinstance(v, float) and np.isnan(v)) or v is pd.NA:
            continue
        if not isinstance(v, (int, float, np.integer, np.floating, bool, np.bool_)):
            raise ValueError(f"y {name!r} ({series.name}) is not a number in every run (e.g. {v!r})")
        out[i] = float(v)
    return out


def _points(spec: Spec) -> pd.DataFrame:
    rows = spec.rows
    valid = (rows["status"] == "complete").to_numpy() & np.isfinite(spec.values)
    paths = _numbers(rows[FAILED_PATHS], FAILED_PATHS) if FAILED_PATHS in rows.columns else None
    group = [*spec.keys, *([spec.hue] if spec.hue else [])]
    members: dict[tuple, list[int]] = {}
    for i, point in enumerate(zip(*(rows[c].tolist() for c in group))):
        members.setdefault(point, []).append(i)
    rank = {c: {v: k for k, v in enumerate(spec.order[c])} for c in group}
    found = {tuple(rank[c][v] for c, v in zip(group, point)): point for point in members}
    hue_first = sorted(found, key=lambda r: (r[len(spec.keys):], r[:len(spec.keys)]))
    out = []
    for point in (found[r] for r in hue_first):
        index = np.asarray(members[point])
        mean, low, high, n = report.seed_interval(spec.values[index][valid[index]])
        failed = paths[index][np.isfinite(paths[index])] if paths is not None else np.empty(0)
        out.append({**{spec.short(c): v for c, v in zip(group, point)}, "mean": mean, "low": low, "high": high,
                    "n": n, "runs": len(index), "failed_runs": (len(index) - n) / len(index),
                    "failed_paths": float(np.mean(failed)) if failed.size else np.nan})
    return pd.DataFrame(out, columns=[*(spec.short(c) for c in group), *POINT_COLUMNS])


def _check_scales(spec: Spec, points: pd.DataFrame, logx: bool, logy: bool) -> None:
    if logx and len(spec.keys) == 2:
        raise ValueError("logx does not apply to a heatmap (its cells are the grid's values); logy scales the colours")
    if logx:
        key = spec.keys[0]
        if not spec.numeric[key] or min(spec.order[key]) <= 0:
            raise ValueError(f"logx: {spec.short(key)} has values that are not positive numbers")
    means = points["mean"].to_numpy()
    if logy and (means[np.isfinite(means)] <= 0).any():
        raise ValueError(f"logy: the mean of {spec.short(spec.y)} is not positive at some point")


def _lineage_entry(run_id, run_dir) -> dict:
    """A run drawn: id, dir, sha256 of its run.json, the metrics table's sha256 as run.json records
    it (and its code version, for the lineage's code_version)."""
    run = Run(Path(run_dir))                 # DamagedRecord (one line) if its run.json cannot be read
    path, record = run.record_file, run.record
    if record.id != run_id:
        raise LineageError(f"{path}: names run {record.id!r}, the runs table {run_id!r} (search the store again)")
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    metrics = getattr(record.tables.get("metrics"), "sha256", None)
    return {"id": run_id, "dir": str(run_dir), "run_json_sha256": digest,
            "tables": {"metrics": metrics} if metrics else {}, "code": record.code_version}


# --- drawing

def _style(i: int, count: int) -> dict:
    """Line style of hue value i of count: the report's grays up to three, else viridis (ordered,
    readable in grayscale), with line styles and markers cycling."""
    viridis = matplotlib.colormaps["viridis"]
    color = COLORS[i % 3] if count <= 3 else matplotlib.colors.to_hex(viridis(0.8 * i / (count - 1)))
    return {"color": color, "ls": LINES[i % 3], "marker": MARKERS[i % len(MARKERS)]}


def _text(value) -> str:
    if isinstance(value, (float, np.floating)):
        return f"{value:g}"
    return str(value)


def _title(spec: Spec) -> str:
    rows = spec.rows
    plants = [str(p) for p in dict.fromkeys(rows["plant"].tolist())] if "plant" in rows.columns else []
    sweeps = []
    for name, sweep_id in zip(rows.get("sweep", pd.Series([None] * len(rows))).tolist(),
                              rows.get("sweep_id", pd.Series([None] * len(rows))).tolist()):
        label = name if isinstance(name, str) and name else sweep_id if isinstance(sweep_id, str) and sweep_id else None
        sweeps.append(label or MISSING)
    sweeps = list(dict.fromkeys(sweeps))

    def listed(names: list[str]) -> str:
        return ", ".join(names[:4]) + (f" and {len(names) - 4} more" if len(names) > 4 else "")
    plants = [p for p in plants if p not in ("None", "nan")] or ["unknown"]
    return (f"plant{'s' if len(plants) > 1 else ''} {listed(plants)}; "
            f"sweep{'s' if len(sweeps) > 1 else ''} {listed(sweeps)}")


def _positions(spec: Spec, key: str, values) -> np.ndarray:
    if spec.numeric[key]:
        return np.asarray([float(v) for v in values])
    where = {v: i for i, v in enumerate(spec.order[key])}
    return np.asarray([where[v] for v in values], dtype=float)


def _lines(spec: Spec, points: pd.DataFrame, logx: bool, logy: bool):
    key, yname = spec.keys[0], spec.short(spec.y)
    xname = spec.short(key)
    hues = spec.order[spec.hue] if spec.hue else [None]
    fig, (ax, ax_fail) = report.figure(report.COLUMN_WIDTH, 3.2, 2, 1, sharex=True,
                                       gridspec_kw={"height_ratios": [3, 1.1]})
    ax.set_title(textwrap.fill(_title(spec), 60))
    if logx:
        ax.set_xscale("log")
    if logy:
        ax.set_yscale("log", nonpositive="clip")
    handles, series = [], []
    for i, value in enumerate(hues):
        frame = points if value is None else points[points[spec.short(spec.hue)] == value]
        style = _style(i, len(hues))
        dx = (i - (len(hues) - 1) / 2) * DODGE
        shift = ScaledTranslation(dx / 72, 0, fig.dpi_scale_trans)
        pos = _positions(spec, key, frame[xname])
        mean, low, high = (frame[c].to_numpy(dtype=float) for c in ("mean", "low", "high"))
        err = np.nan_to_num(np.vstack([mean - low, high - mean]), nan=0.0)
        bars = ax.errorbar(pos, mean, yerr=err, capsize=2, ms=3, transform=ax.transData + shift,
                           label=_text(value) if value is not None else None, **style)
        handles.append(bars)
        mark = {"color": style["color"], "transform": ax_fail.transData + shift, "ms": 3}
        if FAILED_PATHS in spec.rows.columns:
            ax_fail.plot(pos, frame["failed_paths"].to_numpy(dtype=float), ls=style["ls"], marker=style["marker"],
                         **mark)
        ax_fail.plot(pos, frame["failed_runs"].to_numpy(dtype=float), ls="none", marker="x", **mark)
        series.append((pos, mean, high, frame, style))
        # the shifted artists do not enter the data limits: add the points themselves
        for y_values in (mean, low, high):
            finite = np.isfinite(y_values) & np.isfinite(pos)
            if finite.any():
                ax.update_datalim(np.column_stack([pos[finite], y_values[finite]]))
        ax_fail.update_datalim(np.column_stack([pos, np.zeros_like(pos)]))
    ax.set_ylabel(yname)
    ax_fail.set_xlabel(xname)
    ax_fail.set_ylabel("failed")
    _fail_axis(ax_fail, points, FAILED_PATHS in spec.rows.columns)
    _x_axis(spec, key, ax_fail, logx)
    ax.margins(x=0.12, y=0.06)
    ax.autoscale_view()
    if spec.hue:
        ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), title=spec.short(spec.hue),
                  frameon=False)           # beside the axes: never on the data
    proxies = [Line2D([], [], color="0.3", marker="x", ls="none", ms=3, label="runs without a value")]
    if FAILED_PATHS in spec.rows.columns:
        proxies.insert(0, Line2D([], [], color="0.3", marker="o", ls="-", ms=3, label="failed paths (mean over runs)"))
    fig.legend(handles=proxies, loc="outside lower center", ncols=2, frameon=False)
    _tilt_crowded(fig, ax_fail)
    _count_labels(fig, ax, series)
    return fig


def _fail_axis(ax, points: pd.DataFrame, with_paths: bool) -> None:
    """0 to 100% when nothing failed (flat at 0), else up to a little above the largest fraction."""
    shown = [points["failed_runs"].to_numpy(dtype=float)]
    if with_paths:
        shown.append(points["failed_paths"].to_numpy(dtype=float))
    top = np.nanmax(np.concatenate(shown)) if np.isfinite(np.concatenate(shown)).any() else 0.0
    top = 1.0 if top == 0 else min(1.0, 1.15 * top)
    ax.set_ylim(-0.08 * top, 1.08 * top)
    ax.yaxis.set_major_formatter(PercentFormatter(1.0, decimals=0 if top >= 0.05 else 1))
    ax.yaxis.set_major_locator(matplotlib.ticker.MaxNLocator(3))


def _x_axis(spec: Spec, key: str, ax, logx: bool) -> None:
    values = spec.order[key]
    if not spec.numeric[key]:
        ax.set_xticks(range(len(values)), [_text(v) for v in values])
        ax.set_xlim(-0.5, len(values) - 0.5)
    elif len(values) <= 10:
        ax.set_xticks([float(v) for v in values], [_text(v) for v in values])
        ax.minorticks_off()
        if logx:
            ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())


def _tilt_crowded(fig, ax) -> None:
    """Tilt the x tick labels when they would overlap (long category names)."""
    fig.draw_without_rendering()
    boxes = sorted((t.get_window_extent() for t in ax.get_xticklabels() if t.get_text()), key=lambda b: b.x0)
    if any(a.x1 + 2 > b.x0 for a, b in zip(boxes, boxes[1:])):
        ax.tick_params(axis="x", labelrotation=30)
        for label in ax.get_xticklabels():
            label.set(ha="right", rotation_mode="anchor")


def _count_labels(fig, ax, series) -> None:
    """n= of every point, stacked above the highest point drawn at its x (in hue order, in the hue's
    colour; once, "n=5 each", when every hue value has the same); n=0 points (no run with a value)
    along the bottom. Where the x values are too close for that, one vertical label per x value.
    The y axis is raised to fit the labels."""
    step, gap = LABEL + 1.5, 2.0
    tops: dict[float, list] = {}
    for pos, mean, high, frame, style in series:
        for p, m, h, n, runs in zip(pos, mean, high, frame["n"], frame["runs"]):
            top = h if np.isfinite(h) else m
            entry = tops.setdefault(float(p), [-np.inf, []])
            if np.isfinite(top):
                entry[0] = max(entry[0], top)
            text = f"n={n}" if n == runs else f"n={n} of {runs}"
            color = matplotlib.colors.to_rgb(style["color"])
            entry[1].append((text, tuple(min(c, 0.5) for c in color) if len(set(color)) == 1 else color))
    for entry in tops.values():
        if len(entry[1]) > 1 and len({text for text, _ in entry[1]}) == 1:
            entry[1] = [(entry[1][0][0] + " each", "black")]
    width = lambda text: 0.6 * LABEL * len(text)                  # points, about
    xs = np.sort(ax.transData.transform(np.column_stack([list(tops), np.zeros(len(tops))]))[:, 0]) * 72 / fig.dpi
    widest = max(width(text) for _, labels in tops.values() for text, _ in labels)
    vertical = len(xs) > 1 and np.min(np.diff(xs)) < widest + 2
    if vertical:                             # one label per x value, its counts in hue order
        for entry in tops.values():
            entry[1] = [("n=" + ", ".join(text.removeprefix("n=") for text, _ in entry[1]), "black")]
    bottom = blended_transform_factory(ax.transData, ax.transAxes)
    for p, (top, labels) in tops.items():
        for j, (text, color) in enumerate(reversed(labels)):     # the first hue value on top, as in the legend
            xy, coords = ((p, top), "data") if np.isfinite(top) else ((p, 0.0), bottom)
            ax.annotate(text, xy, xycoords=coords, xytext=(0, gap + j * step), textcoords="offset points",
                        ha="center", va="bottom", fontsize=LABEL, color=color, annotation_clip=False,
                        rotation=90 if vertical else 0)
    fig.draw_without_rendering()                 # the axes' final size, to make room for the labels
    scale = ax.yaxis.get_transform()
    y0, y1 = scale.transform(np.asarray(ax.get_ylim(), dtype=float))
    height = ax.bbox.height * 72 / fig.dpi                          # points
    new = y1
    for top, labels in tops.values():
        room = height - (gap + (width(labels[0][0]) if vertical else len(labels) * step) + 3)
        if np.isfinite(top) and room > 0:
            new = max(new, y0 + (scale.transform(np.asarray([top], dtype=float))[0] - y0) * height / room)
    if new > y1:
        ax.set_ylim(ax.get_ylim()[0], float(scale.inverted().transform(np.asarray([new]))[0]))


def _heatmap(spec: Spec, points: pd.DataFrame, logy: bool):
    kx, ky = spec.keys
    cols, rows = spec.order[kx], spec.order[ky]
    grid = np.full((len(rows), len(cols)), np.nan)
    cells = {}
    for _, point in points.iterrows():
        i, j = rows.index(point[spec.short(ky)]), cols.index(point[spec.short(kx)])
        grid[i, j] = point["mean"]
        cells[i, j] = point
    width = report.COLUMN_WIDTH if len(cols) <= 6 else report.PAGE_WIDTH
    fig, ax = report.figure(width, min(1.3 + 0.5 * len(rows), 8.0))
    fig.suptitle(textwrap.fill(_title(spec), 70 if width == report.COLUMN_WIDTH else 140),
                 fontsize=matplotlib.rcParams["axes.titlesize"])
    cmap = matplotlib.colormaps["viridis"].with_extremes(bad="0.92")
    finite = grid[np.isfinite(grid)]
    norm = (matplotlib.colors.LogNorm if logy else matplotlib.colors.Normalize)(
        *(finite.min(), finite.max()) if finite.size else (None, None))
    image = ax.imshow(np.ma.masked_invalid(grid), origin="lower", aspect="auto", cmap=cmap, norm=norm,
                      interpolation="nearest")
    fig.colorbar(image, ax=ax, label=f"{spec.short(spec.y)} (mean over runs)", shrink=0.9)
    size = 6 if len(cols) <= 6 and len(rows) <= 6 else 5
    for (i, j), point in sorted(cells.items()):
        n, runs = int(point["n"]), int(point["runs"])
        lines = [f"{point['mean']:.4g}" if n else "no value", f"n={n}" if n == runs else f"n={n} of {runs}"]
        if np.isfinite(point["failed_paths"]) and point["failed_paths"] > 0:
            lines += [f"{point['failed_paths']:.0%} of paths", "failed"]
        dark = n and np.dot(cmap(norm(point["mean"]))[:3], [0.299, 0.587, 0.114]) < 0.5
        ax.text(j, i, "\n".join(lines), ha="center", va="center", fontsize=size, color="white" if dark else "black")
    for i, j in itertools.product(range(len(rows)), range(len(cols))):
        if (i, j) not in cells:
            ax.text(j, i, "no runs", ha="center", va="center", fontsize=size, color="0.4")
    ax.set_xticks(range(len(cols)), [_text(v) for v in cols])
    ax.set_yticks(range(len(rows)), [_text(v) for v in rows])
    ax.set_xlabel(spec.short(kx))
    ax.set_ylabel(spec.short(ky))
    ax.tick_params(length=0)
    return fig


def _caption(spec: Spec, points: pd.DataFrame) -> str:
    yname = spec.short(spec.y)
    keys = " and ".join(spec.short(k) for k in spec.keys)
    what = (f"{yname} against {keys}" + (f", one line per {spec.short(spec.hue)}" if spec.hue else "")
            if len(spec.keys) == 1 else f"mean of {yname} over the grid of {keys}")
    text = (f"{what} ({_title(spec)}): mean over the runs at each point with a 95% t-interval over runs; n runs "
            f"with a value (status complete, {yname} finite); failed_runs: the fraction of runs without a value, "
            f"left out of the mean; failed_paths: the mean over runs of the fraction of failed closed-loop paths.")
    return text + "\n\n" + report._markdown(points)
