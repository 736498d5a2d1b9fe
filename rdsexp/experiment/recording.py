"""Rerun recordings (.rrd) of a run's tables, for viewing in the Rerun Viewer.

The recording opens on a **summary** tab (`write_summary`, entities under ``/summary``):
sqrt(E||q_k||^2) over the paths with its 95% band, the exact ideal-loop curve and lambda^k
(linear and log10), the EnKF's xi estimates of the identification run with the true and modeled
means (the modeled mean drawn over the modeling window k = K0..K0+K1 only), histograms of the
window's xi samples the model was built from, and a markdown report (gain, statuses, metrics);
a **states** tab: per state q_k and the ensemble mean +- spread over a few sample paths; with the
online controller an **online controller** tab (`_online`, entities under ``/summary/online``),
from its controller table: over the update steps, the median and 10-90% band over paths of the
exact rate on the true plant of the gain in use (against the offline gain's and the optimum), of
the modeled mean and standard deviation of each xi[i] (against the true ones), and of each entry of
the gain in use (against the offline gain). The raw paths follow in one tab per experiment (the
bounded sample the pipeline passes, tracking.recorded_paths per loop).

The trajectories table stays the source of truth; the raw tabs mirror it as

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

import os
import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import rerun as rr
import rerun.blueprint as rrb

from ..numerics.analysis import rms_band
from . import metrics as metric_registry
from .schema import split_column
from .store import RunStore, layout
from .store.table import changed_params
from .summary import drawn_over, lost_paths

KEYS = ["experiment", "k", "path"]
MEMBER_KEYS = ["experiment", "k", "path", "member"]

_SCALARS = rr.Scalars.descriptor_scalars().component
_PROPERTY = "rdsexp"
# View group of a quantity, by the prefix before its first "_" (x_pred_mean -> x).
_GROUPS = {"q": "state", "x": "state", "xi": "xi", "u": "input"}


def disabled() -> bool:
    """Rerun's streams are off (``RERUN=off``, ``0``, ``false`` or ``no`` in the environment): checked
    before any stream exists, since a disabled stream warns at every call, its teardown included."""
    return os.environ.get("RERUN", "").strip().lower() in {"off", "0", "false", "no"}


def _split(column: str) -> tuple[str, int]:
    """(quantity, index) of a value column (`schema.split_column`), which it must be."""
    split = split_column(column)
    if split is None:
        raise ValueError(f"value column {column!r} is not named QUANTITY[i] or QUANTITY[i,j]")
    return split


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
    tables: dict[str, pd.DataFrame] | None = None,
    summary: dict | None = None,
    window: tuple[int, int] | None = None,
    xi_true: np.ndarray | None = None,
    xi_true_std: np.ndarray | None = None,
    squares: dict[str, np.ndarray] | None = None,
) -> bool:
    """Write `trajectories` (rows: (experiment, k, path) grid, P paths per step) and optionally
    `members` (rows: (experiment, k, path, member) grid, M members per path) to the .rrd `path`,
    with a default blueprint. With the run's `tables` (pipeline.TABLES but the streamed ones) and
    `summary` the recording opens on the summary tab (`write_summary`; window: (K0, K0 + K1),
    xi_true, xi_true_std: the true mean and standard deviations of xi in the model's terms, (p,), if
    known; squares: loop -> ||q_k||^2 (K+1, P) over every path, else computed from the paths in
    `trajectories`).
    The file is complete when this returns True; with ``RERUN=off`` in the environment rerun
    disables the stream: nothing is written and this returns False."""
    if disabled():
        return False
    columns = [c for c in trajectories.columns if c not in KEYS]
    split = [_split(c) for c in columns]
    experiments = list(trajectories["experiment"].unique())
    blueprint = _blueprint(experiments, list(dict.fromkeys(q for q, _ in split)))
    if tables is not None:
        blueprint = rrb.Blueprint(rrb.Tabs(*_summary_tabs(tables, trajectories), *blueprint.root_container.contents))

    # A private stream (not the global one) so repeated calls never share state, and leaving the
    # `with` block flushes and finalizes the file sink (footer written, file closed).
    with rr.RecordingStream(application_id, recording_id=recording_id) as rec:
        rec.save(Path(path), default_blueprint=blueprint)
        rec.send_property(_PROPERTY, rr.AnyValues(experiments=experiments, columns=columns))
        if tables is not None:
            write_summary(rec, tables, trajectories, summary or {}, window=window, xi_true=xi_true,
                          xi_true_std=xi_true_std, squares=squares)
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
    return True


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


# ------------------------------------------------------------------------------------ summary
def _values(frame: pd.DataFrame, quantity: str) -> tuple[np.ndarray, np.ndarray]:
    """Steps (K,) and values (K, P, d) of quantity[0..d-1] of one experiment's (k, path) grid."""
    cols = [c for c in frame.columns if split_column(c) and split_column(c)[0] == quantity]
    frame = frame.sort_values(["k", "path"], kind="stable")          # tables are stored path-major
    ks = frame["k"].unique().astype(np.int64)
    return ks, frame[cols].to_numpy(np.float64).reshape(len(ks), -1, len(cols))


def _line(rec, entity: str, ks: np.ndarray, values: np.ndarray, name: str, color=None, width: float = 1.5) -> None:
    """One named scalar series (K,) on the timeline k."""
    rec.log(entity, rr.SeriesLines(names=[name], colors=[color] if color is not None else None, widths=[width]),
            static=True)
    rec.send_columns(entity, indexes=[rr.TimeColumn("k", sequence=ks)],
                     columns=rr.Scalars.columns(scalars=np.asarray(values, np.float64)))


def _log10(values: np.ndarray) -> np.ndarray:
    with np.errstate(all="ignore"):
        return np.where(values > 0, np.log10(values), np.nan)


LOOP_COLORS = {"closed_loop": (31, 119, 180), "open_loop": (214, 39, 40), "online": (44, 160, 44)}
PALETTE = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (148, 103, 189), (140, 86, 75), (227, 119, 194)]
GREY = (200, 200, 200)
STATE_PATHS = 3


def write_summary(rec: rr.RecordingStream, tables: dict[str, pd.DataFrame], trajectories: pd.DataFrame,
                  summary: dict, *, window: tuple[int, int] | None = None, xi_true: np.ndarray | None = None,
                  xi_true_std: np.ndarray | None = None, squares: dict[str, np.ndarray] | None = None) -> None:
    """The summary entities of a run (see the module docstring) from its tables and the recorded
    paths `trajectories`; the rms band from `squares` (loop -> ||q_k||^2 (K+1, P)) when given."""
    exact, gains = tables["exact"], tables["gains"]
    selected = gains[gains["selected"]]
    lam = float(selected["lam"].iloc[0]) if len(selected) else np.nan
    traj = trajectories[trajectories["experiment"] != "identification"]
    for loop, frame in traj.groupby("experiment", sort=False):
        color = LOOP_COLORS.get(loop)
        ks, q = _values(frame, "q")
        if squares is not None and loop in squares:
            sq = squares[loop]
            ks = np.arange(sq.shape[0], dtype=np.int64)
            mean, low, high = rms_band(sq)
        else:
            mean, low, high = rms_band(np.sum(q ** 2, axis=-1))
        ex = exact[exact["experiment"] == loop]
        lines = [("mean", ks, mean, f"{loop} sqrt(E|q|^2)", 2.0), ("band_low", ks, low, f"{loop} 95% band", 0.7),
                 ("band_high", ks, high, f"{loop} 95% band", 0.7)]
        if len(ex):
            lines.append(("exact", ex["k"].to_numpy(np.int64), ex["rms"].to_numpy(), f"{loop} exact (state feedback)",
                          1.0))
            if loop == "closed_loop" and np.isfinite(lam):
                lines.append(("lambda_k", ex["k"].to_numpy(np.int64), ex["rms"].iloc[0] * lam ** ex["k"].to_numpy(),
                              f"lambda^k, lambda = {lam:.4f}", 1.0))
        floor = summary.get("noise_floor")
        if loop == "closed_loop" and floor is not None and np.isfinite(floor) and floor > 0:
            lines.append(("noise_floor", ks, np.full(ks.size, floor), "noise floor (the loop at rest)", 0.7))
        for name, k, v, label, width in lines:
            _line(rec, f"/summary/rms/{loop}/{name}", k, v, label, color, width)
            _line(rec, f"/summary/log10_rms/{loop}/{name}", k, _log10(v), label, color, width)
        if loop == "closed_loop":
            _, x = _values(frame, "x_filt_mean")
            _, std = _values(frame, "x_filt_std")
            for i in range(q.shape[-1]):
                for j in range(min(STATE_PATHS, q.shape[1])):
                    base = f"/summary/state/q{i}/path{j}"
                    _line(rec, f"{base}/q", ks, q[:, j, i], f"q[{i}] path {j}", GREY, 1.5)
                    _line(rec, f"{base}/mean", ks, x[:, j, i], f"x_k|k[{i}] path {j}", color, 1.5)
                    _line(rec, f"{base}/upper", ks, x[:, j, i] + std[:, j, i], "mean + spread", color, 0.5)
                    _line(rec, f"{base}/lower", ks, x[:, j, i] - std[:, j, i], "mean - spread", color, 0.5)
    _xi(rec, tables, window, xi_true)
    if "controller" in tables:
        _online(rec, tables, summary.get("online", {}), xi_true, xi_true_std)
    rec.log("/summary/report", rr.TextDocument(report_markdown(tables, summary), media_type="text/markdown"),
            static=True)


def _xi(rec, tables: dict, window, xi_true) -> None:
    """xi_{k|k} of the identification's first path, the true and modeled means, and the histograms of xi_{k|k}
    over the window of every identification path (what the modeling reads)."""
    ident, model = tables["identification"], tables["model"]
    if not len(ident) or not any(c.startswith("xi_filt_mean[") for c in ident.columns):
        return                            # no identification run, or no xi to estimate (p = 0)
    ks, xi = _values(ident[ident["path"] == 0], "xi_filt_mean")
    _, every = _values(ident, "xi_filt_mean")                             # (K+1, P, p)
    modeled = model[model["quantity"] == "mean"].sort_values("row")["value"].to_numpy()
    k0, k1 = window if window is not None else (int(ks[0]), int(ks[-1]))
    inside = (ks >= k0) & (ks <= k1)
    for i in range(xi.shape[-1]):
        color = PALETTE[i % len(PALETTE)]
        _line(rec, f"/summary/xi/xi{i}/estimate", ks, xi[:, 0, i], f"xi_k|k[{i}]", color, 1.5)
        if i < len(modeled):     # drawn over the modeling window only: it marks the window
            _line(rec, f"/summary/xi/xi{i}/modeled_mean", ks[inside], np.full(inside.sum(), modeled[i]),
                  f"modeled mean[{i}] (k = {k0}..{k1})", color, 3.0)
        if xi_true is not None and i < len(xi_true) and np.isfinite(xi_true[i]):
            _line(rec, f"/summary/xi/xi{i}/true_mean", ks, np.full(len(ks), xi_true[i]), f"true mean[{i}]", GREY, 1.0)
        samples = every[inside, :, i].ravel()
        samples = samples[np.isfinite(samples)]
        if len(samples):
            counts, edges = np.histogram(samples, bins=min(15, max(len(samples) // 4, 1)))
            rec.log(f"/summary/xi_histogram/xi{i}", rr.BarChart(counts, abscissa=(edges[:-1] + edges[1:]) / 2,
                                                                widths=np.diff(edges), color=color), static=True)


def in_use(controller: pd.DataFrame, column: str) -> tuple[np.ndarray, np.ndarray]:
    """Steps (U,) and values (U, P) of `column` for the gain each path holds from each step on.

    controller: the controller table; the initial gain (k = -1) is in use from k = 0 and a gain
    adopted after filtering at k from k + 1, so the steps are 0 and every update step + 1."""
    adopted = controller[controller["adopted"]]
    wide = adopted.pivot(index="k", columns="path", values=column)
    steps = np.union1d(wide.index.to_numpy(), controller["k"].unique())
    return steps.astype(np.int64) + 1, wide.reindex(steps).ffill().to_numpy(np.float64)


def modeled(controller: pd.DataFrame, column: str) -> tuple[np.ndarray, np.ndarray]:
    """Update steps (U,) and the values (U, P) of `column` of each path's decision there."""
    wide = controller[controller["k"] >= 0].pivot(index="k", columns="path", values=column)
    return wide.index.to_numpy(np.int64), wide.to_numpy(np.float64)


def _over_paths(rec, base: str, ks: np.ndarray, values: np.ndarray, label: str, color) -> None:
    """Median and 10-90% band over paths of values (K, P), NaN (not yet modeled) ignored."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)        # steps where no path has a value
        low, mid, high = np.nanpercentile(values, [10, 50, 90], axis=1)
    _line(rec, f"{base}/median", ks, mid, f"{label}, median over paths", color, 2.0)
    _line(rec, f"{base}/q10", ks, low, f"{label}, 10-90% of paths", color, 0.7)
    _line(rec, f"{base}/q90", ks, high, f"{label}, 10-90% of paths", color, 0.7)


def _online(rec, tables: dict, metrics: dict, xi_true, xi_true_std) -> None:
    """The online controller's decisions over time (module docstring, online tab)."""
    controller, gains = tables["controller"], tables["gains"]
    ks, rate = in_use(controller, "rate_plant")
    span = ks[[0, -1]]
    color = LOOP_COLORS["online"]
    _over_paths(rec, "/summary/online/rate_plant/online", ks, rate, "online gain in use", color)
    for name, label, c in (("offline_rate_plant", "offline gain", LOOP_COLORS["closed_loop"]),
                           ("optimal_rate_plant", "optimum on the true plant", GREY)):
        if metrics.get(name) is not None:
            _line(rec, f"/summary/online/rate_plant/{name}", span, np.full(2, metrics[name]),
                  f"{label} {metrics[name]:.4f}", c, 1.0)
    p = sum(1 for c in controller.columns if c.startswith("mean["))
    for i in range(p):
        color = PALETTE[i % len(PALETTE)]
        k, mean = modeled(controller, f"mean[{i}]")
        _over_paths(rec, f"/summary/online/xi_mean/xi{i}", k, mean, f"modeled mean[{i}]", color)
        k, var = modeled(controller, f"cov[{i},{i}]")
        _over_paths(rec, f"/summary/online/xi_std/xi{i}", k, np.sqrt(np.maximum(var, 0.0)), f"modeled std[{i}]",
                    color)
        for truth, what in ((xi_true, "mean"), (xi_true_std, "std")):
            if truth is not None and i < len(truth) and np.isfinite(truth[i]) and len(k):
                _line(rec, f"/summary/online/xi_{what}/xi{i}/true", k[[0, -1]], np.full(2, truth[i]),
                      f"true {what}[{i}]", GREY, 1.0)
    selected = gains[gains["selected"]]
    for column in (c for c in controller.columns if c.startswith("F[")):
        row, j = _split(column)                                   # one view per row of F
        base = f"/summary/online/gain/{row}/{j}"
        _over_paths(rec, f"{base}/online", *in_use(controller, column), column, PALETTE[j % len(PALETTE)])
        if len(selected) and column in selected:
            _line(rec, f"{base}/offline", span, np.full(2, selected[column].iloc[0]), f"offline {column}", GREY, 1.0)


def _fmt(v) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, (float, np.floating)):
        return "n/a" if not np.isfinite(v) else f"{v:.4g}"
    return str(v)


def _data_report(tables: dict[str, pd.DataFrame], s: dict) -> str:
    """A data run's report: the data file, the moments, each design's exact rate on the identified model with
    its spread over the moments' draws, and the held-out validation. No number here is about a plant."""
    d = s["data"]
    lines = [f"# data {d['name']} / model {s.get('model', '')}", "",
             f"- data: sha256 {d['sha256'][:12]}, {d['rows']} rows, {d['paths']} paths x {d['steps']} steps "
             f"({d['identification_paths']} identify, {d['holdout_paths']} held out); **no plant**: every rate is "
             f"exact on the identified model",
             f"- modeling: **{s.get('modeling_status', 'n/a')}**"
             + (f", xi mean {np.round(s['xi_mean'], 4).tolist()}, std {np.round(s['xi_std'], 4).tolist()}"
                if "xi_mean" in s else ""),
             "", "## Designs on the identified model", "",
             "| method | status | rate on model | median over draws | 5% | 95% | worst |",
             "|---|---|---|---|---|---|---|"]
    for method, r in (s.get("design_rates") or {}).items():
        lines.append(f"| {method} | {r['status']} | {_fmt(r.get('rate_model'))} | {_fmt(r.get('rate_model_median'))} "
                     f"| {_fmt(r.get('rate_model_q05'))} | {_fmt(r.get('rate_model_q95'))} | "
                     f"{_fmt(r.get('rate_model_worst'))} |")
    for name, r in (s.get("loops_on_model") or {}).items():
        if isinstance(r, dict):
            lines.append(f"- {name.replace('_', ' ')} (**{s['loops_on_model']['label']}**): **{r['verdict']}**, rate "
                         f"{_fmt(r['rate'][0])} [{_fmt(r['rate'][1])}, {_fmt(r['rate'][2])}] over k = "
                         f"{s['loops_on_model']['rate_window']}, ideal loop on the model {_fmt(r['exact_rate'])}")
    if "validation" in tables:
        v = tables["validation"]
        lines += ["", f"## Validation on held-out paths (y one step ahead, k = {s['validation']['k_from']}.."
                      f"{s['validation']['k_to']})", "", "| law | output | CRPS | coverage 50% | coverage 90% |",
                  "|---|---|---|---|---|"]
        lines += [f"| {r.law} | {r.output} | {_fmt(r.crps)} | {_fmt(r.coverage_50)} | {_fmt(r.coverage_90)} |"
                  for r in v.itertuples()]
    return "\n".join(lines) + "\n"


def report_markdown(tables: dict[str, pd.DataFrame], summary: dict) -> str:
    """The run's gain, statuses and key metrics as a markdown document."""
    s = summary
    if s.get("data"):                  # a data run: no plant, every rate on the identified model
        return _data_report(tables, s)
    lines = [f"# {s.get('plant', 'plant')} / model {s.get('model', '')}", "",
             f"- modeling: **{s.get('modeling_status', 'n/a')}**"
             + (f", xi mean {np.round(s['xi_mean'], 4).tolist()}, nbar {s.get('nbar')}" if "xi_mean" in s else ""),
             f"- gain {s.get('gain_method')}: **{s.get('synthesis_status', 'n/a')}**, lambda {_fmt(s.get('lam'))}, "
             f"exact rate on the true plant {_fmt(s.get('rate_plant'))}"]
    if "modeling_uncertainty" in s:               # the moments' spread over their draws
        u = s["modeling_uncertainty"]
        lines.insert(3, f"- modeled moments' spread over {u['resamples']} {drawn_over(u)}: xi mean sd "
                        f"{np.round(u['xi_mean_sd'], 4).tolist()}, xi std sd {np.round(u['xi_std_sd'], 4).tolist()}")
    if "gain_choice" in s:
        c = s["gain_choice"]
        lines.append(f"- gain choice: **{c['kept']}**; exact rate's {c['quantile']:.0%} quantile over {c['draws']} "
                     f"draws of the moments: designed {_fmt(c['designed_quantile'])}, identification's "
                     f"{_fmt(c['identification_quantile'])}")
    for loop in ("closed_loop", "open_loop", "online"):
        if f"{loop}_rate" in s:
            r = s[f"{loop}_rate"]
            lines.append(f"- {loop.replace('_', ' ')}: **{s.get(f'{loop}_verdict')}**, rate {_fmt(r[0])} "
                         f"[{_fmt(r[1])}, {_fmt(r[2])}] over k = {s.get('rate_window')} "
                         f"({s.get('rate_window_source', 'config')}), ideal loop {_fmt(s.get(f'{loop}_exact_rate'))}: "
                         f"{s.get(f'{loop}_verdict_reason')}")
    if "online" in s:
        o = s["online"]
        lines.append(f"- online controller: final gains' exact rate on the true plant median "
                     f"{_fmt(o.get('final_rate_plant_median'))} [10-90%: {_fmt(o.get('final_rate_plant_q10'))}, "
                     f"{_fmt(o.get('final_rate_plant_q90'))}], {_fmt(o.get('final_stable_fraction'))} of paths "
                     f"stable; offline gain {_fmt(o.get('offline_rate_plant'))}, optimum "
                     f"{_fmt(o.get('optimal_rate_plant'))}; {_fmt(o.get('adoptions_per_path'))} adoptions per path")
        if o.get("lost_more_p") is not None:
            lines.append(f"- online paths lost: {lost_paths(o)}")
    gains = tables["gains"]
    chosen = gains[gains["selected"]]
    if len(chosen):
        cols = [c for c in gains.columns if c.startswith("F[")]
        idx = [tuple(int(v) for v in c[2:-1].split(",")) for c in cols]
        m, n = max(i for i, _ in idx) + 1, max(j for _, j in idx) + 1
        F = chosen[cols].to_numpy(float).reshape(m, n)
        lines += ["", "## Gain F (u = F x)", "", "| | " + " | ".join(f"x{j}" for j in range(n)) + " |",
                  "|---" * (n + 1) + "|"]
        lines += [f"| u{i} | " + " | ".join(_fmt(v) for v in F[i]) + " |" for i in range(m)]
    lines += ["", "## Designs", "", "| distribution | method | status | lam | rate on plant |", "|---|---|---|---|---|"]
    lines += [f"| {r.distribution} | {r.method} | {r.status} | {_fmt(r.lam)} | {_fmt(r.rate_plant)} |"
              for r in gains.itertuples()]
    metrics = tables["metrics"]
    if len(metrics):
        cols = ["experiment", "status", "rate", "rate_low", "rate_high", "failed_fraction", "x_rmse", "xi_rmse"]
        cols = [c for c in cols if c in metrics.columns]
        lines += ["", "## Metrics", "", "| " + " | ".join(cols) + " |", "|---" * len(cols) + "|"]
        lines += ["| " + " | ".join(_fmt(v) for v in row) + " |" for row in metrics[cols].itertuples(index=False)]
    return "\n".join(lines) + "\n"


def _summary_tabs(tables: dict[str, pd.DataFrame], trajectories: pd.DataFrame) -> list:
    """The summary and states tabs of the default blueprint."""
    loops = list(trajectories["experiment"].unique())
    p = sum(1 for c in tables["identification"].columns if c.startswith("xi_filt_mean["))
    n = sum(1 for c in trajectories.columns if split_column(c) and split_column(c)[0] == "q")
    legend = rrb.PlotLegend(corner=rrb.Corner2D.RightTop, visible=True)
    summary = rrb.Grid(
        rrb.TimeSeriesView(name="log10 sqrt(E|q_k|^2): band, exact, lambda^k", origin="/summary/log10_rms",
                           plot_legend=legend),
        rrb.TimeSeriesView(name="sqrt(E|q_k|^2)", origin="/summary/rms", plot_legend=legend),
        rrb.TimeSeriesView(name="xi estimates (identification), true and modeled means", origin="/summary/xi",
                           plot_legend=legend),
        rrb.Horizontal(*(rrb.BarChartView(name=f"xi[{i}] samples in the window", origin=f"/summary/xi_histogram/xi{i}")
                         for i in range(p))) if p else rrb.TextDocumentView(origin="/summary/report"),
        rrb.TextDocumentView(name="report", origin="/summary/report"),
        name="summary", grid_columns=2,
    )
    states = rrb.Grid(*(rrb.TimeSeriesView(name=f"closed loop q[{i}] and x_k|k +- spread ({STATE_PATHS} paths)",
                                           origin=f"/summary/state/q{i}", plot_legend=rrb.PlotLegend(visible=False))
                        for i in range(n)), name="states") if "closed_loop" in loops else None
    tabs = [summary] + ([states] if states is not None else [])
    if "controller" in tables:
        rows = sorted({_split(c)[0] for c in tables["controller"].columns if c.startswith("F[")})
        tabs.append(rrb.Grid(
            rrb.TimeSeriesView(name="exact rate on the true plant of the gain in use", plot_legend=legend,
                               origin="/summary/online/rate_plant"),
            rrb.TimeSeriesView(name="modeled mean of xi (update steps) and true mean", plot_legend=legend,
                               origin="/summary/online/xi_mean"),
            rrb.TimeSeriesView(name="modeled std of xi (update steps) and true std", plot_legend=legend,
                               origin="/summary/online/xi_std"),
            *(rrb.TimeSeriesView(name=f"gain in use, row {row[1:]} of F, and the offline gain", plot_legend=legend,
                                 origin=f"/summary/online/gain/{row}") for row in rows),
            name="online controller", grid_columns=2))
    return tabs


def read_series(path, entity: str, index: str = "k") -> tuple[np.ndarray, np.ndarray]:
    """Steps (timeline `index`: k, or a swept key in a sweep's summary.rrd; a duration timeline reads back as
    timedelta64) and scalar values of one series entity of an .rrd (e.g. /summary/rms/closed_loop/mean), read
    with Rerun's own reader; an entity with several instances per step gives its values step by step."""
    store = rr.chunk.RrdReader(Path(path)).store().stream().filter(content=[entity]).collect()
    column = store.schema().column_for(entity, _SCALARS).name
    table = store.reader(index=index).to_arrow_table().sort_by(index)
    cells = table.column(column).combine_chunks()
    present = cells.is_valid().to_numpy(zero_copy_only=False)
    return table.column(index).to_numpy()[present], cells.filter(present).flatten().to_numpy(zero_copy_only=False)


# ------------------------------------------------------------------------------------ sweeps
# Metrics drawn against the swept values: the registry's plotted ones first (`metrics.plotted`), rates then
# fractions; any other numeric rate (online: final_rate_plant_median, ...) and fraction follow (`metrics.kind_of`).
# One color per hue combination, in the order of its first job (fixed, so a sweep always looks the same).
_HUE_COLORS = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
               (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]
# The jobs table's metrics: the registry's per job (`metrics.per_job`; closed_loop_rate with its interval).
_CORNERS = (rrb.Corner2D.RightBottom, rrb.Corner2D.RightTop, rrb.Corner2D.LeftTop, rrb.Corner2D.LeftBottom)
_FRACTION_AXIS = (-0.03, 1.03)
# The whole timeline (every x value, the margins of /sweep/x_range included), not a window around the cursor.
_WHOLE_X = rrb.archetypes.TimeAxis(view_range=rr.encodings.TimeRange(start=rr.encodings.TimeRangeBoundary.infinite(),
                                                                      end=rr.encodings.TimeRangeBoundary.infinite()))


def _is_number(column: pd.Series) -> bool:
    return pd.api.types.is_numeric_dtype(column) and not pd.api.types.is_bool_dtype(column)


def _floats(column: pd.Series) -> np.ndarray:
    """A column's values as float64, NaN for missing ones (nullable integers such as `job` included)."""
    return pd.to_numeric(column, errors="coerce").to_numpy(np.float64, na_value=np.nan)


def _short(column: str) -> str:
    return column.split(".", 1)[1] if column.startswith(("params.", "metrics.")) else column


def _sweep_metrics(table: pd.DataFrame) -> tuple[list[str], list[str]]:
    """(rates, fractions): the numeric metrics.* columns with a value, the registry's plotted metrics first
    (`metrics.plotted`), each of the kind the registry gives it (`metrics.kind_of`)."""
    names = [c for c in table.columns if c.startswith("metrics.")]
    first = [m.column for m in metric_registry.plotted()]
    rates, fractions = [], []
    for c in [c for c in first if c in names] + [c for c in names if c not in first]:
        if not _is_number(table[c]) or not table[c].notna().any():
            continue
        kind = metric_registry.kind_of(c)
        if kind == metric_registry.FRACTION:
            fractions.append(c)
        elif kind == metric_registry.RATE:
            rates.append(c)
    return rates, fractions


def _x_keys(table: pd.DataFrame, swept: list[str]) -> list[str]:
    """The x axes of a sweep: its numeric swept keys but the seed (the repetition); the seed when nothing else
    numeric is swept; the job index when nothing numeric is swept at all."""
    numeric = [c for c in swept if _is_number(table[c])]
    return [c for c in numeric if c != "params.seed"] or numeric or ["job"]


def _x_timeline(key: str, values: np.ndarray) -> tuple[str, str, float]:
    """(timeline name, TimeColumn kind, scale) of x key `key` with finite `values`: a sequence of the values when
    all are integers; else a duration whose seconds are the values (the axis reads 250ms for 0.25, 2s for 2)
    when they stay below 60 in magnitude (with at least 1e-6, for ns resolution); else a sequence of the values
    times a power of ten. The name says how the axis reads: `KEY`, `KEY (1 s = 1)` or `KEY ×1000`."""
    name = _short(key)
    if np.allclose(values, np.rint(values), rtol=0, atol=1e-9):
        return name, "sequence", 1.0
    magnitude = np.abs(values[values != 0])
    if magnitude.max() < 60 and magnitude.min() >= 1e-6:
        return f"{name} (1 s = 1)", "duration", 1.0
    for digits in range(1, 10):
        if np.allclose(values * 10.0**digits, np.rint(values * 10.0**digits), rtol=1e-9, atol=0):
            break
    else:                                                     # keep four significant digits of the smallest
        digits = int(np.clip(3 - np.floor(np.log10(magnitude.min())), 1, 9))
    return f"{name} ×{10**digits}", "sequence", 10.0**digits


def _x_times(kind: str, scale: float, values: np.ndarray) -> dict:
    """TimeColumn keyword for x values on a timeline of `_x_timeline`."""
    if kind == "duration":
        return {"duration": values.astype(np.float64)}
    return {"sequence": np.rint(values * scale).astype(np.int64)}


def _function_of(table: pd.DataFrame, column: str, key: str) -> bool:
    """Each value of `key` comes with one value of `column` (e.g. a config value derived from the swept one)."""
    pairs = table[[key, column]].astype(str).drop_duplicates()
    return not pairs[key].duplicated().any()


def _hue_keys(table: pd.DataFrame, swept: list[str], x: str) -> list[str]:
    """The swept keys whose combinations are the hues when `x` is the x axis: the other swept keys but the
    seed, without those that follow from x or from a key already taken (one group override that sets two
    params is one hue key)."""
    keys: list[str] = []
    for c in swept:
        if c in (x, "params.seed") or (x != "job" and _function_of(table, c, x)):
            continue
        if not any(_function_of(table, c, k) and _function_of(table, k, c) for k in keys):
            keys.append(c)
    return keys


def _hues(table: pd.DataFrame, keys: list[str]) -> tuple[pd.Series, dict[tuple, str]]:
    """Each row's hue combination (a tuple of the values of `keys` as text) and, in the order of their first
    job, every combination with its label `key=value, ...` ('all runs' without hue keys)."""
    values = table[keys].map(_fmt) if keys else pd.DataFrame(index=table.index)
    combos = pd.Series(list(values.itertuples(index=False, name=None)), index=table.index)
    labels = {c: ", ".join(f"{k.rsplit('.', 1)[-1]}={v}" for k, v in zip(keys, c, strict=True)) or "all runs"
              for c in dict.fromkeys(combos)}
    return combos, labels


def _sweep_series(rec, table: pd.DataFrame, metric: str, group: str, x: str, timeline: str, kind: str,
                  scale: float, combos: pd.Series, labels: dict[tuple, str]) -> None:
    """/sweep/{group}/{metric}/{x}/{hue}/mean (line: the mean of the metric over the runs at each x value, the
    seeds) and .../runs (points: the runs, one instance per run at that x, in job order) for each hue (HUE: its
    label, `all` without hue keys), on the timeline of x only."""
    for i, (combo, label) in enumerate(labels.items()):
        rows = table[(combos == combo) & np.isfinite(_floats(table[x]))]
        if rows.empty:
            continue
        color = _HUE_COLORS[i % len(_HUE_COLORS)]
        hue = rr.escape_entity_path_part(label) if combo else "all"
        base = "/".join(["/sweep", group, _short(metric), _short(x), hue])
        mean = rows.groupby(x, sort=True)[metric].mean()
        xs = mean.index.to_numpy(np.float64)
        index = [rr.TimeColumn(timeline, **_x_times(kind, scale, xs))]
        rec.log(f"{base}/mean", rr.SeriesLines(names=[label], colors=[color], widths=[2.0]), static=True)
        rec.send_columns(f"{base}/mean", indexes=index, columns=rr.Scalars.columns(scalars=mean.to_numpy(np.float64)))
        runs = [rows.loc[rows[x] == v, metric].to_numpy(np.float64) for v in mean.index]
        width = max(len(r) for r in runs)
        rec.log(f"{base}/runs", rr.SeriesPoints(names=[label] * width, colors=[color] * width,
                                                marker_sizes=[3.5] * width), static=True)
        rec.send_columns(f"{base}/runs", indexes=index, columns=rr.Scalars.columns(
            scalars=np.concatenate(runs)).partition([len(r) for r in runs]))


def _legend(table: pd.DataFrame, metric: str, x: str, combos: pd.Series, labels: dict[tuple, str],
            y_range: tuple[float, float] | None = None) -> rrb.PlotLegend:
    """A visible legend in the corner of the plot of `metric` against `x` that covers the fewest of its runs
    and of its mean lines (sampled between their points); the legend's box sized from its labels."""
    xs, ys = [], []
    for combo in labels:
        rows = pd.DataFrame({x: _floats(table.loc[combos == combo, x]),
                             metric: _floats(table.loc[combos == combo, metric])}).dropna()
        if rows.empty:
            continue
        mean = rows.groupby(x)[metric].mean()
        grid = np.linspace(mean.index[0], mean.index[-1], 40)
        xs += [rows[x].to_numpy(), grid]
        ys += [rows[metric].to_numpy(), np.interp(grid, mean.index.to_numpy(), mean.to_numpy())]
    if not xs:
        return rrb.PlotLegend(corner=_CORNERS[0], visible=True)
    x_all, y_all = np.concatenate(xs), np.concatenate(ys)
    low, high = y_range or (y_all.min(), y_all.max())
    u = (x_all - x_all.min()) / ((x_all.max() - x_all.min()) or 1.0)
    v = (y_all - low) / ((high - low) or 1.0)
    width = min(0.9, (7 * max(len(label) for label in labels.values()) + 40) / 450)
    height = min(0.9, 0.06 + 0.09 * len(labels))
    covered = [np.sum((u >= 1 - width if "Right" in c.name else u <= width)
                      & (v <= height if "Bottom" in c.name else v >= 1 - height)) for c in _CORNERS]
    return rrb.PlotLegend(corner=_CORNERS[int(np.argmin(covered))], visible=True)


def _jobs_markdown(table: pd.DataFrame, title: str, swept: list[str], axes: list[str], hue_keys: list[str]) -> str:
    """The sweep's title, how to read its plots, and a markdown table of its jobs (job, status, swept values,
    key metrics; closed_loop_rate with its interval)."""
    statuses = ", ".join(f"{n} {s}" for s, n in table["status"].value_counts(sort=False).items())
    seed = " (the seed is the repetition)" if "params.seed" in swept and axes != ["seed"] else ""
    hues = f"one color per {', '.join(_short(c) for c in hue_keys)}" if hue_keys else "one color"
    lines = [f"**{title}**: {len(table)} jobs ({statuses}); swept: "
             f"**{', '.join(_short(c) for c in swept) or 'nothing'}**{seed}. Plots: x = the active timeline (bottom "
             f"bar): **{'**, **'.join(axes)}**; {hues}; line = mean over the runs at each x (the seeds), points = "
             "the runs.", ""]
    metrics = [m.column for m in metric_registry.per_job() if m.column in table.columns]
    cols = ["job", "status", *swept, *metrics]
    head = [{"metrics.closed_loop_rate": "closed_loop_rate [low, high]"}.get(c, _short(c)) for c in cols]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(cols)]
    bounds = {"metrics.closed_loop_rate_low", "metrics.closed_loop_rate_high"} <= set(table.columns)
    for _, row in table.iterrows():
        cells = [_fmt(row[c]) for c in cols]
        if "metrics.closed_loop_rate" in cols and bounds:
            cells[cols.index("metrics.closed_loop_rate")] += (f" [{_fmt(row['metrics.closed_loop_rate_low'])}, "
                                                              f"{_fmt(row['metrics.closed_loop_rate_high'])}]")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _legend_room(values: np.ndarray, entries: int, height: float) -> tuple[float, float]:
    """A y range over `values` (5% margins) with room above them for a legend of `entries` lines in the top
    corner (about 20 px a line in a plot about `height` px high), so that the legend covers no point."""
    values = values[np.isfinite(values)]
    if not len(values):
        return 0.0, 1.0
    low, high = values.min(), values.max()
    span = (high - low) or abs(high) * 0.1 or 1.0
    low, high = low - 0.05 * span, high + 0.05 * span
    return float(low), float(low + (high - low) / (1 - min(0.6, (10 + 20 * entries) / height)))


def _sweep_blueprint(table: pd.DataFrame, title: str, rates: list[str], fractions: list[str], x: str,
                     timeline: str, vs: str, combos: pd.Series, labels: dict[tuple, str],
                     entries: int) -> rrb.Blueprint:
    """A grid of views, the rates (legend on top, above the values; at most `entries` hues on any x axis) then
    the fractions (axis 0..1, legend in the emptiest corner for the first x axis `x`), over the jobs table,
    which gets the height of its rows up to 45% of the window (then scrolls); the active timeline `timeline`."""
    def view(metric: str, group: str, y_range: tuple[float, float], legend: rrb.PlotLegend) -> rrb.TimeSeriesView:
        return rrb.TimeSeriesView(name=f"{_short(metric)} {vs}", origin=f"/sweep/{group}/{_short(metric)}",
                                  axis_x=_WHOLE_X, axis_y=rrb.ScalarAxis(range=y_range, zoom_lock=False),
                                  plot_legend=legend)

    # heights in px of a window about 1000 px high: about 830 for the views, 21 a row of the jobs table
    share = float(np.clip((110 + 21 * (len(table) + 1)) / 830, 0.3, 0.45))
    n, columns = len(rates) + len(fractions), min(5, -(-(len(rates) + len(fractions)) // 2))
    height = (1 - share) * 830 / max(1, -(-n // columns)) - 45          # a plot, without title and x axis
    top = rrb.PlotLegend(corner=rrb.Corner2D.RightTop, visible=True)
    views = [view(c, "rates", _legend_room(_floats(table[c]), entries, height), top) for c in rates]
    views += [view(c, "fractions", _FRACTION_AXIS, _legend(table, c, x, combos, labels, _FRACTION_AXIS))
              for c in fractions]
    jobs = rrb.TextDocumentView(name=f"{title} · jobs", origin="/sweep/jobs")
    root = rrb.Vertical(rrb.Grid(*views, grid_columns=columns), jobs, row_shares=[1 - share, share],
                        name=title) if views else jobs
    return rrb.Blueprint(root, rrb.TimePanel(timeline=timeline, state="collapsed", play_state="paused"),
                         rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"))


def write_sweep_recording(sweep_dir, table: pd.DataFrame | None = None) -> Path | None:
    """<sweep>/summary.rrd: each metric of the sweep's runs against each numeric swept key.

    Every numeric swept key but the seed (the repetition; the seed itself when nothing else numeric is
    swept, the job index when nothing numeric is) is an x axis: a timeline of its own (see `_x_timeline`),
    so that picking the timeline in the viewer picks the x axis. Per x key and per combination of the other
    swept keys but the seed (the hue; non-numeric keys such as gain.method are only ever hues), the mean
    over the runs at each x (a line) and the runs (points), entities
    /sweep/{rates|fractions}/{METRIC}/{X}/{HUE}/{mean|runs} logged on that x's timeline only; /sweep/x_range/{X}
    widens each timeline a little so that the first and last points are not cut by the plot's edge. A view per
    rate metric (lam, rate_plant, *_rate, exact rates) and per fraction (*_fraction, axis 0..1), colors by hue,
    and the jobs as a markdown table (/sweep/jobs) under the sweep's name and plant(s); the first x key's
    timeline is the active one. Returns its path, None with ``RERUN=off`` (nothing written)."""
    if disabled():
        return None
    sweep_dir = Path(sweep_dir)
    table = RunStore(sweep_dir).table(params=True) if table is None else table
    table = table.sort_values("job", ignore_index=True, kind="stable")
    swept = changed_params(table)
    rates, fractions = _sweep_metrics(table)
    names = [str(v) for v in table["sweep"].dropna().unique()] if "sweep" in table.columns else []
    plants = [str(v) for v in table["plant"].dropna().unique()] if "plant" in table.columns else []
    title = f"sweep {', '.join(names) or sweep_dir.name} · plant {', '.join(plants) or 'n/a'}"

    axes = {}                                 # x key -> (timeline, kind, scale, hue keys, combos, labels)
    for x in _x_keys(table, swept):
        values = _floats(table[x])
        keys = _hue_keys(table, swept, x)
        axes[x] = (*_x_timeline(x, values[np.isfinite(values)]), keys, *_hues(table, keys))
    first = next(iter(axes))
    timeline, _, _, hue_keys, combos, labels = axes[first]
    vs = f"vs {timeline}" if len(axes) == 1 else "vs the active timeline"
    blueprint = _sweep_blueprint(table, title, rates, fractions, first, timeline, vs, combos, labels,
                                 max(len(a[5]) for a in axes.values()))

    path = sweep_dir / layout.SUMMARY_RECORDING
    tmp = sweep_dir / f".{layout.SUMMARY_RECORDING}.tmp"
    with rr.RecordingStream("rdsexp", recording_id=f"sweep/{sweep_dir.name}") as rec:
        rec.save(tmp, default_blueprint=blueprint)
        rec.send_recording_name(title)
        for x, (timeline, kind, scale, _, combos, labels) in axes.items():
            for group, metrics in (("rates", rates), ("fractions", fractions)):
                for metric in metrics:
                    _sweep_series(rec, table, metric, group, x, timeline, kind, scale, combos, labels)
            values = np.unique(_floats(table[x]))
            values = values[np.isfinite(values)]
            if len(values):
                margin = 0.04 * (values[-1] - values[0]) or 0.1 * abs(values[0]) or 1.0
                ends = _x_times(kind, scale, values[[0, -1]] + np.array([-margin, margin]))
                rec.send_columns(f"/sweep/x_range/{_short(x)}", indexes=[rr.TimeColumn(timeline, **ends)],
                                 columns=rr.Scalars.columns(scalars=np.full(2, np.nan)))
        text = _jobs_markdown(table, title, swept, [a[0] for a in axes.values()], hue_keys)
        rec.log("/sweep/jobs", rr.TextDocument(text, media_type="text/markdown"), static=True)
    tmp.replace(path)
    return path
