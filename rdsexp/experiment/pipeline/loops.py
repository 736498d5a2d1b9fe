"""The loops' Monte Carlo and their verdicts: the closed loop u_k = F x_{k|k-1} + d_k with the EnKF as observer
and the open loop (F = 0), in chunks of paths (montecarlo.py), the closed loop's noise floor (at rest), the rate
window and each loop's empirical rate, interval and verdict against its ideal loop's exact rate.

Seeds: the closed and open loops (and the online loop) use SeedSequence(seed, spawn_key=(1,)), the same plant
samples, as in the paper's Figs. decay_proposed and decay_open; the loop at rest (2,); inside each, path j has
its own plant and EnKF streams.
"""
from __future__ import annotations

import dataclasses
from contextlib import closing

import numpy as np
import pandas as pd

from ...numerics.analysis import rms_band
from ...numerics.simulation import Trajectories
from ...numerics.verdict import (
    HEAVY_TAIL,
    LEVEL,
    Floor,
    asks_for_paths,
    judge_loop,
    look_level,
    place_window,
    rate_interval,
    tail_index,
    window_start,
)
from ..config import Experiment
from ..montecarlo import LoopSummary, Simulation, run_chunks
from .results import JudgedLoops, RateWindow
from .stage import Stages
from .tables import carries_d, exact_table, members_table, trajectory_table, with_gains

# the online loop shares the closed loop's seeds: the same plant samples and EnKF noise, a paired comparison
SPAWN_KEYS = {"identification": (0,), "closed_loop": (1,), "open_loop": (1,), "online": (1,), "noise_floor": (2,)}


def root_seed(exp: Experiment, stage: str) -> np.random.SeedSequence:
    """The stage's root seed, SeedSequence(seed, spawn_key=SPAWN_KEYS[stage])."""
    return np.random.SeedSequence(exp.seed, spawn_key=SPAWN_KEYS[stage])


class Sample:
    """The rows the recording shows: the first tracking.recorded_paths paths of each loop (and, tracking full,
    their members), collected chunk by chunk."""

    def __init__(self):
        self.rows: list[pd.DataFrame] = []
        self.members: list[pd.DataFrame] = []


def simulate_loops(exp: Experiment, stages: Stages, F: np.ndarray, observer, sink, sample: Sample,
                   suffix: str = "", paths: tuple[int, int] | None = None) -> dict[str, LoopSummary]:
    """The closed loop with gain F (m, n) and, with closed_loop.open_loop, the open loop, each in chunks of
    paths: rows to the sink chunk by chunk (named loop + suffix), the recorded paths to `sample`; returns a
    LoopSummary per loop. paths: (first, stop), the paths first..stop - 1 (None: every path of a fixed count).
    The open loop is a cached stage (CACHED_LOOPS)."""
    start, stop = paths or (0, exp.loop.paths)
    loops = {}
    for name, gain in [("closed_loop", F)] + ([("open_loop", None)] if exp.loop.open_loop else []):
        with stages.timed(name + suffix), \
                stages.progress(name.replace("_", " "), (stop - start) * exp.loop.disturbance.shape[0]) as progress:
            parts = []
            sim = Simulation.of(exp, observer, gain, root_seed(exp, name), paths=stop, first_path=start)
            chunks = loop_chunks(sim, name, exp.loop.workers, progress,
                                 stages if name in CACHED_LOOPS else Stages(cache=None))
            with closing(chunks):
                for first, tr in chunks:
                    rows = trajectory_table(name + suffix, tr, first, d_columns=carries_d(exp))
                    if exp.controller.kind == "online":     # the gain in use, as in the online rows
                        rows = with_gains(rows, np.zeros((exp.model.m, exp.model.n)) if gain is None else gain)
                    parts.append(stream_chunk(exp, name + suffix, tr, first, rows, sink, sample))
                    tr = rows = None                    # free the chunk before the next
            loops[name] = LoopSummary.concat(parts)
    return loops


def judge_loops(exp: Experiment, loops: dict[str, LoopSummary], floor: Floor | None,
                F: np.ndarray | None, level: float = LEVEL) -> JudgedLoops:
    """The ideal loops' exact curves (gain F), the rate window and every loop's metrics and verdict, with rate
    intervals at `level`. The noise floor each loop is judged against: the closed loop's own; the online loop's
    the closed loop's where that one holds (`Floor.holds`: that it grows or fails at rest is a claim about that
    loop, not the online one, whose own run at rest is a learning transient, not a floor); the open loop's is 0."""
    exact = exact_table(exp, F)
    window = rate_window(exp, exact, floor, loops.get("closed_loop"))
    floors = {"closed_loop": floor, "online": floor if floor is not None and floor.holds else None}
    return JudgedLoops(loops, floor, exact, window, metrics_table(exp, loops, window, floors, exact, level))


def run_loops(exp: Experiment, stages: Stages, F: np.ndarray, observer, sink, sample: Sample, suffix: str = "",
              online=None) -> tuple[JudgedLoops, object]:
    """The loops with gain F judged at each look of closed_loop.paths (`LoopSettings.looks`): a fixed count is one
    look at the 95% level; auto runs the pilot's paths, judges every loop, and while a verdict is undetermined by
    an interval that holds 1 (`Verdict.needs`) or a few paths carry the closed (or online) loop's mean square
    (`needs_more`), adds paths up to the next look, until the last (closed_loop.max_paths). Every look's
    intervals are at 1 - 5% / L for L looks (Bonferroni): whichever look the run stops at, the chance that any
    of its intervals misses is at most 5%, as a fixed count's. Each path keeps its own streams, so a run that
    stops at P paths has the loops of a fixed run of P paths, row for row.

    The noise floor (the loop at rest, closed_loop.floor_paths paths) is measured once, before the looks.
    online: None, or online(first, stop) -> OnlineResult of those paths (`online.online_loop`), extended with
    the others. Returns the last look's JudgedLoops (`looks`: every look's paths, level and verdicts when there
    were several possible) and the online loop's result."""
    looks = exp.loop.looks
    level = look_level(len(looks))
    floor = None
    if F is not None and exp.loop.floor_paths > 0:
        with stages.timed("noise_floor" + suffix):
            floor = noise_floor(exp, observer, F)
    finite = lambda v: float(v) if np.isfinite(v) else None
    loops, online_result, record, first = {}, None, [], 0
    for look, stop in enumerate(looks):
        added = simulate_loops(exp, stages, F, observer, sink, sample, suffix, (first, stop)) if F is not None else {}
        if online is not None:
            with stages.timed("online"):
                part = online(first, stop)
            online_result = part if online_result is None else online_result.extended(part)
            added["online"] = part.loop
        loops = {name: LoopSummary.concat([loops[name], loop]) if name in loops else loop
                 for name, loop in added.items()}
        with stages.timed("metrics"):
            judged = judge_loops(exp, loops, floor, F, level)
        if len(looks) > 1:
            record.append({"paths": stop, "level": level,
                           **{row.experiment: {"verdict": row.verdict, "rate": [row.rate, row.rate_low, row.rate_high],
                                               "tail_khat": finite(row.tail_khat),
                                               "paths_needed": finite(row.paths_needed)}
                              for row in judged.metrics.itertuples()}})
        more = needs_more(judged.metrics)
        if not more or look == len(looks) - 1:
            break
        first = stop
    if len(looks) > 1:
        judged = dataclasses.replace(judged, looks=record, asking=more,
                                     metrics=budget_reached(judged.metrics, exp.loop.max_paths, more))
    return judged, online_result


def needs_more(metrics: pd.DataFrame) -> list[str]:
    """The loops whose verdict `verdict.asks_for_paths` (the closed and online loops feed their estimate back)."""
    asks = [asks_for_paths(row.verdict, row.paths_needed, row.tail_khat, row.experiment in ("closed_loop", "online"))
            for row in metrics.itertuples()]
    return metrics.loc[asks, "experiment"].tolist()


def budget_reached(metrics: pd.DataFrame, budget: int, asking: list[str]) -> pd.DataFrame:
    """The last look's metrics with the reason of each loop still `asking` (`needs_more`) saying the budget ended
    it."""
    out = metrics.copy()
    for i in out.index[out["experiment"].isin(asking)]:
        heavy = out.at[i, "verdict"] != "undetermined"
        out.at[i, "verdict_reason"] += (f"; closed_loop.max_paths = {budget} reached with a few paths still carrying "
                                        f"the mean square (tail k-hat {out.at[i, 'tail_khat']:.2f} > {HEAVY_TAIL:g})"
                                        if heavy else f"; budget reached: closed_loop.max_paths = {budget}")
    return out


CACHED_LOOPS = ("open_loop",)      # loops the stage cache keeps: the open loop does not depend on the gain, so
                                   # every design of a seed shares it; a closed loop is its run's own


def loop_chunks(sim: Simulation, name: str, workers: int, progress, stages: Stages):
    """(first path, Trajectories) of the loop's chunks in path order: a stage keyed by exactly what
    `simulate` reads (the Simulation: plant, observer, gain, disturbance, initial state, seed and the chunks of
    paths), simulated (`run_chunks`, in `workers` processes) or replayed from the stage cache."""
    simulated = lambda: ({"first": first, "trajectories": tr}
                         for first, tr, _ in run_chunks(sim, workers=workers, progress=progress))
    parts, reused = stages.streamed(name, simulated, simulation=sim, chunks=sim.chunks())
    steps = sim.d.shape[0]
    with closing(parts):
        for part in parts:
            if reused:
                progress(part["trajectories"].q.shape[1] * steps)
            yield part["first"], part["trajectories"]


def stream_chunk(exp: Experiment, name: str, tr: Trajectories, first: int, rows: pd.DataFrame, sink,
                 sample: Sample) -> LoopSummary:
    """One chunk of a loop out of memory: its trajectory rows (and, tracking full, its members) to the
    sink, the recorded paths' rows to `sample`; returns what the metrics keep."""
    recorded = exp.tracking.recorded_paths
    sink.append("trajectories", rows)
    sample.rows.append(rows[rows["path"] < recorded])
    if exp.tracking.level == "full":
        members = members_table(name, tr, first)
        sink.append("members", members)
        sample.members.append(members[members["path"] < recorded])
    return LoopSummary.of(tr, exp)


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


def noise_floor(exp: Experiment, enkf, F: np.ndarray) -> Floor:
    """The closed loop's noise floor: the loop with gain F and the EnKF observer started at rest (q_0 =
    0) without disturbance, closed_loop.floor_paths paths; its mean square over the second half of the
    horizon, whether it grows there, and which paths failed (`verdict.Floor`)."""
    K = exp.loop.horizon
    tr = Simulation.of(exp, enkf, F, root_seed(exp, "noise_floor"), d=np.zeros((K + 1, exp.model.m)),
                       q0=np.zeros(exp.plant.n), paths=min(exp.loop.floor_paths, exp.loop.looks[-1]),
                       filter_sees_d=True, keep_members=False).run()
    return Floor.of(np.sum(tr.q ** 2, axis=-1), tr.failed_at)


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


def metrics_table(exp: Experiment, loops: dict[str, LoopSummary], window: RateWindow, floors: dict[str, Floor | None],
                  exact: pd.DataFrame, level: float = LEVEL) -> pd.DataFrame:
    """Per loop: empirical rate over the rate window with its `level` interval (`verdict.rate_interval`), the
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
                             floor=loop_floor, open_loop=name == "open_loop", level=level)
        # the rate over the window as the paper measures it (no floor subtracted); the verdict's own rate is
        # over k_from..k_end with the floor's mean square subtracted
        interval = verdict.window_rate if np.isfinite(verdict.window_rate[0]) else \
            rate_interval(loop.sq[k_from], loop.sq[k_to], k_to - k_from, level=level)
        with np.errstate(all="ignore"):
            exact_rate = (ideal[k_to] / ideal[k_from]) ** (1 / (k_to - k_from)) if ideal.size else np.nan
            end_rms = float(np.sqrt(np.mean(loop.sq[k_to])))
        x_rmse, xi_rmse = loop.rms_of("x_err"), loop.rms_of("xi_err")
        rows.append({"experiment": name, "verdict": verdict.word, "verdict_reason": verdict.reason,
                     "status": loop.status, "rate": interval[0], "rate_low": interval[1], "rate_high": interval[2],
                     "k_from": k_from, "k_to": k_to, "verdict_rate": verdict.rate, "verdict_rate_low": verdict.low,
                     "verdict_rate_high": verdict.high, "k_end": verdict.k_end, "exact_rate": exact_rate,
                     "floor_rms": (0.0 if name == "open_loop" else np.nan) if loop_floor is None else loop_floor.rms,
                     "rms_k_to": end_rms, "tail_khat": tail_index(loop.sq[k_to]), "paths": loop.sq.shape[1],
                     "level": level, "paths_needed": np.nan if verdict.needs is None else float(verdict.needs),
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
                  "rms_k_to", "tail_khat", "paths", "level", "paths_needed", "failed_fraction", "x_error_rms",
                  "q_rms_final", *ESTIMATION)
