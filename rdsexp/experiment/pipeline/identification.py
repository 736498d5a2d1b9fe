"""Identification and modeling: the EnKF on psi = [x; xi] filters an identification run (simulated on the plant
under an M-sequence input, or the recorded (u, y) of a data run), and the moments of xi are modeled from
xi_{k|k} over the window k = K0..K0+K1: as the paper does (Sec. IV, identification.estimator = paper, with a
bootstrap of the window as their uncertainty), or by simulating that estimator on the model (simulated,
`numerics.indirect`: the posterior of the law given what the window reads).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
from scipy.stats import norm

from ...numerics import indirect
from ...numerics.enkf import xi_ends
from ...numerics.modeling import (
    correlation_z,
    correlations,
    model_distribution,
    moment_draws,
    nominal_gain,
    path_moment_draws,
    path_moments,
    time_mean,
)
from ...numerics.simulation import PlantNoise, Trajectories, bytes_per_path
from ...numerics.systems import AffineRandomSystem, MomentModel
from ...numerics.verdict import FAILURES
from ..config import Experiment
from ..montecarlo import MEMORY_BUDGET, Simulation
from .design import safe_rate
from .results import Identified, Uncertainty
from .stage import Stages

UNCERTAINTY_STREAM = 3   # SeedSequence([seed, 3]): the modeling window's bootstrap (stages use spawn keys 0-2)
REPLICATE_STREAM = 4     # [seed, 4, round]: the simulated estimator's replicates and their laws (their own streams)
POSTERIOR_ROUNDS = 2, 4  # the simulated estimator's rounds with a posterior where replicates run as many paths as
                        # the identification (after a first round of one path each), and where a data run's
                        # replicates of one path are averaged to its recorded paths' mean, which pins the law down
                        # far inside the box of two rounds (a user's simulator, 80 paths: median errors 0.09 / 0.18
                        # with 2 rounds, 0.06 / 0.11 with 4)
NOISE_BOX = (0.0, 10 ** 0.5)  # a data run's prior on the noise's sd over the sd the EnKF assumes (`Replay.noisy`):
                        # uniform, so the noise scale (its square) from 0 to 10. Not log10 of the scale: below the
                        # outputs' own spread the summary hardly moves with the noise, a plateau the quadratic
                        # emulator bent into a false mode at the box's low edge (its interval excluded the truth by
                        # 1e5 on a data set whose noise the EnKF assumed). Uniform in the sd, not the variance: a
                        # noise the data cannot tell from none keeps 0 in its interval
MISFIT = 4.0, 1e-3     # status misfit: the data's summary off the posterior mean law's (`indirect.synthetic_posterior`)
                       # by more than 4 sds in a component, or in a summary of k components read, where the larger,
                       # than the normal's two-sided 1 - 1e-3 / k quantile: at most that level for the whole summary
                       # whatever its length (`misfit_bound`: 4 sds up to 16 components, 4.15 for 30, 4.26 for 50)
PASS_TOL = 1e-3        # iterated identification: stop when the moments move less than this (relative)


def identify_and_model(exp: Experiment, stages: Stages, seed) -> Identified:
    """The identification run(s) on the plant and the moments they model: the identification stage's value
    (the stage cache stores it whole)."""
    F_id, info = identification_feedback(exp)
    # the identification input is added on top of the feedback; the EnKF is told the applied input
    total = exp.identification.covariance == "total"
    identify = lambda F, enkf=exp.filter.enkf: Simulation.of(
        exp, enkf, F, seed, d=exp.identification.input, paths=exp.identification.paths,
        filter_sees_d=True).run(keep_xi_cov=total)
    ident = identify(F_id)
    diverged = np.isin(ident.failure, ("diverged", "filter_diverged"))
    if info.get("used") == "open_loop" and diverged.any():
        # auto chose the open loop on the guess, which knows no spread of xi (the spread only raises
        # the mean-square rate): the plant grew until it, or first the EnKF's estimate of it, diverged
        # (random plants: 3 of 200 open-loop mean-square unstable plants stable at their mean),
        # so identify again under nominal feedback
        F_id, retry = identification_feedback(exp, force_nominal=True)
        if F_id is not None:
            first = int(np.flatnonzero(diverged)[0])
            info = retry | {"open_loop_diverged_at": int(ident.failed_at[first]),
                            "open_loop_failure": str(ident.failure[first])}
            ident = identify(F_id)
    if exp.identification.estimator == "simulated" and exp.model.p:
        q0 = exp.q0 if exp.q0.shape == (exp.model.n,) else np.zeros(exp.model.n)
        return simulated_moments(exp, stages, ident, lambda enkf: identify(F_id, enkf),
                                 Replay(exp.identification.input, F_id, q0, paths=exp.identification.paths), info)
    return model_moments(exp, stages, ident, lambda enkf: identify(F_id, enkf), info)


@dataclasses.dataclass(frozen=True)
class Replay:
    """How the simulated estimator's replicates repeat the identification: the input d, (K+1, m) or one per
    recorded path (K+1, P_rec, m), replicate r replaying recorded path r mod P_rec; the feedback F (m, n) (None:
    the inputs as they are); the plant's initial state q0 (n,). noisy (a data run): the replicates' plant carries
    enkf.Q's x block and enkf.R as process and output noise, times a scale whose square root theta's last component
    estimates (in NOISE_BOX): recorded outputs are noisy by an amount nobody states, and the summary depends on it.
    paths: the identification runs of each replicate, every one with its own draws of the replicate's law, whose
    summaries it averages as the observed one averages those of its identification.paths runs."""

    d: np.ndarray
    F: np.ndarray | None
    q0: np.ndarray
    noisy: bool = False
    paths: int = 1


def model_recorded(exp: Experiment, stages: Stages, ident: Trajectories, seed) -> Identified:
    """The modeling stage of a data run on its recorded identification `ident`, with either estimator. The
    simulated estimator's replicates replay each recorded path's inputs as they were applied, from the EnKF's
    initial guess of x, with the noise the EnKF assumes times an estimated scale (`Replay`)."""
    recorded = exp.data.identification
    identify = lambda enkf: identify_recorded(exp, recorded, seed, enkf=enkf)
    feedback = {"mode": "recorded", "used": "the recorded inputs"}
    if exp.identification.estimator == "simulated" and exp.model.p:
        replay = Replay(recorded.u, None, exp.filter.psi0[:exp.model.n], noisy=True)
        return simulated_moments(exp, stages, ident, identify, replay, feedback)
    return model_moments(exp, stages, ident, identify, feedback)


def simulated_moments(exp: Experiment, stages: Stages, ident: Trajectories, identify, replay: Replay,
                      feedback: dict) -> Identified:
    """The modeling stage of identification.estimator = simulated (`numerics.indirect`): the paper's estimator on
    the identification run is the summary (several paths: the mean of theirs); rounds of identification.replicates
    runs of the model as `replay` says, each path drawing xi from its own law, give the posterior of the law's
    means, stds and correlations (and of a data run's noise scale): the first from the prior box, each next one from
    the box the previous posterior spans. A replicate whose identification failed, as the observed one did not, is
    left out; where too few were identified to regress on, the next round draws from the box the identified ones
    span (`posterior_rounds`). The posterior mean is the model, its weighted draws the uncertainty
    (`Identified.posterior`); where no law in the box reproduces the summary (a component of it beyond MISFIT sds of
    the posterior mean law's), the window's moments are kept and the status says misfit.

    Where the random-walk run failed (its xi drifted until the estimate, or the plant under its feedback, diverged),
    the summary is read from a run of `identify(enkf)` whose EnKF draws each step's xi i.i.d. about the prior guess
    with enkf.Q's xi block (Assumption 1; an i.i.d. xi cannot drift), and so are the replicates'."""
    settings, model = exp.identification, exp.model
    enkf, summary_filter = exp.filter.enkf, "random_walk"
    with stages.timed("modeling"):
        summary, failure = identified_moments(exp, ident)
        if summary is None:
            n = model.n
            enkf = dataclasses.replace(enkf, xi_prior=MomentModel(mean=exp.filter.psi0[n:], cov=enkf.Q[n:, n:]))
            ident, summary_filter = identify(enkf), f"i.i.d. about the prior guess (the random walk's {failure})"
            summary, failure = identified_moments(exp, ident)
        if summary is None:
            return Identified(ident, None, failure, feedback, covariance=settings.covariance)
        info = {"name": "simulated", "replicates": settings.replicates, "replicate_laws": settings.replicate_laws,
                "prior_width": settings.prior_width,
                "summary_mean": summary.mean.tolist(),
                "summary_std": np.sqrt(np.diag(summary.cov)).tolist(), "summary_filter": summary_filter}
        ends, low, high = two_point_ends(exp)
        per_path = summary_statistics(exp, ident)
        per_path = per_path[np.all(np.isfinite(per_path), axis=1)]       # the paths whose identification failed out
        if not len(per_path):       # (an output identically 0 has no log mean square): nothing to match
            info |= {"usable": [], "fallback": "no path's summary is finite (an output identically 0?): the "
                                                "window's moments of xi_{k|k} kept"}
            return Identified(ident, summary, "", feedback, covariance=settings.covariance, estimator=info)
        s_obs = per_path.mean(axis=0)           # one path's own summary, bit for bit (x / 1)
        prior = indirect.prior_box(s_obs[:2 * model.p], ends, low, high, settings.prior_width)
        if replay.noisy:
            prior = tuple(np.append(edge, bound) for edge, bound in zip(prior, NOISE_BOX))
        fit = fitted(prior, ends, settings.replicates)
        if len(per_path) > 1:
            info["summary_paths"] = len(per_path)
        if replay.noisy:
            info["recorded"] = True
        if replay.paths > 1:
            info["replicate_paths"] = replay.paths
        rounds = POSTERIOR_ROUNDS[len(per_path) > replay.paths]     # (the first of one path each)
        planned = sum(planned_paths(r, rounds, replay.paths) for r in range(1, rounds + 1))
        with stages.progress("modeling", settings.replicates * planned) as progress:
            posterior, info["usable"], z = posterior_rounds(exp, enkf, replay, s_obs, len(per_path), prior,
                                                            (ends, low, high), fit, progress)
        xi_of = lambda draws: draws[:, :len(prior[0]) - replay.noisy]      # theta's xi part (not a noise scale)
        spread_of = lambda xi, over: Uncertainty(*indirect.moments_of(xi, ends, low, high), settings.resamples, 0, over)
        # where no posterior matched the summary, the window's moments are kept with the prior box as their
        # uncertainty: what is known without the match (the window's bootstrap knows nothing of the estimator's bias)
        box = lambda: spread_of(xi_of(indirect.uniform_draws(*prior, settings.resamples,
                                                             [exp.seed, UNCERTAINTY_STREAM])),
                                "the prior box") if settings.resamples else None
        if posterior is None:       # the window's moments, said so
            info["fallback"] = (f"{max(info['usable'])} of {settings.replicates} replicates identified (needs "
                                f"{10 * (fit.sum() + 1)}): the window's moments of xi_{{k|k}} kept")
            return Identified(ident, summary, "", feedback, covariance=settings.covariance, estimator=info,
                              posterior=box())
        bound = misfit_bound(np.count_nonzero(z))       # (z = 0: a summary not read, or that no replicate varies)
        if np.max(np.abs(z)) > bound:      # no law in the box reproduces what the data read: the window's moments
            worst = int(np.argmax(np.abs(z)))
            info["misfit"] = {"summary": summary_names(model)[worst], "z": float(z[worst]), "bound": round(bound, 2)}
            return Identified(ident, summary, "", feedback, covariance=settings.covariance, estimator=info,
                              posterior=box())
        draws, w = posterior
        info |= diagnostics(draws, w, prior, ends, replay.noisy)
        xi_part = xi_of(draws)
        correlated = fit[indirect.correlation_columns(ends)].all()
        if model.p > 1 and not correlated:
            info["correlations"] = (f"not fitted: {model.p * (model.p - 1) // 2} partial correlations would take theta "
                                    f"to {len(prior[0])} components, for which {settings.replicates} replicates are "
                                    "less than twice the quadratic fit's minimum (identification.replicates="
                                    f"{2 * indirect.quadratic_replicates(len(prior[0]))} fits them); their interval "
                                    "is the prior box's, the model independent")
        mean, cov = indirect.posterior_moments(xi_part, w, ends, low, high, correlated)
        spread = None
        if settings.resamples:          # the uncertainty: identification.resamples draws of the posterior
            picks = indirect.weighted_draws(xi_part, w, settings.resamples, [exp.seed, UNCERTAINTY_STREAM])
            spread = spread_of(picks, "simulated replicates")
    return Identified(ident, MomentModel(mean=mean, cov=cov), "", feedback, covariance=settings.covariance,
                      estimator=info, posterior=spread)


def posterior_rounds(exp: Experiment, enkf, replay: Replay, s_obs: np.ndarray, paths: int, box,
                     laws, fit: np.ndarray, progress=None) -> tuple[tuple | None, list[int], np.ndarray | None]:
    """The replicate rounds of `simulated_moments`: (draws (N, d), weights (N,)) of the posterior, or None where no
    round identified enough replicates to regress on (10 per regressor), each round's count of identified
    replicates, and where s_obs lies among the summaries of the posterior mean's law (`indirect.synthetic_posterior`).
    Each round after the first draws from the box the previous posterior spans (POSTERIOR_ROUNDS of them; one more
    where the first round's identifications mostly failed, and one more where the last posterior presses an edge its
    own round's box drew inside the prior's, `indirect.pressed`, whose components' box may then reach past it).
    s_obs: the mean of `paths` paths' summaries; a replicate's is the mean of fewer (a data run's: one) or as many,
    and the likelihood's covariance scales by the ratio. Replicates of replay.paths > 1 paths (a simulated run's
    identification.paths) run that many only once a first posterior has placed the box: the rounds before run one
    path each, which places the box well enough (four paths on the calibration plants: the same errors and coverage
    as two rounds of every path after it, in two thirds of the time). `laws`: (ends, low, high); `fit`: the
    components of theta the regression fits (`fitted`). progress(paths, more=0): called as each chunk is done, and
    with `more` where a round runs other paths than the bar's total counted (`planned_paths`)."""
    settings = exp.identification
    posterior, rounds, usable, z, prior = None, 0, [], None, box
    wanted = POSTERIOR_ROUNDS[paths > replay.paths]
    # the window's correlations of xi are read where theta's are fitted (else they only hold the replicates' random
    # correlations, which the regression leaves in its residual)
    correlated = fit[indirect.correlation_columns(laws[0])].all()
    read = np.array([correlated or not name.startswith("window correlation") for name in summary_names(exp.model)])
    # a noisy replay's noise sd (theta's last component): the emulator regresses on its square, the noise's
    # variance, in which the summary moves smoothly from the plateau of noise below the outputs' own spread
    squared = (np.arange(fit.size) == fit.size - 1)[fit] if replay.noisy else None
    for round_ in range(1, wanted + 3):
        theta = indirect.uniform_draws(*box, settings.replicates, [exp.seed, REPLICATE_STREAM, round_])
        runs = replay if posterior is not None else dataclasses.replace(replay, paths=1)
        planned = planned_paths(round_, wanted, replay.paths)       # what the bar's total counted for this round
        if progress is not None and runs.paths != planned:       # a round beyond the planned ones, or a failed one's
            progress(0, more=(runs.paths - planned) * settings.replicates)
        s = replicate_summaries(exp, enkf, runs, theta, *laws, round_, progress)[:, read]
        ok = np.all(np.isfinite(s), axis=1)
        usable.append(int(ok.sum()))
        if ok.sum() >= 10 * (fit.sum() + 1):
            # s_obs is the mean of `paths` runs' summaries, a replicate's of runs.paths. A noisy replay's first
            # posterior only places the box, by an emulator of the whole noise range, where the summary bends (a
            # plateau, then a rise): read at one path's precision, its bias does not place the box off the truth
            ratio = 1.0 if replay.noisy and posterior is None else runs.paths / paths
            draws, w, z_read = indirect.synthetic_posterior(theta[:, fit], s, s_obs[read], box[0][fit], box[1][fit],
                                                            ratio, seed=[exp.seed, REPLICATE_STREAM, round_, 1],
                                                            squared=squared)
            z = np.zeros(s_obs.size)        # (a summary not read: no evidence of a misfit)
            z[read] = z_read
            # the components not fitted keep their prior, the box
            posterior = indirect.uniform_draws(*box, len(w), [exp.seed, REPLICATE_STREAM, round_, 3]), w
            posterior[0][:, fit] = draws
            # a posterior that presses an edge this round's box drew inside the prior's (a box placed on a rougher
            # posterior) is cut by it, not by the prior: in those components the next box may reach past this one,
            # up to the prior's, and one more round (POSTERIOR_ROUNDS + 1) draws from the box it then spans
            pressed = indirect.pressed(*posterior, *box, *prior)
            limits = np.where(pressed, prior[0], box[0]), np.where(pressed, prior[1], box[1])
            box, rounds = indirect.posterior_box(*posterior, *limits), rounds + 1
            if rounds > wanted or (rounds == wanted and not pressed.any()):
                break
        elif ok.sum() >= 2 and posterior is None:
            # most laws of the box make the identification diverge, as the observed one did not: the next round
            # draws from the box the identified ones span
            box = indirect.posterior_box(theta[ok], np.ones(ok.sum()), *box)
        else:
            break
    return posterior, usable, z


def fitted(box, ends: np.ndarray, replicates: int) -> np.ndarray:
    """(d,) bool: the components of theta in the prior `box` (lo, hi) that the regression fits and the posterior
    reads: all, or all but the correlations (`indirect.correlation_columns`) where the replicates afford less than
    twice the quadratic fit's minimum in all of them (`indirect.quadratic_replicates`: 2 components of xi at 400
    replicates fit them, 3 do not, 3 at 600 do); the replicates then draw those from their box all the same, so that
    the regression's residual holds what they do, and their posterior is the box. (Fitted with 3 components at 400
    replicates, the p (p - 1) / 2 = 3 weakly told correlations cost the means and stds: `ok` on 41 of 66 runs of
    the calibration plants against 51, the end-to-end 90th percentile x1.107 against x1.022.)"""
    fit = np.ones(box[0].size, dtype=bool)
    if 2 * indirect.quadratic_replicates(fit.size) > replicates:
        fit[indirect.correlation_columns(ends)] = False
    return fit


def misfit_bound(components: int) -> float:
    """The |z| beyond which one of `components` summary components reads misfit (MISFIT)."""
    sds, level = MISFIT
    return max(sds, float(norm.isf(level / (2 * max(components, 1)))))


def planned_paths(round_: int, wanted: int, paths: int) -> int:
    """The paths per replicate `posterior_rounds` plans for round `round_` (from 1) of `wanted`: one in the first,
    `paths` in the others, none beyond them (a pressed box's extra round, a failed round's repeat are unplanned)."""
    return 0 if round_ > wanted else 1 if round_ == 1 else paths


def diagnostics(draws: np.ndarray, w: np.ndarray, prior, ends: np.ndarray, noisy: bool = False) -> dict:
    """The posterior's account for the summary and the status: its effective number of replicates, how much the
    data narrowed each component's prior box (`indirect.narrowed`), and the components of xi's law at the box's
    edge (`at_prior_edge`) or hardly narrowed (`weakly_identified`, above `indirect.WEAK`). noisy: the last
    component is a data run's noise sd ratio, reported (`noise_scale`: its posterior median and 95% interval,
    times the noise the EnKF assumes), not a status (its box's low end is no noise at all)."""
    p = ends.size
    names = [f"xi mean {i + 1}" for i in range(p)] + [f"xi std {i + 1}" for i in np.flatnonzero(~ends)]
    ratio = indirect.narrowed(draws, w, *prior)
    out = {"effective": float(w.sum() ** 2 / (w ** 2).sum()), "narrowed": ratio.tolist()}
    xi = slice(0, len(names))
    edge = indirect.at_the_edge(draws[:, xi], w, prior[0][xi], prior[1][xi], ends)
    if edge.any():                  # the box, not the data, stops the posterior there
        out["at_prior_edge"] = [names[i] for i in np.flatnonzero(edge)]
    weak = ratio[xi] > indirect.WEAK
    if weak.any():                  # the data hardly narrowed the prior box: the outputs do not tell
        out["weakly_identified"] = [names[i] for i in np.flatnonzero(weak)]
    if noisy:
        q = indirect.weighted_quantiles(draws[:, -1], w, [0.025, 0.5, 0.975])
        out["noise_scale"] = {"median": float(q[1] ** 2), "low": float(q[0] ** 2), "high": float(q[2] ** 2),
                              "box": [prior[0][-1] ** 2, prior[1][-1] ** 2]}
    return out


def two_point_ends(exp: Experiment) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ends (p,) bool, low (p,), high (p,)): the components whose law takes only the two ends of the support box
    the plant file's family states (`enkf.xi_ends`: a Bernoulli link; a data run: its model file's prior guess),
    as the online loop models them; their std is fixed by their mean."""
    p, bounds = exp.model.p, exp.filter.enkf.xi_bounds
    family = exp.plant if exp.data is None else exp.data.prior
    ends = xi_ends(exp.model, family) if bounds is not None and family is not None else None
    if ends is None or not ends.any():
        return np.zeros(p, dtype=bool), np.zeros(p), np.ones(p)
    low, high = bounds
    ends = ends & (high > low)
    return ends, np.where(ends, low, 0.0), np.where(ends, high, 1.0)


def replicate_summaries(exp: Experiment, enkf, replay: Replay, theta: np.ndarray, ends, low, high,
                        round_: int, progress=None) -> np.ndarray:
    """(R, S): the `summary_statistics` of R replicates of the identification of the model as `replay` says,
    replicate r's replay.paths runs drawing xi from theta[r] (`indirect.path_laws`: its means, stds and
    correlations; a noisy replay's last column is its noise sd ratio) in one law of random shape
    (identification.replicate_laws = random_shapes, `indirect.random_shapes`, from [seed, REPLICATE_STREAM, round_,
    2]) with `enkf`, averaged over the runs that did not fail; NaN where every run failed. In chunks of paths within
    the Monte Carlo's memory budget (each path its own streams); progress(paths) after each chunk."""
    model, settings = exp.model, exp.identification
    total = settings.covariance == "total"
    shapes = None
    if settings.replicate_laws == "random_shapes":      # one shape per replicate, shared by its paths
        shapes = indirect.random_shapes(len(theta), model.p, [exp.seed, REPLICATE_STREAM, round_, 2])
        shapes = shapes.take(np.repeat(np.arange(len(theta)), replay.paths))
    theta = np.repeat(theta, replay.paths, axis=0)          # replicate r: paths r P .. r P + P - 1
    R, n = len(theta), model.n
    d = replay.d if replay.d.ndim == 2 else replay.d[:, np.arange(R) % replay.d.shape[1]]
    sim = Simulation.of(exp, enkf, replay.F, np.random.SeedSequence([exp.seed, REPLICATE_STREAM, round_]),
                        plant=model, q0=replay.q0, d=d, paths=R, filter_sees_d=True)
    per_path = bytes_per_path(model, sim.observer, ensemble_size=exp.filter.ensemble_size,
                              horizon=d.shape[0] - 1, keep_members=False, block=16)
    size = int(max(1, MEMORY_BUDGET // (3 * per_path)))
    laws = theta[:, :theta.shape[1] - replay.noisy]
    out = []
    for first in range(0, R, size):
        part = slice(first, first + size)
        plant = AffineRandomSystem(model.A, model.B, model.C, model.D,
                                   xi_dist=indirect.path_laws(laws[part], ends, low, high,
                                                              None if shapes is None else shapes.take(part)))
        chunk = dataclasses.replace(sim, plant=plant, d=d if d.ndim == 2 else d[:, part])
        noise = None
        if replay.noisy:
            scale = theta[part, -1, None, None] ** 2
            noise = PlantNoise(scale * enkf.Q[:n, :n], scale * enkf.R)
        out.append(summary_statistics(exp, chunk.run(first, len(laws[part]), keep_xi_cov=total, plant_noise=noise)))
        if progress is not None:
            progress(len(laws[part]))
    s = np.concatenate(out).reshape(R // replay.paths, replay.paths, -1)
    finite = np.all(np.isfinite(s), axis=2, keepdims=True)
    with np.errstate(invalid="ignore"):
        return np.where(finite, s, 0.0).sum(axis=1) / np.where(finite.any(axis=1), finite.sum(axis=1), np.nan)


def summary_names(model) -> list[str]:
    """The names of `summary_statistics`' columns."""
    return [*(f"window mean of xi {i + 1}" for i in range(model.p)),
            *(f"window std of xi {i + 1}" for i in range(model.p)),
            *(f"window correlation of xi {i + 1} and xi {j + 1}" for i, j in zip(*np.tril_indices(model.p, -1))),
            *(f"log mean square of y[{i}]" for i in range(model.ny)),
            *(f"log mean square of innovation {i}" for i in range(model.ny)),
            *(f"lag-1 correlation of y[{i}]" for i in range(model.ny)),
            *(f"correlation of y[{i}] and y[{j}]" for i in range(model.ny) for j in range(i + 1, model.ny))]


def summary_statistics(exp: Experiment, tr: Trajectories) -> np.ndarray:
    """(P, p (p + 3) / 2 + 2 ny + ny (ny + 1) / 2): what the simulated estimator matches, per identification path:
    the paper estimator's mean, std and correlations (Fisher's z) of xi over the window (eq. sample-mean, with
    identification.covariance); the log mean square of each output and of the EnKF's innovation
    y_k - C x_{k|k-1} - D u_k there (the spread of xi moves the outputs' energy, which the filtered means of one
    output may not show); and the outputs' lag-1 and cross correlations (`modeling.correlation_z`). NaN where the
    path failed."""
    settings, model = exp.identification, exp.model
    window = slice(settings.K0, settings.K0 + settings.K1 + 1)
    total = settings.covariance == "total"
    mean, cov = path_moments(tr.xi(tr.psi_filt_mean), settings.K0, settings.K1, tr.xi_filt_cov if total else None)
    x, xi = tr.x(tr.psi_pred_mean)[window], tr.xi(tr.psi_pred_mean)[window]
    y, u = tr.y[window], tr.u[window]
    # y - C(xi) x - D(xi) u, C(xi) = C[0] + sum_j xi_j C[j], as elementwise products summed per row: a path's
    # numbers whatever the other paths in the batch (a batched matrix product rounds by the batch's size)
    apply = lambda M, v: (M * v[..., None, :]).sum(axis=-1)
    coefficients = np.concatenate([np.ones(xi.shape[:-1] + (1,)), xi], axis=-1)
    innovation = y - sum(c[..., None] * (apply(Cj, x) + apply(Dj, u))
                         for c, Cj, Dj in zip(np.moveaxis(coefficients, -1, 0), model.C, model.D))
    with np.errstate(divide="ignore", invalid="ignore"):
        energy = np.log(np.concatenate([time_mean(y ** 2), time_mean(innovation ** 2)], axis=1))
    # the second-order moments system identification reads: each output's lag-1 correlation (the mean dynamics)
    # and the outputs' correlations with each other
    ny = model.ny
    outputs_z = [*(correlation_z(y[1:, :, i], y[:-1, :, i]) for i in range(ny)),
                 *(correlation_z(y[:, :, i], y[:, :, j]) for i in range(ny) for j in range(i + 1, ny))]
    xi_z = np.arctanh(np.clip(correlations(cov), -np.tanh(20.0), np.tanh(20.0)))
    return np.concatenate([mean, np.sqrt(np.einsum("pii->pi", cov)), xi_z, energy, np.stack(outputs_z, axis=1)],
                          axis=1)


def model_moments(exp: Experiment, stages: Stages, ident: Trajectories, identify, feedback: dict) -> Identified:
    """The modeling stage: the moments of xi from the identification's estimates (`identified_moments`), with
    identification.xi_model: iterated the passes that filter again with each pass's prior (`identify(enkf)`)."""
    passes = None
    with stages.timed("modeling"):
        dist, failure = identified_moments(exp, ident)
        if exp.identification.xi_model == "iterated" and exp.model.p:     # (nothing to iterate without xi)
            ident, dist, failure, passes = iterate_identification(exp, identify, ident, dist, failure)
    return Identified(ident, dist, failure, feedback, passes, exp.identification.covariance)


def identified_moments(exp: Experiment, ident: Trajectories) -> tuple[MomentModel | None, str]:
    """The moments modeled from an identification run's xi_{k|k} over the window K0..K0+K1
    (identification.covariance), or (None, why not). Several paths (identification.paths, or recorded): the paths
    whose EnKF estimate failed are left out (`usable_paths`; the summary says how many), unless every one failed."""
    xi = ident.xi(ident.psi_filt_mean)                  # (K+1, P, p): the simulated or recorded paths
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


def left_out_paths(exp: Experiment, identified: Identified) -> dict | None:
    """The identification paths (simulated or recorded) left out of the modeling (`identified_moments`): how
    many, of how many, and why; None where every path was used or there is no model."""
    ident = identified.trajectories
    bad = ~usable_paths(exp, ident)
    if not bad.any() or identified.moments is None:
        return None
    reasons = pd.Series(ident.failure[bad]).replace("", "the filtered xi is not finite").value_counts()
    return {"count": int(bad.sum()), "of": int(bad.size), "reasons": {str(r): int(c) for r, c in reasons.items()}}


def select_paths(tr: Trajectories, keep: np.ndarray) -> Trajectories:
    """The paths `keep` ((P,) bool) of tr (path axis 1 of the (K+1, P, ...) arrays, 0 of the per-path ones)."""
    pick = lambda name, v: None if v is None else (v[keep] if name in ("failed_at", "failure") else v[:, keep])
    return Trajectories(**{f.name: tr.n if f.name == "n" else pick(f.name, getattr(tr, f.name))
                           for f in dataclasses.fields(Trajectories)})


def iterate_identification(exp: Experiment, identify, ident, dist, failure: str):
    """identification.xi_model = iterated: passes whose EnKF draws each step's xi i.i.d. from the
    previous pass's moments (Assumption 1, `EnKF.xi_prior`), so that the next output estimates it, and
    whose modeled moments are the next pass's prior, until mean and standard deviations change by less
    than PASS_TOL (relative to the largest standard deviation) or identification.passes are done: the
    moments as a fixed point of their own estimation. Without a first model (the random-walk pass
    failed) the first prior is xi at the initial ensemble's with enkf.Q's xi block as covariance.
    Returns (the last successful pass's run, moments, failure, info for the summary)."""
    n = exp.model.n
    prior = dist if dist is not None else MomentModel(mean=exp.filter.psi0[n:], cov=exp.filter.enkf.Q[n:, n:])
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


def moment_uncertainty(exp: Experiment, identified: Identified) -> Uncertainty | None:
    """The modeled moments' uncertainty: identification.resamples bootstrap draws of the modeling window of the
    run the moments come from (`modeling.moment_draws`: moving blocks of one path's window; `path_moment_draws`:
    over the identification paths), seeded by the run's seed. None without resamples or without a model."""
    settings, ident = exp.identification, identified.trajectories
    if identified.posterior is not None:
        return identified.posterior
    if identified.moments is None or not settings.resamples or not exp.model.p:
        return None
    total = settings.covariance == "total"
    ok = usable_paths(exp, ident)
    if ident.failed_at.size > 1 and ok.any() and not ok.all():        # paths whose estimate failed
        ident = select_paths(ident, ok)
    xi, xi_cov = ident.xi(ident.psi_filt_mean), ident.xi_filt_cov if total else None
    if xi.shape[1] > 1:             # several paths: a bootstrap over the paths
        mean, cov = path_moment_draws(xi, settings.K0, settings.K1, xi_cov, resamples=settings.resamples,
                                      seed=[exp.seed, UNCERTAINTY_STREAM])
    else:
        mean, cov = moment_draws(xi[:, 0], settings.K0, settings.K1, None if xi_cov is None else xi_cov[:, 0],
                                 resamples=settings.resamples, block=settings.block,
                                 seed=[exp.seed, UNCERTAINTY_STREAM])
    return Uncertainty(mean, cov, settings.resamples, settings.block, "paths" if xi.shape[1] > 1 else "window blocks")


def noise_sensitivity(exp: Experiment, identified: Identified, uncertainty: Uncertainty | None,
                      remodel) -> dict | None:
    """The moments modeled again (`remodel(exp)`: the whole modeling stage, the same seeds) with the noise the EnKF
    assumes, enkf.Q's x block and enkf.R, scaled by each of identification.noise_sensitivity's factors: the
    moments depend on it, and a data run cannot know the noise its data carry. Returns the summary entry (the
    factors with 1 among them, the modeled xi mean and std (factors, p) at each, their statuses, and the largest
    range of a mean or std over the factors in units of its bootstrap sd), or None without factors or a model."""
    scales = exp.identification.noise_scales
    if not scales or identified.moments is None or not exp.model.p:
        return None
    n, base = exp.model.n, exp.filter.enkf
    models = {1.0: identified}
    for c in scales:
        Q = base.Q.copy()
        Q[:n, :n] *= c
        enkf = dataclasses.replace(base, Q=Q, R=c * base.R)
        models[float(c)] = remodel(dataclasses.replace(exp, filter=dataclasses.replace(exp.filter, enkf=enkf)))
    order = sorted(models)
    stds = lambda m: np.sqrt(np.diag(m.cov)) if m is not None else np.full(exp.model.p, np.nan)
    mean = np.array([models[c].moments.mean if models[c].moments is not None else np.full(exp.model.p, np.nan)
                     for c in order])
    std = np.array([stds(models[c].moments) for c in order])
    out = {"scales": order, "xi_mean": mean.tolist(), "xi_std": std.tolist(),
           "status": [models[c].status for c in order]}
    if uncertainty is not None:
        sd = uncertainty.summary()["modeling_uncertainty"]
        with np.errstate(all="ignore"):
            ranges = np.concatenate([np.ptp(mean, axis=0) / np.asarray(sd["xi_mean_sd"]),
                                     np.ptp(std, axis=0) / np.asarray(sd["xi_std_sd"])])
        out["range_over_sd"] = float(np.nanmax(ranges)) if np.isfinite(ranges).any() else None
    return out


def identification_feedback(exp: Experiment, force_nominal: bool = False) -> tuple[np.ndarray | None, dict]:
    """The gain of the identification run (None: open loop) and what was decided, for the summary.

    auto: open loop when the plant at the nominal guess xi_guess (prior knowledge, by default the mean
    of the plant's distribution) is mean-square stable in open loop, else nominal: a stabilizing
    gain designed on the plant at xi_guess (`nominal_gain`); force_nominal: nominal whatever the guess
    (the second try when the open-loop plant diverged)."""
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
    info["F"] = res.F.tolist()                   # the gain the plant is identified under (`design.safer_gain`)
    return res.F, info


def identify_recorded(exp: Experiment, recorded, seed, enkf=None) -> Trajectories:
    """The identification EnKF run on recorded (u, y) (`simulate(recorded=...)`): batched over the recorded
    paths, path j with the EnKF stream j of the identification's seed and the initial ensemble of a
    simulated identification, so that a run's own record gives its estimates bit for bit. In chunks of
    paths within the Monte Carlo's memory budget (`montecarlo.MEMORY_BUDGET`; every path has its own streams,
    so the chunks change nothing), joined along the path axis."""
    total = exp.identification.covariance == "total"
    sim = Simulation.of(exp, enkf or exp.filter.enkf, None, seed, d=np.zeros((recorded.steps, exp.model.m)),
                        q0=np.zeros(exp.model.n), paths=recorded.paths, filter_sees_d=True)
    per_path = bytes_per_path(exp.model, sim.observer, ensemble_size=exp.filter.ensemble_size,
                              horizon=recorded.steps - 1, keep_members=sim.keep_members, block=16)
    size = int(max(1, MEMORY_BUDGET // (3 * per_path)))
    parts = [sim.run(first, min(size, recorded.paths - first), keep_xi_cov=total,
                     recorded=recorded.select(slice(first, first + size)))
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
