"""The online (learning-type) loop run beside the offline one: each path re-designs its gain from its own
xi_{k|k} (numerics.online.OnlineController), in chunks of paths like the other loops, and is compared with the
offline design of the same seed (the same plant samples and EnKF noise) and the optimum on the true plant.
"""
from __future__ import annotations

import dataclasses
from functools import partial

import numpy as np
import pandas as pd

from ...numerics.analysis import empirical_rate_sq, ms_rate
from ...numerics.enkf import EnKF, output_delay, truth_map, xi_ends
from ...numerics.modeling import nominal_gain
from ...numerics.online import OnlineController, rates, two_point_moments
from ...numerics.synthesis import SynthesisResult
from ...numerics.systems import MomentModel
from ...numerics.verdict import paired_losses
from ..config import Experiment
from ..montecarlo import LoopSummary, Simulation, run_chunks
from .design import design, safe_rate
from .loops import Sample, loop_observer, root_seed, stream_chunk
from .results import OnlineResult
from .stage import Stages
from .tables import carries_d, gain_columns, trajectory_table, with_gains

START_HALVINGS = 10


def online_loop(exp: Experiment, stages: Stages, sink, sample: Sample, first: int = 0,
                stop: int | None = None) -> OnlineResult:
    """The online closed loop of paths first..stop - 1 (None: every path of a fixed count): per-path gains
    re-designed from the path's own xi_{k|k}.

    In chunks of paths, and worker processes, like the other loops (`run_chunks`; one controller per
    chunk), rows streamed to the sink with the gain in use (F[i,j])."""
    stop = exp.loop.paths if stop is None else stop
    m, n = exp.model.m, exp.model.n
    enkf = online_observer(exp)
    F0, info = initial_gain(exp, enkf)
    K = exp.loop.disturbance.shape[0] - 1
    parts, controllers = [], []
    sim = Simulation.of(exp, enkf, F0, root_seed(exp, "online"), paths=stop, first_path=first)
    # the prior guess, as the nominal gain sees it: a thin window acts only where it agrees (OnlineController)
    A_guess, B_guess, _, _ = exp.plant.at(exp.identification.xi_guess)
    # a component the EnKF draws from its two-point law is modeled with that law's variance too
    make = partial(OnlineController, exp.model, exp.controller.online, F0, horizon=K, at_guess=(A_guess, B_guess),
                   two_point=enkf.two_point)
    with stages.progress("online", (stop - first) * (K + 1)) as progress:
        for first, tr, controller in run_chunks(sim, workers=exp.loop.workers, progress=progress, controller=make):
            count = tr.q.shape[1]
            history = controller.gain_history()
            in_use = np.stack([history[j][tr.gain_index[:, j]] for j in range(count)])     # (P, K+1, m, n)
            rows = with_gains(trajectory_table("online", tr, first, d_columns=carries_d(exp)),
                              in_use.reshape(count * (K + 1), m, n))
            parts.append(stream_chunk(exp, "online", tr, first, rows, sink, sample))
            controllers.append((first, controller))
    return OnlineResult(LoopSummary.concat(parts), controllers, info)


def initial_gain(exp: Experiment, enkf: EnKF) -> tuple[np.ndarray, dict]:
    """The online loop's gain before any model, F0 (m, n) (controller.initial: zero, nominal or given), and
    how the loop starts, for the summary's online_initial."""
    m, n = exp.model.m, exp.model.n
    initial = exp.controller.initial
    info = {"initial": initial if isinstance(initial, str) else "given",
            # the start before a path's first model, as the loop's EnKF has it (static_mean with observer = model)
            "start": "static_mean" if enkf.static_mean else "random_walk",
            "lag": exp.controller.online.lag, "output_delay": output_delay(exp.model).tolist(),
            "start_scale": enkf.start_scale}
    if exp.controller.online.probe > 0:              # the known excitation on u: amplitude, last step (None: never)
        info["probe"] = [exp.controller.online.probe, exp.controller.online.probe_until]
    F0 = initial if not isinstance(initial, str) else np.zeros((m, n))
    if isinstance(initial, str) and initial == "nominal":
        res, law = online_nominal(exp, enkf)
        info |= {"method": res.method, "status": res.status, "nominal_law": law, "rate_on_law": res.lam}
        if res.F is not None and np.all(np.isfinite(res.F)) and res.lam < 1:
            F0 = res.F
        else:
            info["used"] = "zero (no stabilizing nominal gain)"
    return F0, info


def controller_table(exp: Experiment, online: OnlineResult) -> pd.DataFrame:
    """Every decision of every path (the `controller` table): the initial gains (k = -1: in use from k = 0),
    then in order of k, with the exact rate of each gain on the true plant and its gain index (the initial
    gain is 0, then a path's adopted gains in order; -1: not adopted)."""
    p, m, n = exp.model.p, exp.model.m, exp.model.n
    Abar, Bbar = exp.plant.moment_factors(None)
    frames = []
    for offset, controller in online.controllers:
        d, count = controller.decisions(), controller.P
        with np.errstate(all="ignore"):
            rate_plant = rates(Abar, Bbar, np.nan_to_num(d.F, nan=np.inf)) if len(d.k) else np.zeros(0)
            rate_plant[~np.all(np.isfinite(d.F), axis=(1, 2))] = np.nan
            initial_plant = rates(Abar, Bbar, controller.F0)
        before = partial(initial_nan, count)
        rows = {"path": offset + np.concatenate([np.arange(count), d.path]),
                "k": np.concatenate([np.full(count, -1), d.k]),
                "adopted": np.concatenate([np.ones(count, bool), d.adopted]),
                "reason": np.concatenate([np.full(count, "initial", dtype=object), d.reason]),
                **{name: before(getattr(d, name)) for name in ("rate_model", "rate_current", "rate_worst",
                                                                "rate_current_worst", "rate_current_best",
                                                                "rate_current_guess")},
                "estimates": np.concatenate([np.zeros(count, int), d.estimates]),
                "rate_plant": np.concatenate([initial_plant, rate_plant])}
        mean = initial_nan(count, d.mean)
        rows |= {f"mean[{i}]": mean[:, i] for i in range(p)}
        rows |= {f"cov[{i},{j}]": before(d.cov[:, i, j]) for i in range(p) for j in range(p)}
        rows |= gain_columns(np.concatenate([controller.F0, d.F]).reshape(-1, m, n))
        frames.append(pd.DataFrame(rows))
    table = pd.concat(frames, ignore_index=True)
    table.insert(4, "gain_index", np.where(table["adopted"], table.groupby("path")["adopted"].cumsum() - 1, -1))
    return table.sort_values(["path", "k"], kind="stable", ignore_index=True)


def initial_nan(count: int, values: np.ndarray) -> np.ndarray:
    """values after `count` NaN (the initial gains' rows of the controller table)."""
    return np.concatenate([np.full((count, *values.shape[1:]), np.nan), values])


def analyse_online(exp: Experiment, stages: Stages, online: OnlineResult, paths: pd.DataFrame,
                   F_offline: np.ndarray | None, window: tuple[int, int]) -> OnlineResult:
    """The online loop against the offline loop of the same seed (`paths`: the paths table with the closed
    loop's rows; F_offline its gain) and the optimum on the true plant: its `controller` table, per path the
    first step at which it holds a gain stable in mean square on the true plant (-1: never) and the exact true
    rate of its final gain, and the metrics of the summary's `online` entry (rates over `window`)."""
    loop, table = online.loop, controller_table(exp, online)
    P = loop.failed_at.size
    adopted = table[table["adopted"]]
    final = adopted.groupby("path")["rate_plant"].last().reindex(range(P)).to_numpy()
    stable = adopted[adopted["rate_plant"] < 1].groupby("path")["k"].min().reindex(range(P))
    first = np.where(stable.isna(), -1, stable.fillna(0).to_numpy() + 1).astype(int)
    per_path = pd.DataFrame({"experiment": "online", "path": np.arange(P), "first_stable_k": first,
                             "final_rate_plant": final})
    # the optimal rate on the true plant: the better of Theorem 2's bisection and policy iteration
    # (policy iteration from F = 0 can stall on an open-loop unstable plant)
    truth = exp.plant.check_distribution(None)
    optimum = min((design(stages, exp.plant, truth, method, {}, exp.design.lmi_max_n, f"synthesis/plant/{method}")
                   for method in ("proposed", "policy_iteration")),
                  key=lambda res: res.lam if np.isfinite(res.lam) else np.inf)
    offline = safe_rate(exp.plant, None, F_offline) if F_offline is not None else np.nan
    q = np.nanpercentile(final, [10, 50, 90]) if np.isfinite(final).any() else [np.nan] * 3
    # paths lost by one loop alone (the two loops share each path's plant samples) and whether online loses
    # more than chance explains: the exact paired test (rare losses make two bare counts differ by chance)
    offline_paths = paths[paths["experiment"] == "closed_loop"].sort_values("path")
    lost = (paired_losses(loop.failed_at >= 0, offline_paths["failed_at"].to_numpy() >= 0)
            if len(offline_paths) == P else (np.nan,) * 3)
    metrics = {"final_rate_plant_q10": q[0], "final_rate_plant_median": q[1], "final_rate_plant_q90": q[2],
               "final_stable_fraction": float(np.mean(final < 1)),
               "first_stable_k_median": float(np.median(first[first >= 0])) if (first >= 0).any() else np.nan,
               "never_stable_fraction": float(np.mean(first < 0)),
               "adoptions_per_path": int((table["adopted"] & (table["k"] >= 0)).sum()) / P,
               # the k-window rate over the paths that did not diverge (the `rate` column is NaN
               # as soon as one path diverged)
               "rate_not_diverged": empirical_rate_sq(*(loop.sq[k, loop.failed_at < 0] for k in window),
                                                      window[1] - window[0])[0]
               if (loop.failed_at < 0).any() else np.nan,
               "offline_rate_plant": offline, "optimal_rate_plant": optimum.lam,
               "lost_online_only": lost[0], "lost_offline_only": lost[1], "lost_more_p": lost[2],
               **held_by_lost(loop, adopted)}
    return dataclasses.replace(online, controller=table, paths=per_path, metrics=metrics)


def held_by_lost(loop: LoopSummary, adopted: pd.DataFrame) -> dict:
    """The gains the lost paths held (each acted from the step after its adoption, before the loss): how many
    lost paths held one unstable on the true plant, and the worst rate held. All of them mean-square stable
    says that what grew is the loop through the EnKF's estimate, not the ideal loop of any one gain (switching
    between stable gains is not covered by their rates)."""
    failed_at = loop.failed_at[adopted["path"].to_numpy()]
    held = adopted[(failed_at >= 0) & (adopted["k"].to_numpy() + 1 < failed_at)]
    worst_held = held["rate_plant"].fillna(np.inf).groupby(held["path"]).max()    # a NaN rate counts as unstable
    return {"lost_held_unstable": float((~(worst_held < 1)).sum()) if len(worst_held) else np.nan,
            "lost_held_rate_max": float(worst_held.max()) if len(worst_held) else np.nan}


def online_nominal(exp: Experiment, enkf: EnKF) -> tuple[SynthesisResult, str]:
    """The online loop's nominal gain and the law it was designed on: "start", the mean-square LQR at the
    guess with the spread xi has in the loop's EnKF before any output (`EnKF.start_cov`; a two-point
    component the variance its mean fixes), in the model's terms; or "guess", the deterministic design at
    the guess (`nominal_gain`) where the start's law admits no stabilizing gain or the model's xi is not an
    affine map of the plant's. The EnKF draws its start from that law, so a gain it destabilises leaves the
    ensemble's spread growing without bound, and the state estimate with it (docs/online-rounds.md)."""
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
    estimate fed back is worse than none. The check guards the other way: narrowing moves only the Gaussian
    components, not a two-point one, whose spread its mean fixes, so a narrowed law can admit a gain that leans
    on the Gaussian components' certainty and holds the whole law worse than the deterministic design
    (the measurements behind both: docs/online-rounds.md)."""
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

