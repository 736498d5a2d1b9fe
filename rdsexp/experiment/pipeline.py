"""The stage pipeline: a validated Experiment computed into tables, without touching the file system.

Stages (docs/design.md): identification -> modeling -> synthesis -> closed loop (and open loop) ->
noise floor (the closed loop at rest) -> metrics (rate window, verdicts). Seeds: the identification
run uses SeedSequence(seed, spawn_key=(0,)), the closed and open loops SeedSequence(seed,
spawn_key=(1,)) (the same plant samples, as in the paper's Figs. decay_proposed and decay_open), the
loop at rest (2,); inside each, path j has its own plant and EnKF streams.
"""
from __future__ import annotations

import dataclasses
import logging
import sys
import time
from contextlib import closing, contextmanager
from dataclasses import dataclass, field
from functools import partial

import numpy as np
import pandas as pd
from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from ..errors import ConfigError, StageError, WriteError, one_line
from ..numerics import observer_loop
from ..numerics.analysis import empirical_rate_sq, exact_costs, ms_rate, rms_band, second_moments
from ..numerics.distributions import ensemble_crps, expected_crps, interval_hits
from ..numerics.enkf import EnKF, output_delay, sqrtm_psd, truth_map, xi_ends
from ..numerics.modeling import model_distribution, moment_draws, nominal_gain, path_moment_draws
from ..numerics.online import OnlineController, moment_factors, rates, two_point_moments
from ..numerics.simulation import Trajectories, bytes_per_path, path_generators, simulate
from ..numerics.synthesis import SynthesisResult, synthesize
from ..numerics.systems import MomentModel
from ..numerics.verdict import FAILURES, Floor, judge_loop, paired_losses, place_window, rate_interval, window_start
from .config import Experiment
from .montecarlo import MEMORY_BUDGET, LoopSummary, chunk_starts, run_chunks

log = logging.getLogger("rdsexp")
# the online loop shares the closed loop's seeds: the same plant samples and EnKF noise, a paired comparison
SPAWN_KEYS = {"identification": (0,), "closed_loop": (1,), "open_loop": (1,), "online": (1,), "noise_floor": (2,)}
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


@contextmanager
def timed(timings: dict, stage: str):
    """Time the block into timings[stage] and log the stage with its seconds (rdsexp.log); an
    unexpected exception inside becomes a StageError naming the innermost stage."""
    start = time.perf_counter()
    log.info("%s ...", stage)
    try:
        yield
    except (StageError, WriteError, ConfigError):   # named by an inner stage, or not a stage's failure
        raise
    except Exception as err:
        raise StageError(stage, err) from err
    timings[stage] = round(time.perf_counter() - start, 4)
    log.info("%s done in %.3f s", stage, timings[stage])


class Stages:
    """The one wrapper every stage of a run goes through (docs/design.md: the two levels of reuse).

    `timed(name)`: the stage's seconds into `timings[name]` and rdsexp.log; an unexpected exception
    inside becomes a StageError naming the innermost stage. `cached(name, compute, **inputs)`: a
    stage computed from exactly `inputs` (numerics objects, arrays, seeds: their digest is the key)
    is taken from the stage cache when it holds that key (this process's memory, then the store's
    entries), else computed and stored there; `streamed` is the same for a stage whose value is a
    sequence of parts (a loop's chunks), stored part by part as they are computed.

    cache: a store.stages.StageCache (a store's, or `StageCache.in_process()`), or None: every stage
    is computed (`rdsexp-runs verify`)."""

    def __init__(self, cache=None):
        self.cache = cache
        self.timings: dict = {}

    def timed(self, name: str):
        return timed(self.timings, name)

    def cached(self, name: str, compute, *, label: str | None = None, **inputs) -> tuple[object, bool]:
        """(the stage's value, whether it was reused rather than computed in this run)."""
        if self.cache is None:
            return compute(), False
        key = self.cache.key(name, **inputs)
        value = self.cache.load(name, key, label or name)
        if value is not None:
            return value, True
        value = compute()
        self.cache.save(name, key, value)
        return value, False

    def streamed(self, name: str, compute, *, label: str | None = None, **inputs):
        """(an iterator of the stage's parts, whether they are reused); computed parts are stored as they
        are consumed, the entry committed when the last one is, dropped if the consumer stops early."""
        if self.cache is None:
            return compute(), False
        key = self.cache.key(name, **inputs)
        stored = self.cache.load_parts(name, key, label or name)
        if stored is not None:
            return stored, True
        return self._storing(self.cache.writer(name, key), compute()), False

    @staticmethod
    def _storing(writer, parts):
        try:
            for part in parts:
                writer.add(part)
                yield part
        except BaseException:         # an error, Ctrl-C or a consumer that closed the iterator
            writer.abort()
            raise
        writer.commit()


@contextmanager
def console_to_tqdm():
    """Console log records through tqdm.write (they do not break a progress bar), at the console
    handler's own level: tqdm's handler takes every level, which would put INFO lines on the terminal."""
    console = [h for h in logging.root.handlers
               if isinstance(h, logging.StreamHandler) and not isinstance(h, logging.FileHandler)]
    before = list(logging.root.handlers)
    with logging_redirect_tqdm():
        for handler in logging.root.handlers:
            if handler not in before and console:
                handler.setLevel(console[0].level)
        yield


def _progress(desc: str, total: int):
    """A tqdm bar (silent when not on a terminal) and its per-step callback."""
    bar = tqdm(total=total, desc=desc, disable=None, leave=False, file=sys.stderr)
    return bar, lambda k: bar.update(1)


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
    stages, summary = Stages(cache), {}
    timings = stages.timings
    root = lambda stage: np.random.SeedSequence(exp.seed, spawn_key=SPAWN_KEYS[stage])
    sim = exp.simulation()
    keep = exp.tracking.level == "full"

    with stages.timed("identification"):      # with modeling (iterated identification runs the EnKF again)
        identified, _ = stages.cached(
            "identification", partial(identify_and_model, exp, stages, root("identification"), sim, keep),
            plant=exp.plant, model=exp.model, filter=exp.filter, identification=exp.identification,
            simulation=sim, seed=root("identification"), keep_members=keep)
    ident, dist = identified["ident"], identified["dist"]
    summary.update(identified["summary"])
    draws = moment_uncertainty(exp, ident, summary) if dist is not None else None
    with stages.timed("synthesis"):
        # the loop's method and the comparison designs (gain.designs) on the identified moments (the
        # selected one with its configured options) and, when the config gives them, on the moments a
        # paper reports; a design that cannot be applied or fails is a status in the gains table, never
        # the end of the run
        designs = {}
        for source, moments in (("identified", dist), ("reported", exp.reported)):
            for method in exp.design.methods if moments is not None else ():
                designs[source, method] = (moments, configured_design(stages, exp, moments, method, source))
        selected = (exp.design.source, exp.design.method)
        if exp.design.source == "fixed":      # a given F (e.g. a paper's own gain): no design, its exact rate
            selected, moments = ("fixed", "fixed"), dist if dist is not None else exp.reported
            rate = ms_rate(exp.model, moments, exp.design.F) if moments is not None else np.nan
            nbar = int(exp.model.Gbar(moments).shape[0]) if moments is not None else 0
            designs[selected] = (moments, SynthesisResult("fixed", exp.design.F, rate, "fixed", nbar=nbar))
        chosen = designs.get(selected, (None, None))[1]
        fallback = exp.design.fallback
        if chosen is not None and chosen.status == "not_applicable" and fallback not in (None, selected[1]):
            # the loop's method cannot run on this system (e.g. an LMI design above gain.lmi_max_n): the
            # loop uses gain.fallback, designed on the same moments, and the summary says so
            moments = designs[selected][0]
            if (selected[0], fallback) not in designs:
                designs[selected[0], fallback] = (moments, configured_design(stages, exp, moments, fallback,
                                                                             selected[0]))
            summary["gain_fallback"] = {"method": fallback, "instead_of": selected[1],
                                        "because": chosen.info.get("reason", chosen.status)}
            selected = (selected[0], fallback)
            chosen = designs[selected][1]
        if selected[0] == "identified" and draws is not None and chosen is not None and chosen.F is not None:
            kept = safer_gain(exp, dist, chosen, draws, summary)
            if kept is not None:                # the identification's own gain: the loop keeps it
                selected = ("identified", kept.method)
                designs[selected] = (dist, kept)
                chosen = kept
        observer = loop_observer(exp, designs.get(selected, (None, None))[0])

    # closed and open loop in chunks of paths: rows go to the sink chunk by chunk, the metrics keep a
    # LoopSummary per loop, the recording a bounded sample of paths (montecarlo.py)
    sink = MemorySink() if sink is None else sink
    loops, sample, sample_members = {}, [], []
    if keep:
        sample_members.append(members_table("identification", ident))
        sink.append("members", sample_members[0])
    if chosen is not None and chosen.F is not None:
        settings = dict(d=exp.loop.disturbance, filter_sees_d=exp.loop.filter_sees_disturbance, **sim)
        runs = [("closed_loop", chosen.F)] + ([("open_loop", None)] if exp.loop.open_loop else [])
        for name, F in runs:
            with stages.timed(name):
                bar, _ = _progress(name.replace("_", " "), exp.loop.paths * exp.loop.disturbance.shape[0])
                parts = []
                chunks = loop_chunks(exp, name, dict(settings, F=F, seed=root(name)), observer, keep, bar.update,
                                     stages if name in CACHED_LOOPS else Stages(cache=None))
                with bar, console_to_tqdm(), closing(chunks):
                    for first, tr in chunks:
                        rows = trajectory_table(name, tr, first, d_columns=carries_d(exp))
                        if exp.controller.kind == "online":     # the gain in use, as in the online rows
                            rows = with_gains(rows, np.zeros((exp.model.m, exp.model.n)) if F is None else F)
                        parts.append(stream_chunk(exp, name, tr, first, rows, sink, sample, sample_members))
                        tr = rows = None                    # free the chunk before the next
                loops[name] = LoopSummary.concat(parts)
    if not loops:                              # no gain to simulate: the table's columns, no rows
        rows = trajectory_table("closed_loop", None, exp=exp)
        if exp.controller.kind == "online":    # and the gain columns the online loop's rows bring
            rows = with_gains(rows, np.zeros((0, exp.model.m, exp.model.n)))
        sink.append("trajectories", rows)
    floor = None
    if "closed_loop" in loops and exp.loop.floor_paths > 0:
        with stages.timed("noise_floor"):
            floor = noise_floor(exp, observer, chosen.F, root("noise_floor"), sim)
    floors = {"closed_loop": floor}

    online = None
    if exp.controller.kind == "online":
        with stages.timed("online"):
            online, summary["online_initial"] = online_loop(exp, root("online"), keep, sim, sink, sample,
                                                            sample_members)
            loops["online"] = online[0]
        # the fixed-gain loop's floor is the level the EnKF's noise keeps a decayed loop at, where it has one;
        # that it grows or fails at rest is a claim about that loop, not the online one (whose own run at rest
        # is a learning transient, not a floor: its first gains are designed on models of no data)
        floors["online"] = floor if floor is not None and floor.holds else None

    with stages.timed("metrics"):
        exact = exact_table(exp, chosen)
        window = rate_window(exp, exact, floor, loops.get("closed_loop"))
        tables = {
            "identification": trajectory_table("identification", ident),
            "paths": path_table({"identification": LoopSummary.of(ident, exp), **loops}),
            "model": model_table(exp, dist),
            "gains": gains_table(exp, designs, selected),
            "metrics": metrics_table(exp, loops, window, floors, exact),
            "exact": exact,
        }
        summary.update(rate_window=list(window.k), rate_window_source=window.source if window.placed else "none",
                       noise_floor=np.nan if floor is None else floor.rms,
                       loop={"estimate": exp.loop.estimate, "observer_xi": exp.loop.observer_xi,
                             "filter_sees_disturbance": exp.loop.filter_sees_disturbance})
        if isinstance(sink, MemorySink):
            tables |= sink.tables()
    if online is not None:
        add_online_tables(exp, stages, tables, online, chosen, summary)
    summary.update(_summary(exp, dist, chosen, tables))
    if "gain_fallback" in summary:                      # the method whose gain the loop uses
        summary["gain_method"] = summary["gain_fallback"]["method"]
    if (summary.get("gain_choice") or {}).get("kept") == "identification":
        summary["gain_method"] = KEPT_GAIN
    timings["synthesis_by_method"] = {f"{source}/{method}": round(res.seconds, 4)
                                      for (source, method), (_, res) in designs.items()}
    recorded = pd.concat([tables["identification"], *sample], ignore_index=True)
    recorded_members = pd.concat(sample_members, ignore_index=True) if keep else None
    return Outcome(tables=tables, summary=summary, timings=timings, recorded=recorded,
                   recorded_members=recorded_members, squares={name: loop.sq for name, loop in loops.items()})


def identify_and_model(exp: Experiment, stages: Stages, seed, sim: dict, keep: bool) -> dict:
    """The identification run(s) and the moments they model: {"ident": the Trajectories the moments
    come from, "dist": MomentModel or None, "failure": why not, "summary": the decisions that go into
    the run summary (identification_feedback, identification_passes, modeling_status and _covariance)},
    the identification stage's value (the stage cache stores it whole)."""
    summary = {}
    F_id, info = identification_feedback(exp)
    # the identification input is added on top of the feedback; the EnKF is told the applied input
    total = exp.identification.covariance == "total"
    identify = lambda F, enkf=exp.filter.enkf: simulate(
        exp.plant, enkf, F=F, d=exp.identification.input, paths=1, seed=seed,
        filter_sees_d=True, keep_members=keep, keep_xi_cov=total, **sim)
    ident = identify(F_id)
    if info.get("used") == "open_loop" and ident.failure[0] in ("diverged", "filter_diverged"):
        # auto chose the open loop on the guess, which knows no spread of xi (the spread only raises
        # the mean-square rate): the plant grew until it, or first the EnKF's estimate of it, diverged
        # (random plants: 3 of 200 open-loop mean-square unstable plants stable at their mean),
        # so identify again under nominal feedback
        F_id, retry = identification_feedback(exp, force_nominal=True)
        if F_id is not None:
            info = retry | {"open_loop_diverged_at": int(ident.failed_at[0]),
                            "open_loop_failure": str(ident.failure[0])}
            ident = identify(F_id)
    summary["identification_feedback"] = info
    ident, dist, failure = model_moments(exp, stages, ident, lambda enkf: identify(F_id, enkf), sim, summary)
    return {"ident": ident, "dist": dist, "failure": failure, "summary": summary}


def model_moments(exp: Experiment, stages: Stages, ident: Trajectories, identify, sim: dict, summary: dict):
    """The modeling stage: the moments of xi from the identification's estimates (`identified_moments`), with
    identification.xi_model: iterated the passes that filter again with each pass's prior (`identify(enkf)`);
    (the Trajectories they come from, MomentModel or None, why not). Its decisions go into `summary`."""
    with stages.timed("modeling"):
        dist, failure = identified_moments(exp, ident)
        if exp.identification.xi_model == "iterated" and exp.model.p:     # (nothing to iterate without xi)
            ident, dist, failure, summary["identification_passes"] = iterate_identification(
                exp, identify, ident, dist, failure, sim["psi0"])
        passes = summary.get("identification_passes") or {}
        unsettled = dist is not None and passes.get("passes") and not passes.get("converged")
        summary["modeling_status"] = failure or ("unsettled" if unsettled else "ok")
        if dist is not None:
            summary["modeling_covariance"] = exp.identification.covariance
    return ident, dist, failure


CACHED_LOOPS = ("open_loop",)      # loops the stage cache keeps: the open loop does not depend on the gain, so
                                   # every design of a seed shares it; a closed loop is its run's own


def loop_chunks(exp: Experiment, name: str, settings: dict, observer, keep: bool, progress, stages: Stages):
    """(first path, Trajectories) of the loop's chunks in path order: a stage keyed by exactly what
    `simulate` reads (the plant, the observer, the settings with gain, disturbance, initial state and
    seed, and the chunks of paths), simulated (`run_chunks`) or replayed from the stage cache."""
    simulated = lambda: ({"first": first, "trajectories": tr} for first, tr, _ in run_chunks(
        exp, settings, keep_members=keep, enkf=observer, workers=exp.loop.workers, progress=progress))
    parts, reused = stages.streamed(name, simulated, plant=exp.plant, observer=observer, settings=settings,
                                    chunks=chunk_starts(exp, keep_members=keep), keep_members=keep)
    steps = exp.loop.disturbance.shape[0]
    with closing(parts):
        for part in parts:
            if reused:
                progress(part["trajectories"].q.shape[1] * steps)
            yield part["first"], part["trajectories"]


def stream_chunk(exp: Experiment, name: str, tr: Trajectories, first: int, rows: pd.DataFrame, sink,
                 sample: list, sample_members: list) -> LoopSummary:
    """One chunk of a loop out of memory: its trajectory rows (and, tracking full, its members) to the
    sink, the recorded paths' rows to `sample`/`sample_members`; returns what the metrics keep."""
    recorded = exp.tracking.recorded_paths
    sink.append("trajectories", rows)
    sample.append(rows[rows["path"] < recorded])
    if exp.tracking.level == "full":
        members = members_table(name, tr, first)
        sink.append("members", members)
        sample_members.append(members[members["path"] < recorded])
    return LoopSummary.of(tr, exp)


class MemorySink:
    """Collects the streamed tables' rows in memory; `tables()` gives them whole (tests, tracking off)."""

    def __init__(self):
        self.parts: dict[str, list[pd.DataFrame]] = {}

    def append(self, name: str, rows: pd.DataFrame) -> None:
        self.parts.setdefault(name, []).append(rows)

    def tables(self) -> dict[str, pd.DataFrame]:
        return {name: pd.concat(parts, ignore_index=True) for name, parts in self.parts.items()}


def online_loop(exp: Experiment, seed, keep: bool, sim: dict, sink, sample: list, sample_members: list):
    """The online (learning-type) closed loop: per-path gains re-designed from the path's own xi_{k|k}.

    In chunks of paths, and worker processes, like the other loops (`run_chunks`; one controller per
    chunk), rows streamed to the sink with the gain in use (F[i,j]). Returns
    ((LoopSummary, [(first_path, controller)]), info for the summary)."""
    m, n = exp.model.m, exp.model.n
    enkf = online_observer(exp)
    info = {"initial": exp.controller.initial if isinstance(exp.controller.initial, str) else "given",
            # the start before a path's first model, as the loop's EnKF has it (static_mean with observer = model)
            "start": "static_mean" if enkf.static_mean else "random_walk",
            "lag": exp.controller.online.lag, "output_delay": output_delay(exp.model).tolist(),
            "start_scale": enkf.start_scale}
    if exp.controller.online.probe > 0:              # the known excitation on u: amplitude, last step (None: never)
        info["probe"] = [exp.controller.online.probe, exp.controller.online.probe_until]
    F0 = exp.controller.initial if not isinstance(exp.controller.initial, str) else np.zeros((m, n))
    if isinstance(exp.controller.initial, str) and exp.controller.initial == "nominal":
        res, law = online_nominal(exp, enkf)
        info |= {"method": res.method, "status": res.status, "nominal_law": law, "rate_on_law": res.lam}
        if res.F is not None and np.all(np.isfinite(res.F)) and res.lam < 1:
            F0 = res.F
        else:
            info["used"] = "zero (no stabilizing nominal gain)"
    K = exp.loop.disturbance.shape[0] - 1
    parts, controllers = [], []
    bar, _ = _progress("online", exp.loop.paths * (K + 1))
    settings = dict(F=F0, d=exp.loop.disturbance, seed=seed, filter_sees_d=exp.loop.filter_sees_disturbance, **sim)
    # the prior guess, as the nominal gain sees it: a thin window acts only where it agrees (OnlineController)
    A_guess, B_guess, _, _ = exp.plant.at(exp.identification.xi_guess)
    # a component the EnKF draws from its two-point law is modeled with that law's variance too
    make = partial(OnlineController, exp.model, exp.controller.online, F0, horizon=K, at_guess=(A_guess, B_guess),
                   two_point=enkf.two_point)
    with bar, console_to_tqdm():
        for first, tr, controller in run_chunks(exp, settings, keep_members=keep, workers=exp.loop.workers,
                                                progress=bar.update, controller=make, enkf=enkf):
            count = tr.q.shape[1]
            history = controller.gain_history()
            in_use = np.stack([history[j][tr.gain_index[:, j]] for j in range(count)])     # (P, K+1, m, n)
            rows = with_gains(trajectory_table("online", tr, first, d_columns=carries_d(exp)),
                              in_use.reshape(count * (K + 1), m, n))
            parts.append(stream_chunk(exp, "online", tr, first, rows, sink, sample, sample_members))
            controllers.append((first, controller))
    return (LoopSummary.concat(parts), controllers), info


def with_gains(rows: pd.DataFrame, F: np.ndarray) -> pd.DataFrame:
    """rows with the gain in use as columns F[i,j] (u_i = sum_j F[i,j] x_j).

    F: (len(rows), m, n), one gain per row, or (m, n), the same gain on every row."""
    F = np.asarray(F, dtype=float)
    F = F if F.ndim == 3 else np.broadcast_to(F, (len(rows), *F.shape))
    return rows.assign(**gain_columns(F))


def gain_columns(F: np.ndarray) -> dict[str, np.ndarray]:
    """{"F[i,j]": F[:, i, j]} of gains F (rows, m, n), the gains table's naming."""
    return {f"F[{i},{j}]": F[:, i, j] for i in range(F.shape[1]) for j in range(F.shape[2])}


def add_online_tables(exp: Experiment, stages: Stages, tables: dict, online, chosen, summary: dict) -> None:
    """The `controller` table (every decision), per-path and summary metrics of the online loop
    against the offline design of the same seed and the optimum on the true plant.

    online: (LoopSummary, [(first_path, OnlineController)]) from `online_loop`."""
    loop, controllers = online
    P, p, m, n = loop.failed_at.size, exp.model.p, exp.model.m, exp.model.n
    Abar, Bbar = exp.plant.moment_factors(None)
    frames = []
    for offset, controller in controllers:
        d, count = controller.decisions(), controller.P
        with np.errstate(all="ignore"):
            rate_plant = rates(Abar, Bbar, np.nan_to_num(d.F, nan=np.inf)) if len(d.k) else np.zeros(0)
            rate_plant[~np.all(np.isfinite(d.F), axis=(1, 2))] = np.nan
            initial_plant = rates(Abar, Bbar, controller.F0)
        rows = {"path": offset + np.concatenate([np.arange(count), d.path]),
                "k": np.concatenate([np.full(count, -1), d.k]),
                "adopted": np.concatenate([np.ones(count, bool), d.adopted]),
                "reason": np.concatenate([np.full(count, "initial", dtype=object), d.reason]),
                "rate_model": np.concatenate([np.full(count, np.nan), d.rate_model]),
                "rate_current": np.concatenate([np.full(count, np.nan), d.rate_current]),
                "rate_worst": np.concatenate([np.full(count, np.nan), d.rate_worst]),
                "rate_current_worst": np.concatenate([np.full(count, np.nan), d.rate_current_worst]),
                "rate_current_best": np.concatenate([np.full(count, np.nan), d.rate_current_best]),
                "rate_current_guess": np.concatenate([np.full(count, np.nan), d.rate_current_guess]),
                "estimates": np.concatenate([np.zeros(count, int), d.estimates]),
                "rate_plant": np.concatenate([initial_plant, rate_plant])}
        mean = np.concatenate([np.full((count, p), np.nan), d.mean])
        rows |= {f"mean[{i}]": mean[:, i] for i in range(p)}
        rows |= {f"cov[{i},{j}]": np.concatenate([np.full(count, np.nan), d.cov[:, i, j]])
                 for i in range(p) for j in range(p)}
        rows |= gain_columns(np.concatenate([controller.F0, d.F]).reshape(-1, m, n))
        frames.append(pd.DataFrame(rows))   # the initial gains (k = -1: in use from k = 0), then in order of k
    table = pd.concat(frames, ignore_index=True)
    # gain index: the initial gain is 0, then a path's adopted gains in order (-1: not adopted)
    table.insert(4, "gain_index", np.where(table["adopted"], table.groupby("path")["adopted"].cumsum() - 1, -1))
    table = table.sort_values(["path", "k"], kind="stable", ignore_index=True)
    tables["controller"] = table
    adopted_count = int((table["adopted"] & (table["k"] >= 0)).sum())

    # per path: the first step at which it holds a gain stable in mean square on the true plant
    # (-1: never) and the exact true rate of its final gain
    adopted = table[table["adopted"]]
    final = adopted.groupby("path")["rate_plant"].last().reindex(range(P)).to_numpy()
    stable = adopted[adopted["rate_plant"] < 1].groupby("path")["k"].min().reindex(range(P))
    first = np.where(stable.isna(), -1, stable.fillna(0).to_numpy() + 1).astype(int)
    paths = tables["paths"]
    extra = pd.DataFrame({"experiment": "online", "path": np.arange(P), "first_stable_k": first,
                          "final_rate_plant": final})
    tables["paths"] = paths.merge(extra, on=["experiment", "path"], how="left")
    # the optimal rate on the true plant: the better of Theorem 2's bisection and policy iteration
    # (policy iteration from F = 0 can stall on an open-loop unstable plant)
    truth = exp.plant.check_distribution(None)
    optimum = min((design(stages, exp.plant, truth, method, {}, exp.design.lmi_max_n, f"synthesis/plant/{method}")
                   for method in ("proposed", "policy_iteration")),
                  key=lambda res: res.lam if np.isfinite(res.lam) else np.inf)
    offline = safe_rate(exp.plant, None, chosen.F) if chosen is not None and chosen.F is not None else np.nan
    window = tuple(summary["rate_window"])          # as the metrics stage resolved it
    q = np.nanpercentile(final, [10, 50, 90]) if np.isfinite(final).any() else [np.nan] * 3
    # paths lost by one loop alone (the two loops share each path's plant samples) and whether online loses
    # more than chance explains: the exact paired test (rare losses make two bare counts differ by chance)
    offline_paths = paths[paths["experiment"] == "closed_loop"].sort_values("path")
    lost = (paired_losses(loop.failed_at >= 0, offline_paths["failed_at"].to_numpy() >= 0)
            if len(offline_paths) == P else (np.nan,) * 3)
    # the gains the lost paths held (each acted from the step after its adoption, before the loss): all of them
    # mean-square stable on the true plant says that what grew is the loop through the EnKF's estimate, not the
    # ideal loop of any one gain (switching between stable gains is not covered by their rates)
    failed_at = loop.failed_at[adopted["path"].to_numpy()]
    held = adopted[(failed_at >= 0) & (adopted["k"].to_numpy() + 1 < failed_at)]
    worst_held = held["rate_plant"].fillna(np.inf).groupby(held["path"]).max()    # a NaN rate counts as unstable
    lost_held = {"lost_held_unstable": float((~(worst_held < 1)).sum()) if len(worst_held) else np.nan,
                 "lost_held_rate_max": float(worst_held.max()) if len(worst_held) else np.nan}
    online_metrics = {"final_rate_plant_q10": q[0], "final_rate_plant_median": q[1], "final_rate_plant_q90": q[2],
                      "final_stable_fraction": float(np.mean(final < 1)),
                      "first_stable_k_median": float(np.median(first[first >= 0])) if (first >= 0).any() else np.nan,
                      "never_stable_fraction": float(np.mean(first < 0)),
                      "adoptions_per_path": adopted_count / P,
                      # the k-window rate over the paths that did not diverge (the `rate` column is NaN
                      # as soon as one path diverged)
                      "rate_not_diverged": empirical_rate_sq(*(loop.sq[k, loop.failed_at < 0] for k in window),
                                                             window[1] - window[0])[0]
                      if (loop.failed_at < 0).any() else np.nan,
                      "offline_rate_plant": offline, "optimal_rate_plant": optimum.lam,
                      "lost_online_only": lost[0], "lost_offline_only": lost[1], "lost_more_p": lost[2], **lost_held}
    metrics = tables["metrics"]
    for name, value in online_metrics.items():
        metrics[name] = np.where(metrics["experiment"] == "online", value, np.nan)
    summary["online"] = {k: (None if not np.isfinite(v) else float(v)) for k, v in online_metrics.items()}


LMI_METHODS = ("proposed", "nominal_lmi", "robust_box")      # designs that solve semidefinite programs


def design(stages: Stages, model, moments: MomentModel, method: str, options: dict, lmi_max_n: int | None,
           label: str) -> SynthesisResult:
    """The design stage: `method` with `options` on `moments`, from the stage cache when a design with the
    same model bases, moments, method and options is there (the jobs of a sweep that share them design
    once; a reused design reports seconds 0: no time spent in this run), else `safe_synthesize`.
    Synthesis is deterministic, so the tables are the same. label: the design in run.json's stage_keys."""
    res, reused = stages.cached("synthesis", partial(safe_synthesize, model, moments, method, options, lmi_max_n),
                                label=label, A=model.A, B=model.B, C=model.C, D=model.D, mean=moments.mean,
                                cov=moments.cov, method=method, options=options, lmi_max_n=lmi_max_n)
    if reused:
        if res.status.startswith("failed"):
            log.warning("design %s %s", method, res.status)
        res.seconds = 0.0
    return res


def configured_design(stages: Stages, exp: Experiment, moments: MomentModel, method: str,
                      source: str) -> SynthesisResult:
    """`design` of `method` with its configured options on the moments from `source` (identified | reported)."""
    return design(stages, exp.model, moments, method, exp.design.options_by_method[method], exp.design.lmi_max_n,
                  f"synthesis/{source}/{method}")


def safe_synthesize(model, moments, method: str, options: dict, lmi_max_n: int | None = None) -> SynthesisResult:
    """`synthesize`, with every way a design can fail on this system as a status, never an exception.

    not_applicable: pole placement without poles in the config, or an LMI design (LMI_METHODS) on a
    system with more than `lmi_max_n` states (config gain.lmi_max_n: its SDPs would run for hours, the
    SDP-free designs do not). failed: <reason>: the method raised
    (e.g. a Riccati equation without a solution) or returned a gain that is not finite."""
    if method == "pole_placement" and options.get("poles") is None:
        return SynthesisResult(method, None, float("nan"), "not_applicable", nbar=0,
                               info={"reason": "no poles in the config (plant.poles or gain.options.poles)"})
    if method in LMI_METHODS and lmi_max_n is not None and model.n > lmi_max_n:
        return SynthesisResult(method, None, float("nan"), "not_applicable", nbar=0,
                               info={"reason": f"n = {model.n} > gain.lmi_max_n = {lmi_max_n}: an SDP of this size "
                                               f"runs for hours; policy_iteration and ms_lqr need none"})
    start = time.perf_counter()
    try:
        with np.errstate(all="ignore"):
            res = synthesize(model, moments, method, **options)
    except Exception as err:                      # noqa: BLE001 -- any failure of one design is its status
        log.warning("design %s failed: %s", method, one_line(err))
        res = SynthesisResult(method, None, float("nan"), f"failed: {one_line(err)}", nbar=0)
    if res.F is not None and not np.all(np.isfinite(res.F)):
        res = SynthesisResult(method, None, float("nan"), "failed: the gain is not finite", nbar=res.nbar)
    res.seconds = res.seconds or time.perf_counter() - start
    return res


UNCERTAINTY_STREAM = 3   # SeedSequence([seed, 3]): the modeling window's bootstrap (stages use spawn keys 0-2)
KEPT_GAIN = "identification_gain"     # the method name of the identification's gain when the loop keeps it
CRPS_SEED, CRPS_DRAWS = 20240, 20_000   # the plant's xi drawn for the summary's xi_crps (Monte Carlo error < 1%)
PASS_TOL = 1e-3        # iterated identification: stop when the moments move less than this (relative)


def identified_moments(exp: Experiment, ident: Trajectories) -> tuple[MomentModel | None, str]:
    """The moments modeled from an identification run's xi_{k|k} over the window K0..K0+K1
    (identification.covariance), or (None, why not). Several recorded paths: the paths whose EnKF
    estimate failed are left out (`usable_paths`; the summary says how many), unless every one failed."""
    xi = ident.xi(ident.psi_filt_mean)                  # (K+1, P, p): one path simulated, or the recorded paths
    K0, K1 = exp.identification.K0, exp.identification.K1
    ok = usable_paths(exp, ident)
    if xi.shape[1] > 1 and ok.any() and not ok.all():
        ident = select_paths(ident, ok)
        xi = xi[:, ok]
    if ident.status != "ok" or not np.all(np.isfinite(xi[K0:K0 + K1 + 1])):
        bad = np.flatnonzero((ident.failed_at >= 0) | ~np.all(np.isfinite(xi[K0:K0 + K1 + 1]), axis=(0, 2)))[0]
        reason = ident.failure[bad] or "the filtered xi is not finite"
        k_fail = ident.failed_at[bad] if ident.failed_at[bad] >= 0 else "window"
        where = f" (path {bad})" if xi.shape[1] > 1 else ""
        return None, f"identification failed at k = {k_fail}{where}: {FAILURES.get(reason, reason)}"
    total = exp.identification.covariance == "total"
    # the paths' windows pooled (model_distribution): one path's moments bit for bit as before
    return model_distribution(xi, K0, K1, ident.xi_filt_cov if total else None), ""


def usable_paths(exp: Experiment, ident: Trajectories) -> np.ndarray:
    """(P,) bool: the identification paths that did not fail and whose filtered xi is finite over the window."""
    K0, K1 = exp.identification.K0, exp.identification.K1
    xi = ident.xi(ident.psi_filt_mean)[K0:K0 + K1 + 1]
    return (ident.failed_at < 0) & np.all(np.isfinite(xi), axis=(0, 2))


def select_paths(tr: Trajectories, keep: np.ndarray) -> Trajectories:
    """The paths `keep` ((P,) bool) of tr (path axis 1 of the (K+1, P, ...) arrays, 0 of the per-path ones)."""
    pick = lambda name, v: None if v is None else (v[keep] if name in ("failed_at", "failure") else v[:, keep])
    return Trajectories(**{f.name: tr.n if f.name == "n" else pick(f.name, getattr(tr, f.name))
                           for f in dataclasses.fields(Trajectories)})


def iterate_identification(exp: Experiment, identify, ident, dist, failure: str, psi0: np.ndarray):
    """identification.xi_model = iterated: passes whose EnKF draws each step's xi i.i.d. from the
    previous pass's moments (Assumption 1, `EnKF.xi_prior`), so that the next output estimates it, and
    whose modeled moments are the next pass's prior, until mean and standard deviations change by less
    than PASS_TOL (relative to the largest standard deviation) or identification.passes are done: the
    moments as a fixed point of their own estimation. Without a first model (the random-walk pass
    failed) the first prior is xi at the initial ensemble's with enkf.Q's xi block as covariance.
    Returns (the last successful pass's run, moments, failure, info for the summary)."""
    n = exp.model.n
    prior = dist if dist is not None else MomentModel(mean=psi0[n:], cov=exp.filter.enkf.Q[n:, n:])
    info = {"first": "random_walk" if dist is not None else f"the prior guess ({failure})", "passes": 0,
            "converged": False}
    for _ in range(exp.identification.passes):
        tr = identify(dataclasses.replace(exp.filter.enkf, xi_prior=prior))
        new, why = identified_moments(exp, tr)
        if new is None:
            info["failed"] = why
            break
        info["passes"] += 1
        ident, dist, failure = tr, new, ""
        scale = max(np.sqrt(np.diag(new.cov)).max(initial=0.0), 1e-12)
        change = max(np.abs(new.mean - prior.mean).max(),
                     np.abs(np.sqrt(np.diag(new.cov)) - np.sqrt(np.diag(prior.cov))).max()) / scale
        prior = new
        info["last_change"], info["tolerance"] = float(change), PASS_TOL
        if change < PASS_TOL:
            info["converged"] = True
            break
    return ident, dist, failure, info


def moment_uncertainty(exp: Experiment, ident: Trajectories, summary: dict) -> tuple[np.ndarray, np.ndarray] | None:
    """The modeled moments' uncertainty: identification.resamples moving-block bootstrap draws (means (B, p),
    covariances (B, p, p)) of the modeling window of the run the moments come from (`modeling.moment_draws`),
    seeded by the run's seed; their spread (std over draws of each xi mean and std) goes into the summary.
    None without resamples."""
    settings = exp.identification
    if not settings.resamples or not exp.model.p:
        return None
    total = settings.covariance == "total"
    ok = usable_paths(exp, ident)
    if ident.failed_at.size > 1 and ok.any() and not ok.all():        # recorded paths whose estimate failed
        ident = select_paths(ident, ok)
    xi, xi_cov = ident.xi(ident.psi_filt_mean), ident.xi_filt_cov if total else None
    if xi.shape[1] > 1:             # several (recorded) paths: a bootstrap over the paths
        mean, cov = path_moment_draws(xi, settings.K0, settings.K1, xi_cov, resamples=settings.resamples,
                                      seed=[exp.seed, UNCERTAINTY_STREAM])
    else:
        mean, cov = moment_draws(xi[:, 0], settings.K0, settings.K1, None if xi_cov is None else xi_cov[:, 0],
                                 resamples=settings.resamples, block=settings.block,
                                 seed=[exp.seed, UNCERTAINTY_STREAM])
    std = np.sqrt(np.clip(np.diagonal(cov, axis1=1, axis2=2), 0, None))
    summary["modeling_uncertainty"] = {"resamples": settings.resamples, "block": settings.block,
                                       "over": "paths" if xi.shape[1] > 1 else "window blocks",
                                       "xi_mean_sd": mean.std(axis=0, ddof=1).tolist(),
                                       "xi_std_sd": std.std(axis=0, ddof=1).tolist()}
    return mean, cov


def safer_gain(exp: Experiment, dist: MomentModel, chosen: SynthesisResult, draws: tuple[np.ndarray, np.ndarray],
               summary: dict) -> SynthesisResult | None:
    """When the identification ran under a feedback gain F_id (summary["identification_feedback"]["F"]): the
    exact rates of the designed gain and of F_id at every draw of the modeled moments (`moment_uncertainty`),
    at their worst over the draws. The
    designed gain is the optimum at the point estimate only; where it is worse at its worst than the gain the
    plant was run with, the loop keeps F_id (a SynthesisResult with status `kept`; None: the designed gain
    stays). The comparison and the choice go into summary["gain_choice"]."""
    F_id = (summary.get("identification_feedback") or {}).get("F")
    if F_id is None:
        return None
    F_id = np.asarray(F_id, dtype=float)
    Abar, Bbar = moment_factors(exp.model, *draws)
    with np.errstate(all="ignore"):
        designed = rates(Abar, Bbar, np.broadcast_to(chosen.F, (len(Abar),) + chosen.F.shape))
        held = rates(Abar, Bbar, np.broadcast_to(F_id, (len(Abar),) + F_id.shape))
    worst_designed, worst_held = float(np.max(designed)), float(np.max(held))
    keep = worst_held < worst_designed
    summary["gain_choice"] = {"kept": "identification" if keep else "designed", "draws": int(len(Abar)),
                              "designed_worst": worst_designed, "identification_worst": worst_held,
                              "designed_median": float(np.median(designed)),
                              "identification_median": float(np.median(held))}
    if not keep:
        return None
    return SynthesisResult(KEPT_GAIN, F_id, safe_rate(exp.model, dist, F_id), "kept",
                           nbar=int(exp.model.Gbar(dist).shape[0]))


def identification_feedback(exp: Experiment, force_nominal: bool = False) -> tuple[np.ndarray | None, dict]:
    """The gain of the identification run (None: open loop) and what was decided, for the summary.

    auto: open loop when the plant at the nominal guess xi_guess (prior knowledge, by default the mean
    of the plant's distribution) is mean-square stable in open loop, else nominal: a stabilizing
    gain designed on the plant at xi_guess (`nominal_gain`); force_nominal: nominal whatever the guess
    (run_experiment's second try when the open-loop plant diverged)."""
    mode = exp.identification.feedback
    info = {"mode": mode}
    if mode == "none":
        return None, info
    if mode == "given":
        return exp.identification.gain, info | {"used": "given", "F": exp.identification.gain.tolist()}
    guess = MomentModel.deterministic(exp.identification.xi_guess)
    with np.errstate(all="ignore"):
        info["open_loop_rate_at_guess"] = safe_rate(exp.plant, guess, np.zeros((exp.plant.m, exp.plant.n)))
    if mode == "auto" and info["open_loop_rate_at_guess"] < 1 and not force_nominal:
        return None, info | {"used": "open_loop"}
    res = nominal_gain(exp.plant, exp.identification.xi_guess)
    info |= {"used": "nominal", "method": res.method, "status": res.status, "rate_at_guess": res.lam}
    if res.F is None or not np.all(np.isfinite(res.F)) or not res.lam < 1:
        info["used"] = "open_loop (no stabilizing nominal gain)"
        return None, info
    with np.errstate(all="ignore"):
        info["rate_plant"] = safe_rate(exp.plant, None, res.F)
    info["F"] = res.F.tolist()                   # the gain the plant is identified under (`safer_gain`)
    return res.F, info


def safe_rate(system, dist, F) -> float:
    """ms_rate, NaN where it cannot be computed (a gain so large that the operator is not finite)."""
    try:
        with np.errstate(all="ignore"):
            return ms_rate(system, dist, F)
    except (ValueError, np.linalg.LinAlgError):
        return float("nan")


# ------------------------------------------------------------------------------------ tables
def _columns(name: str, values: np.ndarray) -> dict:
    """{"name[i]": values[..., i]} for the last axis of values (K+1, P, ...), flattened path-major
    (path, then k, then the rest) so that the rows of consecutive chunks of paths line up."""
    values = np.moveaxis(values, 1, 0)
    return {f"{name}[{i}]": values[..., i].ravel() for i in range(values.shape[-1])}


def carries_d(exp: Experiment) -> bool:
    """Whether some loop of the trajectories table estimates the unknown input disturbance d: every loop with
    enkf.disturbance (`loop_observer`), the online loop with controller.disturbance (`online_loop`)."""
    return exp.filter.disturbance is not None or (exp.controller.kind == "online"
                                                   and exp.controller.disturbance is not None)


def trajectory_table(experiment: str, tr: Trajectories | None, first_path: int = 0,
                     exp: Experiment | None = None, d_columns: bool = False) -> pd.DataFrame:
    """One row per (path, k), paths first_path.. in order: plant q, y, u and the EnKF's mean and
    spread of x and xi before and after filtering, and where the EnKF estimates the unknown input
    disturbance d (enkf.disturbance: every loop's EnKF, `loop_observer`; controller.disturbance: the
    online loop's) its filtered mean and spread; with d_columns, a loop whose EnKF does not has them NaN
    (one set of columns for every loop of a table, `carries_d`)."""
    if tr is None:                       # no gain to simulate: an empty table with the usual columns
        n, p, ny, m = exp.model.n, exp.model.p, exp.model.ny, exp.model.m
        shape = lambda d: np.zeros((0, 0, d))
        d = shape(m) if carries_d(exp) else None
        tr = Trajectories(q=shape(n), y=shape(ny), u=shape(m), psi_pred_mean=shape(n + p),
                          psi_pred_std=shape(n + p), psi_filt_mean=shape(n + p), psi_filt_std=shape(n + p),
                          failed_at=np.zeros(0, int), failure=np.zeros(0, object), n=n, d_filt_mean=d, d_filt_std=d)
    steps, P = tr.q.shape[:2]
    cols = {"experiment": np.full(steps * P, experiment), "k": np.tile(np.arange(steps), P),
            "path": np.repeat(first_path + np.arange(P), steps)}
    cols.update(_columns("q", tr.q) | _columns("y", tr.y) | _columns("u", tr.u))
    for stage in ("pred", "filt"):
        for stat in ("mean", "std"):
            psi = getattr(tr, f"psi_{stage}_{stat}")
            cols.update(_columns(f"x_{stage}_{stat}", tr.x(psi)) | _columns(f"xi_{stage}_{stat}", tr.xi(psi)))
    for stat in ("mean", "std") if tr.d_filt_mean is not None or d_columns else ():
        values = getattr(tr, f"d_filt_{stat}")
        cols.update(_columns(f"d_filt_{stat}", np.full(tr.u.shape, np.nan) if values is None else values))
    return pd.DataFrame(cols)


def members_table(experiment: str, tr: Trajectories, first_path: int = 0) -> pd.DataFrame:
    """Every filtered ensemble member: one row per (path, k, member) (tracking level `full`)."""
    steps, P, M, _ = tr.members.shape
    cols = {"experiment": np.full(steps * P * M, experiment), "k": np.tile(np.repeat(np.arange(steps), M), P),
            "path": np.repeat(first_path + np.arange(P), steps * M), "member": np.tile(np.arange(M), steps * P)}
    cols.update(_columns("x_filt", tr.x(tr.members)) | _columns("xi_filt", tr.xi(tr.members)))
    return pd.DataFrame(cols)


def path_table(loops: dict[str, LoopSummary]) -> pd.DataFrame:
    """Per path: the step it failed at (-1: never) and why."""
    return pd.DataFrame([{"experiment": name, "path": j, "failed_at": int(loop.failed_at[j]),
                          "failure": str(loop.failure[j]) if loop.failure[j] not in (None, "") else None}
                         for name, loop in loops.items() for j in range(loop.failed_at.size)])


def model_table(exp: Experiment, dist) -> pd.DataFrame:
    """The modeled distribution: mean, cov, second moment and Gbar as (quantity, row, col, value)."""
    rows = []
    if dist is not None:
        for name, value in (("mean", dist.mean[:, None]), ("cov", dist.cov), ("second_moment", dist.second_moment),
                            ("Gbar", exp.model.Gbar(dist))):
            rows += [{"quantity": name, "row": i, "col": j, "value": float(v)}
                     for (i, j), v in np.ndenumerate(value)]
    return pd.DataFrame(rows, columns=["quantity", "row", "col", "value"])


def gains_table(exp: Experiment, designs: dict, selected: tuple[str, str]) -> pd.DataFrame:
    """Per (distribution, method): status, lam (design), bracket, nbar, exact rates, LQ costs and H2
    norms on the design moments and on the true plant (`performance`), robust_box's certified box rate
    (lam_box), its proven lower end (lam_box_lower) and, with find_max_width, the largest certified and
    smallest proven-infeasible box widths (max_width, min_infeasible_width; NaN otherwise), F.
    designs: {(source, method): (moments, SynthesisResult)}; `selected` is the (source, method) the
    closed loop used (gain.source; ("fixed", "fixed") for a given F).

    Only reproducible numbers go into tables; synthesis times are in run.json's timings."""
    rows = []
    for (source, method), (moments, res) in designs.items():
        found = res.F is not None
        F = res.F if found else np.full((exp.model.m, exp.model.n), np.nan)
        rows.append({"distribution": source, "method": method,
                     "selected": (source, method) == selected,
                     "status": res.status, "lam": res.lam, "lam_lower": res.lam_lower,
                     "nbar": res.nbar,
                     "rate_model": safe_rate(exp.model, moments, F) if found and moments is not None else np.nan,
                     "rate_plant": safe_rate(exp.plant, None, F) if found and exp.plant is not None else np.nan,
                     **performance(exp, moments, F if found and moments is not None else None),
                     "lam_box": res.info.get("lam_box", np.nan),
                     "lam_box_lower": res.info.get("lam_box_lower", np.nan),
                     "max_width": res.info.get("max_width", np.nan),
                     "min_infeasible_width": res.info.get("min_infeasible_width", np.nan),
                     **{f"F[{i},{j}]": v for (i, j), v in np.ndenumerate(F)}})     # F[i,j]: (m, n) unambiguous
    # the columns also when no design ran (no model, no reported moments): readers select on them
    columns = [*GAIN_COLUMNS, *(f"F[{i},{j}]" for i in range(exp.model.m) for j in range(exp.model.n))]
    return pd.DataFrame(rows, columns=columns)


GAIN_COLUMNS = ("distribution", "method", "selected", "status", "lam", "lam_lower", "nbar", "rate_model",
                "rate_plant", "lq_cost_q0_plant", "lq_cost_plant", "h2_plant", "lq_cost_model", "h2_model",
                "lam_box", "lam_box_lower", "max_width", "min_infeasible_width")


def performance(exp: Experiment, moments, F) -> dict:
    """Exact LQ cost (weights I, I) from the plant's q0 and averaged over x0 ~ N(0, I), and the H2 norm
    from d (added on u) to [x; F x], on the true plant and on the design moments; inf where not
    mean-square stable, NaN without a gain."""
    keys = ("lq_cost_q0_plant", "lq_cost_plant", "h2_plant", "lq_cost_model", "h2_model")
    if F is None or not np.all(np.isfinite(F)):
        return dict.fromkeys(keys, np.nan)
    model = exact_costs(exp.model, moments, F)
    if exp.plant is None:                       # a data run: no true plant, no number on it
        return dict.fromkeys(keys[:3], np.nan) | {"lq_cost_model": model["lq_cost"], "h2_model": model["h2"]}
    plant = exact_costs(exp.plant, None, F, exp.q0)
    return {"lq_cost_q0_plant": plant["lq_cost_x0"], "lq_cost_plant": plant["lq_cost"], "h2_plant": plant["h2"],
            "lq_cost_model": model["lq_cost"], "h2_model": model["h2"]}


@dataclass(frozen=True)
class RateWindow:
    """The window [k_from, k_to] the loops' rates are measured over: from the config (source
    "config"), or placed on the ideal loop's exact curve above the noise floor ("auto"); placed False
    when no such window exists (k is then the span from the window's start to the horizon, shown but
    not trusted: the verdict is undetermined)."""

    k: tuple[int, int]
    source: str
    placed: bool = True


def rate_window(exp: Experiment, exact: pd.DataFrame, floor: Floor | None, closed: LoopSummary | None) -> RateWindow:
    """closed_loop.rate_window as configured, or (auto) placed on the exact RMS curve of the ideal
    closed loop (of the open loop without a gain) from the end of the disturbance, above the noise
    floor, where the closed loop's own RMS is above it too (numerics/verdict.py)."""
    if exp.loop.rate_window is not None:
        return RateWindow(exp.loop.rate_window, "config")
    loop = "closed_loop" if (exact["experiment"] == "closed_loop").any() else "open_loop"
    curve = exact.loc[exact["experiment"] == loop, "rms"].to_numpy()
    start = window_start(exp.loop.disturbance, exp.model.n)
    empirical = rms_band(closed.sq)[0] if closed is not None else None    # over the paths still finite
    placed = place_window(curve, start, np.nan if floor is None else floor.rms, empirical)
    K = exp.loop.horizon
    return RateWindow(placed, "auto") if placed is not None else \
        RateWindow((min(start, K - 1), K), "auto", placed=False)


def online_nominal(exp: Experiment, enkf: EnKF) -> tuple[SynthesisResult, str]:
    """The online loop's nominal gain and the law it was designed on: "start", the mean-square LQR at the
    guess with the spread xi has in the loop's EnKF before any output (`EnKF.start_cov`; a two-point
    component the variance its mean fixes), in the model's terms; or "guess", the deterministic design at
    the guess (`nominal_gain`) where the start's law admits no stabilizing gain or the model's xi is not an
    affine map of the plant's. The EnKF draws its start from that law, so a gain it destabilises leaves the
    ensemble's spread growing without bound, and the state estimate with it (docs/online-rounds.md, an
    eleventh round)."""
    law = start_law(exp, enkf)
    if law is None:
        return nominal_gain(exp.plant, exp.identification.xi_guess), "guess"
    res = nominal_gain(exp.model, *law)
    return res, "start" if res.method == "ms_lqr" else "guess"          # (nominal_gain returns it only if stable)


def start_law(exp: Experiment, enkf: EnKF) -> tuple[np.ndarray, np.ndarray] | None:
    """(mean (p,), cov (p, p)): the law of the first xi the online loop's EnKF draws, xi_guess with the start's
    spread (`EnKF.start_cov`; a two-point component the variance its mean fixes), in the model's terms; None
    where the model's xi is not an affine map of the plant's."""
    truth = truth_map(exp.model, exp.plant)
    if truth is None:
        return None
    n, dim = exp.model.n, enkf.dim
    guess = truth[0] @ np.asarray(exp.identification.xi_guess, dtype=float) + truth[1]
    return two_point_moments(guess, enkf.start_cov(exp.filter.P0[n:dim, n:dim]), enkf.two_point)


START_HALVINGS = 10


def stabilizable_start(exp: Experiment, enkf: EnKF) -> EnKF:
    """enkf with its static-mean start law scaled (`EnKF.start_scale`) by the largest c of 1, 1/2, ..., 2^-10
    at which the law admits a mean-square stabilizing gain (the mean-square LQR at it, `nominal_gain`'s first
    design), if that gain holds the whole law no worse than the deterministic design at the guess does (their
    exact rates there); unscaled where none does, the check fails or `start_law` is None.

    The start's spread is an assumption, enkf.Q's xi block, not a measurement. Its members move x with their
    draws under the gain in use; a law under which no gain is mean-square stable leaves the nominal gain
    designed at the guess alone, which that law destabilises, and the ensemble's x spread grows until the
    estimate fed back is worse than none (seed 6's random plant 19: 78 of 100 paths lost against none offline;
    docs/online-rounds.md, a thirteenth round). The check: narrowing moves only the Gaussian components, not a
    two-point one, whose spread its mean fixes; far from the plant's mean (seed 0's random plant 9, the guess one
    standard deviation off) a law narrowed to 2^-8 admits a gain that leans on the Gaussian components'
    certainty (exact rate 2.30 at the whole law, 3.25 on the plant, against the deterministic design's 1.42 and
    1.35)."""
    full = start_law(exp, enkf)
    if full is None:
        return enkf
    for c in 0.5 ** np.arange(START_HALVINGS + 1):
        scaled = dataclasses.replace(enkf, start_scale=float(c))
        res = nominal_gain(exp.model, *start_law(exp, scaled))
        if res.method != "ms_lqr":
            continue
        if c == 1:
            return enkf
        whole = MomentModel(mean=full[0], cov=full[1])
        deterministic = nominal_gain(exp.model, full[0])
        held = deterministic.F is None or ms_rate(exp.model, whole, res.F) <= ms_rate(exp.model, whole, deterministic.F)
        return scaled if held else enkf
    return enkf


def online_observer(exp: Experiment) -> EnKF:
    """The online loop's EnKF: the loops' observer (`loop_observer`) with the online controller's unknown-input
    estimate, smoother lag, start (static_mean with observer = model only; its law narrowed where no gain keeps it
    mean-square stable: `stabilizable_start`) and two-point components."""
    online = exp.controller.online
    enkf = loop_observer(exp, None)
    if enkf.disturbance is None and exp.controller.disturbance is not None:
        # controller.disturbance: the online loop's EnKF estimates an unknown input disturbance, which it
        # would otherwise read as a wrong xi, the data the controller models xi from
        enkf = dataclasses.replace(enkf, disturbance=exp.controller.disturbance)
    # where the plant file's family fixes a component's law by its mean (a Bernoulli dropout), the static-mean
    # start and each path's model draw that law, not a Gaussian (`EnKF.xi_ends`)
    ends = xi_ends(exp.model, exp.plant) if enkf.xi_bounds is not None else None
    static_mean = online.observer == "model" and online.start == "static_mean"
    enkf = dataclasses.replace(enkf, lag=online.lag, static_mean=static_mean, start_spread=online.start_spread,
                               mean_spread=online.mean_spread, xi_ends=ends)
    # a start law no gain keeps mean-square stable is narrowed to one that some gain does
    return stabilizable_start(exp, enkf) if static_mean else enkf


def loop_observer(exp: Experiment, moments):
    """The EnKF of the closed and open loops (and their noise floor) and, without moments, of the online
    loop: the identification's, with its predicted xi drawn i.i.d. from the design moments
    (EnKF.xi_prior) when closed_loop.observer_xi is `model`, the paper's random walk (`random_walk`) or
    without moments; and with enkf.disturbance, an estimate of an unknown input disturbance in its state
    (EnKF.disturbance), which identification, whose input the filter is told, does without."""
    enkf = exp.filter.enkf
    if exp.loop.observer_xi == "model" and moments is not None:
        enkf = dataclasses.replace(enkf, xi_prior=moments)
    if exp.filter.disturbance is not None:
        enkf = dataclasses.replace(enkf, disturbance=exp.filter.disturbance)
    return enkf


def noise_floor(exp: Experiment, enkf, F: np.ndarray, seed, sim: dict) -> Floor:
    """The closed loop's noise floor: the loop with gain F and the EnKF observer started at rest (q_0 =
    0) without disturbance, closed_loop.floor_paths paths; its mean square over the second half of the
    horizon, whether it grows there, and which paths failed (`verdict.Floor`)."""
    K = exp.loop.horizon
    tr = simulate(exp.plant, enkf, F=F, d=np.zeros((K + 1, exp.model.m)),
                  paths=min(exp.loop.floor_paths, exp.loop.paths), seed=seed, filter_sees_d=True,
                  **dict(sim, q0=np.zeros(exp.plant.n)))
    return Floor.of(np.sum(tr.q ** 2, axis=-1), tr.failed_at)


def metrics_table(exp: Experiment, loops: dict[str, LoopSummary], window: RateWindow, floors: dict[str, Floor | None],
                  exact: pd.DataFrame) -> pd.DataFrame:
    """Per loop: empirical rate over the rate window with its 95% interval (`verdict.rate_interval`), the
    ideal loop's exact rate over the same window, the noise floor, the verdict, its reason and the rate it
    was decided on (`judge_loop`: over k_from..k_end, k_end before k_to where the loop reached its floor,
    the floor's mean square subtracted), failures, estimation quality.

    x_error_rms: RMS of the predicted x_{k|k-1} against q_k (k >= 0); x_rmse, xi_rmse: RMS of the
    filtered x_{k|k}, xi_{k|k} against q_k and the true xi (k >= 1; the true xi at k is T s_{k-1} + t
    from `truth_map`, NaN when the model's xi has no value in the plant's terms); *_spread_error:
    sqrt(mean sum std^2) / RMSE (1: the ensemble spread matches its error). Means are over every
    finite (step, path). floors: the noise floor each loop is judged against (absent or None: none, floor_rms
    NaN): the closed loop's own; the online loop's the closed loop's where that one holds (`Floor.holds`); the
    open loop's is 0 (its observer does not act on the plant)."""
    k_from, k_to = window.k
    rows = []
    for name, loop in loops.items():
        loop_floor = floors.get(name)
        ideal = exact.loc[exact["experiment"] == name, "rms"].to_numpy()
        verdict = judge_loop(loop.sq, failed_at=loop.failed_at, failure=loop.failure,
                             window=window.k if window.placed else None, exact_rms=ideal if ideal.size else None,
                             floor=loop_floor, open_loop=name == "open_loop")
        # the rate over the window as the paper measures it (no floor subtracted); the verdict's own rate is
        # over k_from..k_end with the floor's mean square subtracted
        interval = verdict.window_rate if np.isfinite(verdict.window_rate[0]) else \
            rate_interval(loop.sq[k_from], loop.sq[k_to], k_to - k_from)
        with np.errstate(all="ignore"):
            exact_rate = (ideal[k_to] / ideal[k_from]) ** (1 / (k_to - k_from)) if ideal.size else np.nan
            end_rms = float(np.sqrt(np.mean(loop.sq[k_to])))
        x_rmse, xi_rmse = loop.rms_of("x_err"), loop.rms_of("xi_err")
        rows.append({"experiment": name, "verdict": verdict.word, "verdict_reason": verdict.reason,
                     "status": loop.status, "rate": interval[0], "rate_low": interval[1], "rate_high": interval[2],
                     "k_from": k_from, "k_to": k_to, "verdict_rate": verdict.rate, "verdict_rate_low": verdict.low,
                     "verdict_rate_high": verdict.high, "k_end": verdict.k_end, "exact_rate": exact_rate,
                     "floor_rms": (0.0 if name == "open_loop" else np.nan) if loop_floor is None else loop_floor.rms,
                     "rms_k_to": end_rms, "paths": loop.sq.shape[1],
                     "failed_fraction": float(np.mean(loop.failed_at >= 0)),
                     "x_error_rms": loop.rms_of("x_pred_err"),
                     "q_rms_final": float(np.sqrt(np.mean(loop.sq[-1]))),
                     "x_rmse": x_rmse, "x_spread_error": _ratio(loop.rms_of("x_var"), x_rmse),
                     "xi_rmse": xi_rmse, "xi_spread_error": _ratio(loop.rms_of("xi_var"), xi_rmse)})
    return pd.DataFrame(rows, columns=list(METRIC_COLUMNS))


def _ratio(a: float, b: float) -> float:
    """a / b, NaN when b is 0 (no error to compare the spread with, e.g. p = 0)."""
    return a / b if b != 0 else float("nan")


ESTIMATION = ("x_rmse", "x_spread_error", "xi_rmse", "xi_spread_error")
METRIC_COLUMNS = ("experiment", "verdict", "verdict_reason", "status", "rate", "rate_low", "rate_high", "k_from",
                  "k_to", "verdict_rate", "verdict_rate_low", "verdict_rate_high", "k_end", "exact_rate", "floor_rms",
                  "rms_k_to", "paths", "failed_fraction", "x_error_rms", "q_rms_final", *ESTIMATION)


def exact_table(exp: Experiment, chosen: SynthesisResult | None) -> pd.DataFrame:
    """sqrt(E||q_k||^2) of the ideal loops (state feedback, true plant distribution), exactly."""
    frames = []
    gains = ([("closed_loop", chosen.F)] if chosen is not None and chosen.F is not None else []) + \
        [("open_loop", np.zeros((exp.plant.m, exp.plant.n)))]
    for name, F in gains:
        with np.errstate(all="ignore"):     # a growing loop overflows: its curve is inf or NaN there
            _, second = second_moments(exp.plant, None, F, exp.q0, exp.loop.disturbance)
            rms = np.sqrt(np.trace(second, axis1=1, axis2=2))
        frames.append(pd.DataFrame({"experiment": name, "k": np.arange(second.shape[0]), "rms": rms}))
    return pd.concat(frames, ignore_index=True)


def _summary(exp: Experiment, dist, chosen, tables: dict) -> dict:
    """Key numbers of the run (run.json `summary`); what print_summary shows."""
    s = {"plant": exp.plant_name, "model": exp.model_name, "gain_method": exp.design.method}
    if dist is not None:
        s.update(nbar=int(exp.model.Gbar(dist).shape[0]), xi_mean=dist.mean.tolist(),
                 xi_std=np.sqrt(np.diag(dist.cov)).tolist())
    truth = truth_map(exp.model, exp.plant)
    if truth is not None:                # the plant file's distribution in the model's xi = T s + t
        T, t = truth
        family = exp.plant.xi_dist
        s.update(plant_xi_mean=(T @ family.mean + t).tolist(),
                 plant_xi_std=np.sqrt(np.diag(T @ family.cov @ T.T)).tolist())
        if dist is not None:             # the model's error: RMS over components of mean and std
            for what in ("mean", "std"):
                err = np.subtract(s[f"xi_{what}"], s[f"plant_xi_{what}"])
                s[f"xi_{what}_error"] = float(np.sqrt(np.mean(err ** 2)))
            # and a proper score of the modeled marginals against the plant's xi, mean over components, from
            # one fixed set of draws (the same yardstick for every run and seed)
            draws = family.sample(np.random.default_rng(CRPS_SEED), (CRPS_DRAWS,)) @ T.T + t
            s["xi_crps"] = float(np.mean(expected_crps(dist.mean, s["xi_std"], draws)))
    if chosen is not None:
        s.update(synthesis_status=chosen.status, lam=chosen.lam,
                 rate_plant=safe_rate(exp.plant, None, chosen.F) if chosen.F is not None else None)
    gains = tables["gains"]
    s["designs"] = {row.method: row.status for row in gains.itertuples() if row.distribution == "identified"}
    paths = tables["paths"]
    for row in tables["metrics"].itertuples():
        s[f"{row.experiment}_status"] = row.status
        s[f"{row.experiment}_verdict"] = row.verdict
        s[f"{row.experiment}_verdict_reason"] = row.verdict_reason
        s[f"{row.experiment}_exact_rate"] = row.exact_rate              # the ideal loop over the same window
        # the error of the estimate the feedback uses: x_{k|k-1} (predicted) or x_{k|k} (filtered)
        fed_back = row.x_error_rms if exp.loop.estimate == "predicted" else row.x_rmse
        s[f"{row.experiment}_estimation"] = {"estimate": exp.loop.estimate, "x_error_rms": fed_back,
                                             "rms_k_to": row.rms_k_to}
        s[f"{row.experiment}_rate"] = [row.rate, row.rate_low, row.rate_high]
        failed = paths[(paths["experiment"] == row.experiment) & (paths["failed_at"] >= 0)]["failed_at"]
        if len(failed):
            reasons = paths[(paths["experiment"] == row.experiment) & (paths["failed_at"] >= 0)]["failure"]
            s[f"{row.experiment}_failed"] = {"fraction": row.failed_fraction, "first_k": int(failed.min()),
                                             "median_k": float(failed.median()),
                                             "reasons": {str(r): int(c) for r, c in reasons.value_counts().items()}}
    through_y = loop_through_outputs(exp, chosen, s)
    if through_y:
        s["closed_loop_through_y"] = through_y
    if exp.reference is not None:
        s["reference"] = exp.reference
    return s


OBSERVER_SEARCH_MAX_N = 20    # the search for a linear observer runs on 2n states: up to this n
OBSERVER_SEARCH_STEPS = 40    # its BFGS steps (n = 6: about 0.3 s). The rate reported is the exact rate of the
                              # observer found; against 200 steps, on the random plants (seeds 0-4) whose rate is
                              # 0.9-1.15: within 0.005, none on the other side of 1 (0.05 on plants near 0.6)


def loop_through_outputs(exp: Experiment, chosen, s: dict) -> dict | None:
    """When the closed loop is not found stable although its gain stabilizes the true plant with the true
    state: the exact rate of the loop through y with the best linear observer found (`best_observer` on the
    true plant, the loop's estimate), which tells a plant whose outputs cannot carry this gain's loop (>= 1)
    from an EnKF that falls short of a linear observer (< 1; the search stops at the first such observer,
    which answers it). None otherwise."""
    rate, verdict = s.get("rate_plant"), s.get("closed_loop_verdict")
    if verdict in (None, "stable") or rate is None or not rate < 1 or exp.plant.n > OBSERVER_SEARCH_MAX_N:
        return None
    why = observer_loop.applies(exp.plant)
    if why:
        return {"rate": None, "not_applicable": why}
    try:
        found = observer_loop.best_observer(exp.plant, None, chosen.F, estimate=exp.loop.estimate,
                                            max_iter=OBSERVER_SEARCH_STEPS, stop_below=1.0)
    except (ValueError, np.linalg.LinAlgError) as err:
        return {"rate": None, "not_applicable": str(err)}
    return {"rate": found.rate, "kalman_rate": found.kalman_rate, "estimate": exp.loop.estimate}




# ------------------------------------------------------------------------------------ data runs
DATA_TABLES = ("identification", "paths", "model", "gains", "metrics", "exact", "trajectories")


def identify_recorded(exp: Experiment, recorded, seed, sim: dict, keep: bool, enkf=None,
                      keep_forecast: bool = False) -> Trajectories:
    """The identification EnKF run on recorded (u, y) (`simulate(recorded=...)`): batched over the recorded
    paths, path j with the EnKF stream j of the identification's seed and the initial ensemble of a
    simulated identification, so that a run's own record gives its estimates bit for bit. In chunks of
    paths within the Monte Carlo's memory budget (`montecarlo.MEMORY_BUDGET`; every path has its own streams,
    so the chunks change nothing), joined along the path axis."""
    total = exp.identification.covariance == "total"
    enkf = enkf or exp.filter.enkf
    per_path = bytes_per_path(exp.model, enkf, ensemble_size=exp.filter.ensemble_size, horizon=recorded.steps - 1,
                              keep_members=keep, block=16)
    per_path += 8 * recorded.steps * exp.filter.ensemble_size * exp.model.ny if keep_forecast else 0
    size = int(max(1, MEMORY_BUDGET // (3 * per_path)))
    parts = [simulate(None, enkf, d=np.zeros((recorded.steps, exp.model.m)), paths=min(size, recorded.paths - first),
                      first_path=first, seed=seed, filter_sees_d=True, keep_members=keep, keep_xi_cov=total,
                      keep_forecast=keep_forecast, recorded=recorded.select(slice(first, first + size)),
                      **dict(sim, q0=np.zeros(exp.model.n)))
             for first in range(0, recorded.paths, size)]
    return parts[0] if len(parts) == 1 else join_paths(parts)


def join_paths(parts: list[Trajectories]) -> Trajectories:
    """Trajectories of consecutive chunks of paths as one (path axis 1 of the (K+1, P, ...) arrays, 0 of the
    per-path ones)."""
    def join(name):
        values = [getattr(part, name) for part in parts]
        if values[0] is None:
            return None
        return np.concatenate(values, axis=0 if name in ("failed_at", "failure") else 1)
    return Trajectories(**{f.name: parts[0].n if f.name == "n" else join(f.name)
                           for f in dataclasses.fields(Trajectories)})


def run_on_data(exp: Experiment, sink=None, cache=None) -> Outcome:
    """A data run (exp.data): identification on the recorded paths (all but the held-out ones), the moments
    over the window with their uncertainty (a bootstrap over the recorded paths, or over blocks of the window
    for one path), the loop's gain and gain.designs on them, each with its exact rate on the identified model
    and its spread over the moments' draws. There is no plant: no loop is simulated and no number claims one.
    Iterated identification (identification.xi_model: iterated) re-filters the same recorded data with each
    pass's prior: the record does not change between passes (a simulated open-loop identification's would not
    either; one under feedback would, and a data run cannot reproduce that). cache: as `run_experiment`'s (the
    designs only: the recorded identification is the data file's own)."""
    stages, summary = Stages(cache), {}
    timings = stages.timings
    seed = np.random.SeedSequence(exp.seed, spawn_key=SPAWN_KEYS["identification"])
    sim, keep = exp.simulation(), exp.tracking.level == "full"
    data = exp.data
    with stages.timed("identification"):
        identify = partial(identify_recorded, exp, data.identification, seed, sim, keep)
        ident = identify()
        summary["identification_feedback"] = {"mode": "recorded", "used": "the recorded inputs"}
    ident, dist, _ = model_moments(exp, stages, ident, lambda enkf: identify(enkf=enkf), sim, summary)
    draws = moment_uncertainty(exp, ident, summary) if dist is not None else None
    with stages.timed("synthesis"):
        designs = {}
        for source, moments in (("identified", dist), ("reported", exp.reported)):
            for method in exp.design.methods if moments is not None else ():
                designs[source, method] = (moments, configured_design(stages, exp, moments, method, source))
        selected = (exp.design.source, exp.design.method)
        if exp.design.source == "fixed":
            moments = dist if dist is not None else exp.reported
            rate = ms_rate(exp.model, moments, exp.design.F) if moments is not None else np.nan
            designs[("fixed", "fixed")] = (moments, SynthesisResult("fixed", exp.design.F, rate, "fixed", nbar=0))
            selected = ("fixed", "fixed")
        chosen = designs.get(selected, (None, None))[1]
    with stages.timed("metrics"):
        gains = gains_table(exp, designs, selected)
        spread = design_spread(exp, designs, draws)
        for column in ("rate_model_median", "rate_model_q05", "rate_model_q95", "rate_model_worst"):
            gains[column] = [spread.get((row.distribution, row.method), {}).get(column, np.nan)
                             for row in gains.itertuples()]
        tables = {"identification": trajectory_table("identification", ident),
                  "paths": path_table({"identification": LoopSummary.of(ident, exp)}),
                  "model": model_table(exp, dist), "gains": gains,
                  "metrics": pd.DataFrame(columns=list(METRIC_COLUMNS)),
                  "exact": pd.DataFrame({"experiment": pd.Series(dtype=str), "k": pd.Series(dtype=np.int64),
                                         "rms": pd.Series(dtype=float)})}
    if exp.data.holdout_data is not None and dist is not None:
        with stages.timed("validation"):
            tables["validation"], summary["validation"] = validate_holdout(exp, dist, sim)
    sink = MemorySink() if sink is None else sink
    sample = []
    if exp.data.loops and chosen is not None and chosen.F is not None and dist is not None:
        with stages.timed("loops_on_model"):
            summary["loops_on_model"] = loops_on_model(exp, dist, chosen, tables, sink, sample)
    else:
        sink.append("trajectories", trajectory_table("closed_loop", None, exp=exp))
    if isinstance(sink, MemorySink):
        tables |= sink.tables()
    summary.update(data_summary(exp, dist, chosen, designs, spread, ident))
    bad = ~usable_paths(exp, ident)
    if bad.any() and dist is not None:       # modeled without them (`identified_moments`)
        reasons = pd.Series(ident.failure[bad]).replace("", "the filtered xi is not finite").value_counts()
        summary["identification_failed_paths"] = {"count": int(bad.sum()), "of": int(bad.size),
                                                  "reasons": {str(r): int(c) for r, c in reasons.items()}}
    recorded = pd.concat([tables["identification"], *sample], ignore_index=True)
    return Outcome(tables=tables, summary=summary, timings=timings, recorded=recorded,
                   recorded_members=members_table("identification", ident) if keep else None, squares={})


def design_spread(exp: Experiment, designs: dict, draws) -> dict:
    """Per design with a gain: its exact rate on the identified model at every draw of the moments
    (`moment_uncertainty`): median, 5% and 95% quantiles and worst; {} without draws."""
    if draws is None:
        return {}
    Abar, Bbar = moment_factors(exp.model, *draws)
    out = {}
    for (source, method), (_, res) in designs.items():
        if source != "identified" or res.F is None:
            continue
        with np.errstate(all="ignore"):
            r = rates(Abar, Bbar, np.broadcast_to(res.F, (len(Abar),) + res.F.shape))
        q = np.nanpercentile(r, [5, 50, 95]) if np.isfinite(r).any() else [np.nan] * 3
        out[source, method] = {"rate_model_q05": float(q[0]), "rate_model_median": float(q[1]),
                               "rate_model_q95": float(q[2]), "rate_model_worst": float(np.max(r)),
                               "draws": int(len(r))}
    return out


def data_summary(exp: Experiment, dist, chosen, designs: dict, spread: dict, ident: Trajectories) -> dict:
    """A data run's key numbers: the data file, the modeled moments, and each design's exact rate on the
    identified model with its spread over the moments' draws. Nothing here is a number on a true plant."""
    info = exp.data.data.info
    s = {"plant": None, "model": exp.model_name, "gain_method": exp.design.method,
         "data": {"name": info["name"], "sha256": info["sha256"], "rows": info["rows"], "paths": info["paths"],
                  "steps": info["steps"], "identification_paths": int(ident.failed_at.size),
                  "holdout_paths": exp.data.holdout_paths},
         "no_plant": "a data run: every rate is exact on the identified model; there is no true plant"}
    if dist is not None:
        s.update(nbar=int(exp.model.Gbar(dist).shape[0]), xi_mean=dist.mean.tolist(),
                 xi_std=np.sqrt(np.diag(dist.cov)).tolist())
    if chosen is not None:
        s.update(synthesis_status=chosen.status, lam=chosen.lam,
                 rate_model=safe_rate(exp.model, dist, chosen.F) if chosen.F is not None and dist is not None
                 else None)
    s["designs"] = {method: res.status for (source, method), (_, res) in designs.items() if source == "identified"}
    s["design_rates"] = {method: {"status": res.status,
                                  "rate_model": safe_rate(exp.model, dist, res.F) if res.F is not None else None,
                                  **spread.get((source, method), {})}
                         for (source, method), (_, res) in designs.items() if source == "identified"}
    return s


VALIDATION_KEY = (4,)          # SeedSequence(seed, spawn_key=(4,)): the held-out paths' EnKF (stages use 0-2)
VALIDATION_LEVELS = (0.5, 0.9)  # central intervals whose coverage is reported
VALIDATION_COLUMNS = ("law", "output", "crps", "coverage_50", "coverage_90", "steps", "paths")


def validate_holdout(exp: Experiment, dist: MomentModel, sim: dict) -> tuple[pd.DataFrame, dict]:
    """The modeled law on the held-out recorded paths (data.holdout), against the nominal model.

    For each law of xi, the EnKF runs on the held-out (u, y) with its predicted xi drawn i.i.d. from it
    (`EnKF.xi_prior`): `modeled`, the identified moments; `nominal`, xi fixed at their mean (zero covariance).
    The one-step-ahead predictive ensemble of y_k is every member's predicted output from psi_{k|k-1} plus
    output noise N(0, R) (the EnKF's R: the noise the model assumes), the same noise draws for both laws and
    the same EnKF streams (a paired comparison). Scored for k = max(K0, 1)..K (after the identification's
    warm-up) on every held-out path and output: CRPS (mean; lower is better) and the fraction of y_k inside
    the ensemble's central 50% and 90% intervals (calibrated: 0.5 and 0.9). Returns (the `validation`
    table: one row per law and output, and `all`, the mean over outputs; the summary's entry)."""
    held = exp.data.holdout_data
    seed = np.random.SeedSequence(exp.seed, spawn_key=VALIDATION_KEY)
    noise_seed = np.random.SeedSequence(seed.entropy, spawn_key=seed.spawn_key + (2,))   # per path: chunk-free
    k_from = max(exp.identification.K0, 1)
    enkf = exp.filter.enkf
    steps, P, ny, M = held.steps - k_from, held.paths, exp.model.ny, exp.filter.ensemble_size
    R_sqrt = sqrtm_psd(enkf.R)
    # chunks of held-out paths within the memory budget, scored as they come: sums per output of the CRPS and
    # of the hits, and the count of finite (step, path) pairs
    per_path = bytes_per_path(exp.model, enkf, ensemble_size=M, horizon=held.steps - 1) + 8 * 4 * held.steps * M * ny
    size = int(max(1, MEMORY_BUDGET // (3 * per_path)))
    laws = {"modeled": dist, "nominal": MomentModel(mean=dist.mean, cov=np.zeros_like(dist.cov))}
    rows, summary = [], {"paths": P, "k_from": k_from, "k_to": held.steps - 1, "levels": list(VALIDATION_LEVELS)}
    for law, moments in laws.items():
        observer = dataclasses.replace(enkf, xi_prior=moments)
        sums = np.zeros((2 + len(VALIDATION_LEVELS), ny))      # crps, hits per level, count
        failed = 0
        for first in range(0, P, size):
            count = min(size, P - first)
            part = held.select(slice(first, first + count))
            tr = simulate(None, observer, d=np.zeros((held.steps, exp.model.m)), paths=count, first_path=first,
                          seed=seed, filter_sees_d=True, recorded=part, keep_forecast=True,
                          **dict(sim, q0=np.zeros(exp.model.n)))
            v = np.stack([g.standard_normal((steps, M, ny)) for g in path_generators(noise_seed, 0,
                                                                                     range(first, first + count))],
                         axis=1) @ R_sqrt.T                                          # (T, count, M, ny)
            members = np.moveaxis(tr.y_forecast[k_from:] + v, 2, -1)                 # (T, count, ny, M)
            finite = np.all(np.isfinite(members), axis=-1)
            y = part.y[k_from:]
            with np.errstate(invalid="ignore"):
                sums[0] += np.where(finite, ensemble_crps(np.nan_to_num(members), y), 0.0).sum(axis=(0, 1))
                for j, level in enumerate(VALIDATION_LEVELS):
                    sums[1 + j] += (finite & interval_hits(np.nan_to_num(members), y, level)).sum(axis=(0, 1))
            sums[-1] += finite.sum(axis=(0, 1))
            failed += int(np.sum(tr.failed_at >= 0))
        with np.errstate(invalid="ignore"):
            means = sums[:-1] / sums[-1]
            total = sums[:-1].sum(axis=1) / sums[-1].sum()
        for i in [*range(ny), "all"]:
            value = means[:, i] if i != "all" else total
            rows.append({"law": law, "output": str(i), "crps": float(value[0]),
                         **{f"coverage_{round(100 * lv)}": float(value[1 + j])
                            for j, lv in enumerate(VALIDATION_LEVELS)}, "steps": steps, "paths": P})
        summary[law] = {k: rows[-1][k] for k in ("crps", "coverage_50", "coverage_90")}
        summary[law]["failed_paths"] = failed
    better = summary["modeled"]["crps"] < summary["nominal"]["crps"]
    summary["crps_gain"] = summary["nominal"]["crps"] - summary["modeled"]["crps"]
    summary["modeled_better"] = bool(better)
    return pd.DataFrame(rows, columns=list(VALIDATION_COLUMNS)), summary


ON_MODEL = "_on_model"       # a data run's loops are named closed_loop_on_model, open_loop_on_model everywhere
ON_MODEL_LABEL = "simulated on the model, not the plant"


def model_system(exp: Experiment, dist: MomentModel):
    """The identified model as a system to simulate: the model's bases with xi ~ N(mean, cov) of the identified
    moments (a Gaussian law of those moments: the moments are all a data run knows of xi)."""
    from ..numerics.distributions import from_spec
    from ..numerics.systems import AffineRandomSystem
    law = from_spec({"family": "normal", "mean": dist.mean.tolist(), "cov": dist.cov.tolist()})
    return AffineRandomSystem(exp.model.A, exp.model.B, exp.model.C, exp.model.D, xi_dist=law)


def loops_on_model(exp: Experiment, dist: MomentModel, chosen: SynthesisResult, tables: dict, sink,
                   sample: list) -> dict:
    """data.loops: the closed loop (and, with closed_loop.open_loop, the open loop) of the loop's gain with the
    EnKF observer, simulated on the identified model (`model_system`, q0 = ones) exactly as a run simulates them
    on a plant (same seeds, chunks, noise floor, rate window and verdicts), named closed_loop_on_model and
    open_loop_on_model in every table and labelled so in the summary: they are evidence about the model, not
    about the system the data came from. Adds the metrics and exact tables (renamed); returns the summary entry."""
    sexp = dataclasses.replace(exp, plant=model_system(exp, dist), q0=np.ones(exp.model.n), data=None)
    root = lambda stage: np.random.SeedSequence(exp.seed, spawn_key=SPAWN_KEYS[stage])
    sim = sexp.simulation()
    observer = loop_observer(sexp, dist)
    settings = dict(d=exp.loop.disturbance, filter_sees_d=exp.loop.filter_sees_disturbance, **sim)
    loops = {}
    for name, F in [("closed_loop", chosen.F)] + ([("open_loop", None)] if exp.loop.open_loop else []):
        parts = []
        for first, tr, _ in run_chunks(sexp, dict(settings, F=F, seed=root(name)), keep_members=False,
                                       enkf=observer, workers=exp.loop.workers):
            rows = trajectory_table(name + ON_MODEL, tr, first)
            parts.append(stream_chunk(sexp, name, tr, first, rows, sink, sample, []))
        loops[name] = LoopSummary.concat(parts)
    floor = noise_floor(sexp, observer, chosen.F, root("noise_floor"), sim) if exp.loop.floor_paths > 0 else None
    exact = exact_table(sexp, chosen)
    window = rate_window(sexp, exact, floor, loops.get("closed_loop"))
    metrics = metrics_table(sexp, loops, window, {"closed_loop": floor}, exact)
    rename = lambda frame: frame.assign(experiment=frame["experiment"] + ON_MODEL)
    tables["metrics"], tables["exact"] = rename(metrics), rename(exact)
    tables["paths"] = pd.concat([tables["paths"], rename(path_table(loops))], ignore_index=True)
    out = {"label": ON_MODEL_LABEL, "rate_window": list(window.k), "xi_law": "normal (the identified moments)"}
    for row in metrics.itertuples():
        out[row.experiment + ON_MODEL] = {"verdict": row.verdict, "verdict_reason": row.verdict_reason,
                                          "rate": [row.rate, row.rate_low, row.rate_high],
                                          "exact_rate": row.exact_rate, "failed_fraction": row.failed_fraction}
    return out
