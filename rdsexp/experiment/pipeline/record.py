"""The run summary (run.json's `summary`, what the console and the catalog show), derived in one place from the
stages' typed results: `run_summary` for a simulated run, `data_summary` for a data run.
"""
from __future__ import annotations

import numpy as np
import pandas as pd

from ...numerics import observer_loop
from ...numerics.distributions import expected_crps
from ...numerics.enkf import truth_map
from ...numerics.modeling import correlations
from ..config import Experiment
from .design import safe_rate
from .identification import left_out_paths
from .results import DesignSet, Identified, JudgedLoops, OnlineResult, Uncertainty, Validation

CRPS_SEED, CRPS_DRAWS = 20240, 20_000   # the plant's xi drawn for the summary's xi_crps (Monte Carlo error < 1%)
OBSERVER_SEARCH_MAX_N = 20    # the search for a linear observer runs on 2n states: up to this n
OBSERVER_SEARCH_STEPS = 40    # its BFGS steps (n = 6: about 0.3 s). The rate reported is the exact rate of the
                              # observer found; against 200 steps, on the random plants (seeds 0-4) whose rate is
                              # 0.9-1.15: within 0.005, none on the other side of 1 (0.05 on plants near 0.6)


def stages_summary(exp: Experiment, identified: Identified, uncertainty: Uncertainty | None,
                   designs: DesignSet, sensitivity: dict | None) -> dict:
    """What every run's summary says of identification, modeling (with the moments' noise sensitivity,
    `identification.noise_sensitivity`) and synthesis."""
    s = {"model": exp.model_name, "gain_method": designs.method(exp.design.method), "prior": prior_summary(exp),
         **identified.summary(), **designs.summary()}
    if uncertainty is not None:
        s |= uncertainty.summary()
    if sensitivity is not None:
        s["noise_sensitivity"] = sensitivity
    if (left_out := left_out_paths(exp, identified)) is not None:
        s["identification_failed_paths"] = left_out
    dist, chosen = identified.moments, designs.chosen
    if dist is not None:
        s.update(nbar=int(exp.model.Gbar(dist).shape[0]), xi_mean=dist.mean.tolist(),
                 xi_std=np.sqrt(np.diag(dist.cov)).tolist())
        if exp.model.p > 1:
            s["xi_corr"] = correlations(dist.cov).tolist()
    if chosen is not None:
        s.update(synthesis_status=chosen.status, lam=chosen.lam)
    s["designs"] = {method: res.status for (source, method), (_, res) in designs.designs.items()
                    if source == "identified"}
    return s


def prior_summary(exp: Experiment) -> dict:
    """The prior guess of xi (identification.xi_guess, the plant file's xi), where it came from (config.PRIORS:
    `oracle` is the only source that reads the law a simulated plant is drawn from) and which stages use it."""
    ident = exp.identification
    used = [use for use, on in (("the EnKF's start", exp.filter.start == "guess"),
                                ("the identification feedback",
                                 exp.data is None and ident.feedback in ("nominal", "auto")),
                                ("the online controller", exp.controller.kind == "online")) if on]
    return {"xi_guess": ident.xi_guess.tolist(), "source": ident.prior, "used_by": used}


def run_summary(exp: Experiment, identified: Identified, uncertainty: Uncertainty | None, designs: DesignSet,
                judged: JudgedLoops, online: OnlineResult | None, sensitivity: dict | None = None,
                optimum: dict | None = None) -> dict:
    """Key numbers of a simulated run: the stages' decisions, the model against the plant file's law, the
    gain's exact rate on the true plant and against the optimum for the law (`design.against_optimum`), and
    per loop its rate, interval, verdict and failures."""
    s = {"plant": exp.plant_name, **stages_summary(exp, identified, uncertainty, designs, sensitivity),
         **(optimum or {}), **judged.summary(),
         "loop": {"estimate": exp.loop.estimate, "observer_xi": exp.loop.observer_xi,
                  "filter_sees_disturbance": exp.loop.filter_sees_disturbance}}
    s |= model_error(exp, identified)
    if designs.chosen is not None:
        s["rate_plant"] = safe_rate(exp.plant, None, designs.gain) if designs.gain is not None else None
    if online is not None:
        s["online_initial"] = online.initial
        s["online"] = {k: (None if not np.isfinite(v) else float(v)) for k, v in online.metrics.items()}
    for row in judged.metrics.itertuples():
        s |= loop_summary(exp, row, judged.loops[row.experiment])
    through_y = loop_through_outputs(exp, designs.gain, s)
    if through_y:
        s["closed_loop_through_y"] = through_y
    if exp.reference is not None:
        s["reference"] = exp.reference
    return s


def model_error(exp: Experiment, identified: Identified) -> dict:
    """The plant file's law of xi in the model's xi = T s + t, and the model's error against it: RMS over
    components of mean and std, and a proper score (CRPS) of the modeled marginals from one fixed set of draws
    (the same yardstick for every run and seed). {} where the model's xi is no affine map of the plant's."""
    truth = truth_map(exp.model, exp.plant)
    if truth is None:
        return {}
    T, t = truth
    family, dist = exp.plant.xi_dist, identified.moments
    s = {"plant_xi_mean": (T @ family.mean + t).tolist(),
         "plant_xi_std": np.sqrt(np.diag(T @ family.cov @ T.T)).tolist()}
    if exp.model.p > 1:
        s["plant_xi_corr"] = correlations(T @ family.cov @ T.T).tolist()
    if dist is not None and exp.model.p:        # (a model without xi has no error to measure)
        std = np.sqrt(np.diag(dist.cov)).tolist()
        for what, modeled in (("mean", dist.mean.tolist()), ("std", std)):
            err = np.subtract(modeled, s[f"plant_xi_{what}"])
            s[f"xi_{what}_error"] = float(np.sqrt(np.mean(err ** 2)))
        draws = family.sample(np.random.default_rng(CRPS_SEED), (CRPS_DRAWS,)) @ T.T + t
        s["xi_crps"] = float(np.mean(expected_crps(dist.mean, std, draws)))
    return s


def loop_summary(exp: Experiment, row, loop) -> dict:
    """One loop's entries: `row` its metrics row, `loop` its LoopSummary (the failed paths: fraction, first and
    median step, reasons)."""
    name = row.experiment
    # the error of the estimate the feedback uses: x_{k|k-1} (predicted) or x_{k|k} (filtered)
    fed_back = row.x_error_rms if exp.loop.estimate == "predicted" else row.x_rmse
    s = {f"{name}_status": row.status, f"{name}_verdict": row.verdict, f"{name}_verdict_reason": row.verdict_reason,
         f"{name}_exact_rate": row.exact_rate,              # the ideal loop over the same window
         f"{name}_estimation": {"estimate": exp.loop.estimate, "x_error_rms": fed_back, "rms_k_to": row.rms_k_to},
         # the paths' |q_k_to|^2 tail (`verdict.tail_index`); None below 20 paths
         f"{name}_tail_khat": float(row.tail_khat) if np.isfinite(row.tail_khat) else None,
         f"{name}_paths": int(row.paths),             # closed_loop.paths auto: the last look's
         f"{name}_rate": [row.rate, row.rate_low, row.rate_high]}
    bad = loop.failed_at >= 0
    if bad.any():
        failed = pd.Series(loop.failed_at[bad].astype(int))
        reasons = pd.Series([str(f) if f not in (None, "") else None for f in loop.failure[bad]], dtype=object)
        s[f"{name}_failed"] = {"fraction": row.failed_fraction, "first_k": int(failed.min()),
                               "median_k": float(failed.median()),
                               "reasons": {str(r): int(c) for r, c in reasons.value_counts().items()}}
    return s


def loop_through_outputs(exp: Experiment, F: np.ndarray | None, s: dict) -> dict | None:
    """When the closed loop is not found stable although its gain F stabilizes the true plant with the true
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
        found = observer_loop.best_observer(exp.plant, None, F, estimate=exp.loop.estimate,
                                            max_iter=OBSERVER_SEARCH_STEPS, stop_below=1.0)
    except (ValueError, np.linalg.LinAlgError) as err:
        return {"rate": None, "not_applicable": str(err)}
    return {"rate": found.rate, "kalman_rate": found.kalman_rate, "estimate": exp.loop.estimate}


def data_summary(exp: Experiment, identified: Identified, uncertainty: Uncertainty | None, designs: DesignSet,
                 spread: dict, validation: Validation | None, on_model: dict | None,
                 sensitivity: dict | None = None) -> dict:
    """A data run's key numbers: the data file, the modeled moments, and each design's exact rate on the
    identified model with its spread over the moments' draws. Nothing here is a number on a true plant."""
    info, dist = exp.data.data.info, identified.moments
    s = {"plant": None, **stages_summary(exp, identified, uncertainty, designs, sensitivity),
         "data": {"name": info["name"], "sha256": info["sha256"], "rows": info["rows"], "paths": info["paths"],
                  "steps": info["steps"], "identification_paths": int(identified.trajectories.failed_at.size),
                  "holdout_paths": exp.data.holdout_paths},
         "no_plant": "a data run: every rate is exact on the identified model; there is no true plant"}
    if designs.chosen is not None:
        s["rate_model"] = safe_rate(exp.model, dist, designs.gain) if designs.gain is not None and dist is not None \
            else None
    s["design_rates"] = {method: {"status": res.status,
                                  "rate_model": safe_rate(exp.model, dist, res.F) if res.F is not None else None,
                                  **spread.get((source, method), {})}
                         for (source, method), (_, res) in designs.designs.items() if source == "identified"}
    if validation is not None:
        s["validation"] = validation.summary
    if on_model is not None:
        s["loops_on_model"] = on_model
    return s
