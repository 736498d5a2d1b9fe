"""A run computed from its validated Experiment, stage by stage, into tables and a summary (no file system).

Simulated runs and data runs go through the same stage functions: identification and modeling
(`identification`), the moments' uncertainty, synthesis (`design.design_set`), the loops and the online loop
(`loops.run_loops`, `online`: simulated and judged at each look of closed_loop.paths), and the summary (`record`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial

import numpy as np
import pandas as pd

from ..config import Experiment
from ..montecarlo import LoopSummary
from .data import loops_on_model, validate_holdout
from .design import against_optimum, design_set, design_spread
from .identification import identify_and_model, identify_recorded, model_recorded, moment_uncertainty, noise_sensitivity
from .loops import METRIC_COLUMNS, Sample, loop_observer, root_seed, run_loops
from .online import analyse_online, online_loop
from .record import data_summary, run_summary
from .results import Identified
from .stage import MemorySink, Stages
from .tables import gains_table, members_table, model_table, path_table, trajectory_table, with_gains

TABLES = ("trajectories", "identification", "paths", "model", "gains", "metrics", "exact")
STREAMED = ("trajectories", "members")        # written chunk by chunk through a sink


@dataclass
class Outcome:
    """What a run computed: tables by name (the streamed ones only without a sink), a flat summary
    of key numbers, seconds per stage, and the rows the recording shows (identification and the
    first tracking.recorded_paths paths of each loop)."""

    tables: dict[str, pd.DataFrame]
    summary: dict
    timings: dict = field(default_factory=dict)
    recorded: pd.DataFrame | None = None
    recorded_members: pd.DataFrame | None = None
    squares: dict[str, np.ndarray] = field(default_factory=dict)   # loop -> ||q_k||^2 (K+1, P), every path


def run_experiment(exp: Experiment, sink=None, cache=None) -> Outcome:
    """Compute every stage of the experiment; numerical failures become statuses in the tables.

    The large tables (STREAMED: trajectories, members) go to `sink.append(name, rows)` chunk by
    chunk (store.files.ParquetSink writes them as they come); without a sink they are collected and
    returned in Outcome.tables with the others.

    cache: a stage cache (store.stages.StageCache: a store's, or this process's memory only) or None
    (compute everything, as `verify` does). Every stage runs through `Stages`: a cached stage whose
    inputs equal those of a stored entry is loaded from it instead of computed, and a computed one is
    stored: identification with modeling (keyed by the plant, model, EnKF, identification settings,
    initial state and seed), each design (model, moments, method, options) and the open loop (what
    `simulate` reads: plant, the loop's observer with the moments it draws xi from, disturbance,
    initial state, seed, chunks of paths; not the gain). Tables and summary are the same either way.
    Tracking level full (every loop's members) keeps nothing in the store, only in this process."""
    if exp.data is not None:
        return run_on_data(exp, sink, cache)
    if cache is not None and cache.dir is not None and exp.tracking.level == "full":
        cache = type(cache).in_process()
    stages, keep = Stages(cache), exp.tracking.level == "full"
    with stages.timed("identification"):      # with modeling (iterated identification runs the EnKF again)
        seed = root_seed(exp, "identification")
        identified, _ = stages.cached(
            "identification", partial(identify_and_model, exp, stages, seed), result=Identified.__name__,
            plant=exp.plant, model=exp.model, filter=exp.filter, identification=exp.identification, q0=exp.q0,
            estimate=exp.loop.estimate, seed=seed, keep_members=keep)
    uncertainty = moment_uncertainty(exp, identified)
    with stages.timed("noise_sensitivity"):
        sensitivity = noise_sensitivity(exp, identified, uncertainty,
                                        lambda scaled: identify_and_model(scaled, Stages(cache=None), seed))
    with stages.timed("synthesis"):
        designs = design_set(exp, stages, identified.moments, uncertainty, identified.feedback)
        observer = loop_observer(exp, designs.moments)

    # closed and open loop in chunks of paths: rows go to the sink chunk by chunk, the metrics keep a
    # LoopSummary per loop, the recording a bounded sample of paths (montecarlo.py)
    sink, sample = MemorySink() if sink is None else sink, Sample()
    if keep:
        sample.members.append(members_table("identification", identified.trajectories))
        sink.append("members", sample.members[0])
    F = designs.gain
    if F is None:                              # no gain to simulate: the table's columns, no rows
        rows = trajectory_table("closed_loop", None, exp=exp)
        if exp.controller.kind == "online":    # and the gain columns the online loop's rows bring
            rows = with_gains(rows, np.zeros((0, exp.model.m, exp.model.n)))
        sink.append("trajectories", rows)
    online_paths = partial(online_loop, exp, stages, sink, sample) if exp.controller.kind == "online" else None
    judged, online = run_loops(exp, stages, F, observer, sink, sample, online=online_paths)
    loops = judged.loops

    with stages.timed("loop_tables"):
        tables = {"identification": trajectory_table("identification", identified.trajectories),
                  "paths": path_table({"identification": LoopSummary.of(identified.trajectories, exp), **loops}),
                  "model": model_table(exp, identified.moments), "gains": gains_table(exp, designs),
                  "metrics": judged.metrics, "exact": judged.exact}
        if isinstance(sink, MemorySink):
            tables |= sink.tables()
    if online is not None:
        online = analyse_online(exp, stages, online, tables["paths"], F, judged.window.k)
        add_online_tables(tables, online)
    with stages.timed("against_optimum"):
        optimum = against_optimum(exp, stages, designs)
    summary = run_summary(exp, identified, uncertainty, designs, judged, online, sensitivity, optimum)
    stages.timings["synthesis_by_method"] = {f"{source}/{method}": round(res.seconds, 4)
                                             for (source, method), (_, res) in designs.designs.items()}
    return Outcome(tables=tables, summary=summary, timings=stages.timings,
                   recorded=pd.concat([tables["identification"], *sample.rows], ignore_index=True),
                   recorded_members=pd.concat(sample.members, ignore_index=True) if keep else None,
                   squares={name: loop.sq for name, loop in loops.items()})


def add_online_tables(tables: dict, online) -> None:
    """The online loop's `controller` table, its per-path columns in `paths` and its metrics as columns of its
    `metrics` row (NaN on the other loops' rows)."""
    tables["controller"] = online.controller
    tables["paths"] = tables["paths"].merge(online.paths, on=["experiment", "path"], how="left")
    metrics = tables["metrics"]
    for name, value in online.metrics.items():
        metrics[name] = np.where(metrics["experiment"] == "online", value, np.nan)


def run_on_data(exp: Experiment, sink=None, cache=None) -> Outcome:
    """A data run (exp.data): identification on the recorded paths (all but the held-out ones), the moments
    over the window with their uncertainty (a bootstrap over the recorded paths, or over blocks of the window
    for one path), the loop's gain and gain.designs on them, each with its exact rate on the identified model
    and its spread over the moments' draws. There is no plant: no loop is simulated on one and no number claims
    one. Iterated identification (identification.xi_model: iterated) re-filters the same recorded data with
    each pass's prior: the record does not change between passes (a simulated open-loop identification's would
    not either; one under feedback would, and a data run cannot reproduce that). cache: as `run_experiment`'s
    (the designs and loops on the model only: the recorded identification is the data file's own)."""
    stages, keep = Stages(cache), exp.tracking.level == "full"
    seed = root_seed(exp, "identification")
    with stages.timed("identification"):
        ident = identify_recorded(exp, exp.data.identification, seed)
    identified = model_recorded(exp, stages, ident, seed)
    dist, uncertainty = identified.moments, moment_uncertainty(exp, identified)
    with stages.timed("noise_sensitivity"):
        remodel = lambda scaled: model_recorded(scaled, Stages(cache=None),
                                                identify_recorded(scaled, scaled.data.identification, seed), seed)
        sensitivity = noise_sensitivity(exp, identified, uncertainty, remodel)
    with stages.timed("synthesis"):
        designs = design_set(exp, stages, dist, uncertainty, identified.feedback)
    with stages.timed("metrics"):
        spread = design_spread(exp, designs, uncertainty)
        tables = {"identification": trajectory_table("identification", identified.trajectories),
                  "paths": path_table({"identification": LoopSummary.of(identified.trajectories, exp)}),
                  "model": model_table(exp, dist), "gains": gains_table(exp, designs, spread),
                  "metrics": pd.DataFrame(columns=list(METRIC_COLUMNS)),
                  "exact": pd.DataFrame({"experiment": pd.Series(dtype=str), "k": pd.Series(dtype=np.int64),
                                         "rms": pd.Series(dtype=float)})}
    validation = None
    if exp.data.holdout_data is not None and dist is not None:
        with stages.timed("validation"):
            validation = validate_holdout(exp, dist)
            tables["validation"] = validation.table
    sink, sample, on_model = MemorySink() if sink is None else sink, Sample(), None
    if exp.data.loops and designs.gain is not None and dist is not None:
        with stages.timed("loops_on_model"):
            on_model = loops_on_model(exp, stages, dist, designs, tables, sink, sample)
    else:
        sink.append("trajectories", trajectory_table("closed_loop", None, exp=exp))
    if isinstance(sink, MemorySink):
        tables |= sink.tables()
    summary = data_summary(exp, identified, uncertainty, designs, spread, validation, on_model, sensitivity)
    return Outcome(tables=tables, summary=summary, timings=stages.timings,
                   recorded=pd.concat([tables["identification"], *sample.rows], ignore_index=True),
                   recorded_members=members_table("identification", identified.trajectories) if keep else None,
                   squares={})
