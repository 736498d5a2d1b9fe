"""Synthesis: the loop's gain and the comparison designs (gain.designs) on the modeled moments and on the moments
a paper reports, the fallback where the loop's method does not apply, and the identification's own gain where
it is safer over the moments' uncertainty. A design that cannot be applied or fails is a status, never the end
of a run (Theorem 2's LMI, the Riccati-type and classical designs: numerics.synthesis).
"""
from __future__ import annotations

import logging
import time
from functools import partial

import numpy as np

from ...errors import one_line
from ...numerics.analysis import exact_costs, ms_rate
from ...numerics.online import moment_factors, rates
from ...numerics.synthesis import SynthesisResult, synthesize
from ...numerics.systems import MomentModel
from ..config import Experiment
from .results import KEPT_GAIN, DesignSet, Uncertainty
from .stage import Stages

log = logging.getLogger("rdsexp")
LMI_METHODS = ("proposed", "nominal_lmi", "robust_box")      # designs that solve semidefinite programs
RISK = 0.95     # the quantile of a gain's exact rate over the moments' draws that the gain choice reads


def design_set(exp: Experiment, stages: Stages, dist: MomentModel | None, uncertainty: Uncertainty | None,
               feedback: dict) -> DesignSet:
    """Every design of a run (simulated or data): the loop's method and gain.designs on the identified moments
    and, when the config gives them, on the moments a paper reports; gain.source fixed: the given F with its
    exact rate; gain.fallback where the loop's method is not_applicable; and the identification's gain (run
    under `feedback["F"]`) where the designed gain risks instability over the moments' draws (`safer_gain`)."""
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
    result = DesignSet(designs, selected)
    chosen, fallback = result.chosen, exp.design.fallback
    if chosen is not None and chosen.status == "not_applicable" and fallback not in (None, selected[1]):
        # the loop's method cannot run on this system (e.g. an LMI design above gain.lmi_max_n): the
        # loop uses gain.fallback, designed on the same moments, and the summary says so
        moments = designs[selected][0]
        if (selected[0], fallback) not in designs:
            designs[selected[0], fallback] = (moments, configured_design(stages, exp, moments, fallback,
                                                                         selected[0]))
        result.fallback = {"method": fallback, "instead_of": selected[1],
                           "because": chosen.info.get("reason", chosen.status)}
        result.selected = (selected[0], fallback)
    chosen, F_id = result.chosen, feedback.get("F")
    if result.selected[0] == "identified" and uncertainty is not None and chosen is not None and chosen.F is not None \
            and F_id is not None:
        result.choice, kept = safer_gain(exp, dist, chosen, uncertainty.draws, np.asarray(F_id, dtype=float))
        if kept is not None:                # the identification's own gain: the loop keeps it
            result.selected = ("identified", kept.method)
            designs[result.selected] = (dist, kept)
    return result


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


def safer_gain(exp: Experiment, dist: MomentModel, chosen: SynthesisResult, draws: tuple[np.ndarray, np.ndarray],
               F_id: np.ndarray) -> tuple[dict, SynthesisResult | None]:
    """The identification ran under a feedback gain F_id (m, n): the exact rates of the designed gain and of
    F_id at every draw of the modeled moments (means (B, p), covariances (B, p, p)). The designed gain is the
    optimum of its objective at the point estimate; it stays unless it risks instability over the moments'
    uncertainty: where its rate's RISK quantile over the draws is at or above 1 (it fails to stabilize more than
    1 - RISK of the laws the data allow) and F_id's is lower, the loop keeps F_id. A rate that cannot be computed
    counts as unstable. Returns (the comparison and the choice, for the summary's gain_choice; F_id as a
    SynthesisResult with status `kept`, or None: the designed gain stays)."""
    Abar, Bbar = moment_factors(exp.model, *draws)
    with np.errstate(all="ignore"):
        designed, held = (np.nan_to_num(rates(Abar, Bbar, np.broadcast_to(F, (len(Abar),) + F.shape)), nan=np.inf)
                          for F in (chosen.F, F_id))
    risk_designed, risk_held = (float(np.quantile(r, RISK, method="inverted_cdf")) for r in (designed, held))
    keep = risk_designed >= 1 and risk_held < risk_designed
    choice = {"kept": "identification" if keep else "designed", "draws": int(len(Abar)), "quantile": RISK,
              "designed_quantile": risk_designed, "identification_quantile": risk_held,
              "designed_worst": float(np.max(designed)), "identification_worst": float(np.max(held)),
              "designed_median": float(np.median(designed)), "identification_median": float(np.median(held))}
    if not keep:
        return choice, None
    return choice, SynthesisResult(KEPT_GAIN, F_id, safe_rate(exp.model, dist, F_id), "kept",
                                   nbar=int(exp.model.Gbar(dist).shape[0]))


def design_spread(exp: Experiment, designs: DesignSet, uncertainty: Uncertainty | None) -> dict:
    """Per identified design with a gain: its exact rate on the identified model at every draw of the moments
    (`identification.moment_uncertainty`): median, 5% and 95% quantiles and worst; {} without draws."""
    if uncertainty is None:
        return {}
    Abar, Bbar = moment_factors(exp.model, *uncertainty.draws)
    out = {}
    for (source, method), (_, res) in designs.designs.items():
        if source != "identified" or res.F is None:
            continue
        with np.errstate(all="ignore"):
            r = rates(Abar, Bbar, np.broadcast_to(res.F, (len(Abar),) + res.F.shape))
        q = np.nanpercentile(r, [5, 50, 95]) if np.isfinite(r).any() else [np.nan] * 3
        out[source, method] = {"rate_model_q05": float(q[0]), "rate_model_median": float(q[1]),
                               "rate_model_q95": float(q[2]), "rate_model_worst": float(np.max(r)),
                               "draws": int(len(r))}
    return out


RATE_OBJECTIVE = ("proposed", "policy_iteration", "nominal_lmi")     # designs that minimise the mean-square rate
COST_OBJECTIVE = ("ms_lqr", "lqr_mean")                             # designs that minimise an LQ cost


def against_optimum(exp: Experiment, stages: Stages, designs: DesignSet) -> dict:
    """The end-to-end figure of a simulated run: the loop's gain on the true plant against the optimum for the
    true law of the configured method's objective. An LQ design (COST_OBJECTIVE): cost_ratio_plant, the exact LQ
    cost (the method's weights, x0 ~ N(0, I)) of the gain over that of the mean-square LQ optimum for the law
    (>= 1); a rate design (RATE_OBJECTIVE): rate_excess_plant, the gain's exact rate minus the optimal rate (>= 0;
    policy iteration's, Theorem 2's bisection where policy iteration is not certified optimal). {} without a
    plant, a gain, or for a method with neither objective (pole placement, a given gain)."""
    F, method = designs.gain, exp.design.method
    if exp.plant is None or F is None or method not in RATE_OBJECTIVE + COST_OBJECTIVE:
        return {}
    truth, lmi_max_n = exp.plant.check_distribution(None), exp.design.lmi_max_n
    optimal = lambda name, options: design(stages, exp.plant, truth, name, options, lmi_max_n,
                                           f"synthesis/plant/{name}")
    with np.errstate(all="ignore"):
        if method in COST_OBJECTIVE:
            weights = {k: v for k, v in exp.design.options.items() if k in ("state_weight", "input_weight")}
            best = optimal("ms_lqr", weights)
            if best.F is None:
                return {}
            cost = lambda gain: exact_costs(exp.plant, None, gain, **weights)["lq_cost"]
            return {"cost_ratio_plant": float(cost(F) / cost(best.F))}
        results = [optimal("policy_iteration", {})]
        if results[0].status != "optimal":
            results.append(optimal("proposed", {}))
        rate = min((res.lam for res in results if np.isfinite(res.lam)), default=np.nan)
        return {"rate_excess_plant": float(safe_rate(exp.plant, None, F) - rate)} if np.isfinite(rate) else {}


def safe_rate(system, dist, F) -> float:
    """ms_rate, NaN where it cannot be computed (a gain so large that the operator is not finite)."""
    try:
        with np.errstate(all="ignore"):
            return ms_rate(system, dist, F)
    except (ValueError, np.linalg.LinAlgError):
        return float("nan")
