"""The run tables' data dictionary: what every column means and its unit, and every key of run.json's summary.

Each table a run writes carries it in its parquet schema metadata (pandas `DataFrame.attrs`,
restored by `pd.read_parquet`; stored under the key ``PANDAS_ATTRS`` for other readers) as
``{"rdsexp": {"run": id, "table": name, "columns": {column: {"description", "unit"}}}}``.
`python -m rdsexp.experiment.schema` prints the dictionary as docs/data_dictionary.md.

Vector quantities are one column per component, ``q[i]`` (i = 0..n-1); the gain F (m x n) is one
column per entry, ``F[i,j]`` (u_i = sum_j F[i,j] x_j). Missing values are null (NaN for numbers).
"""
from __future__ import annotations

import re

import pandas as pd

from . import metrics

_TRAJECTORY = {
    "experiment": ("which simulation: identification, closed_loop, open_loop or online", None),
    "k": ("time step k = 0..horizon", "step"),
    "path": ("sample path j (own plant and EnKF random streams)", None),
    "member": ("ensemble member (0..M-1)", None),
    "q[i]": ("plant state q_k, component i", "state"),
    "y[i]": ("measured output y_k, component i", "output"),
    "u[i]": ("applied input u_k = F x_{k|k-1} + d_k, component i", "input"),
    "x_pred_mean[i]": ("EnKF predicted mean x_{k|k-1} (ensemble mean), component i", "state"),
    "x_pred_std[i]": ("EnKF predicted spread (ensemble standard deviation) of x, component i", "state"),
    "x_filt_mean[i]": ("EnKF filtered mean x_{k|k}, component i", "state"),
    "x_filt_std[i]": ("EnKF filtered spread of x, component i", "state"),
    "xi_pred_mean[i]": ("EnKF predicted mean xi_{k|k-1} of the model's random parameters, component i", "xi"),
    "xi_pred_std[i]": ("EnKF predicted spread of xi, component i", "xi"),
    "xi_filt_mean[i]": ("EnKF filtered mean xi_{k|k}, component i (the modeling data, eq. sample-mean)", "xi"),
    "xi_filt_std[i]": ("EnKF filtered spread of xi, component i", "xi"),
    "d_filt_mean[i]": ("EnKF filtered mean of the unknown input disturbance d added on u_k (enkf.disturbance; "
                       "NaN where the EnKF does not carry it), component i", "input"),
    "d_filt_std[i]": ("EnKF filtered spread of d, component i", "input"),
    "x_filt[i]": ("filtered ensemble member's x, component i", "state"),
    "xi_filt[i]": ("filtered ensemble member's xi, component i", "xi"),
    "F[i,j]": ("gain in use at step k (online runs; their offline loops carry the fixed gain)", None),
}
COLUMNS: dict[str, dict[str, tuple[str, str | None]]] = {
    "trajectories": _TRAJECTORY,
    "identification": _TRAJECTORY,
    "members": _TRAJECTORY,
    "paths": {
        "experiment": _TRAJECTORY["experiment"], "path": _TRAJECTORY["path"],
        "failed_at": ("step at which the path failed (-1: never)", "step"),
        "failure": ("why the path failed (e.g. diverged); null if it did not", None),
    },
    "model": {
        "quantity": ("mean, cov, second_moment of the modeled xi, or Gbar (eq. Gbar)", None),
        "row": ("matrix row (0 for the mean vector)", None),
        "col": ("matrix column", None),
        "value": ("entry of the matrix", None),
    },
    "gains": {
        "distribution": ("moments designed on: identified (from the EnKF), reported (a paper's), fixed", None),
        "method": ("synthesis method (rdsexp.numerics.synthesis.METHODS) or fixed", None),
        "selected": ("the gain the closed loop used", None),
        "status": ("design status, one of the statuses listed below this table", None),
        "lam": ("decay rate lambda the design reports (mean-square rate on its moments)", "1/step"),
        "lam_lower": ("certified lower end of the bisection bracket on lambda", "1/step"),
        "nbar": ("rank of Gbar (number of independent random directions)", None),
        "rate_model": ("exact mean-square rate of F on the design moments", "1/step"),
        "rate_plant": ("exact mean-square rate of F on the true plant distribution", "1/step"),
        "lq_cost_q0_plant": ("exact LQ cost sum E(|q|^2 + |u|^2) from the plant's q0, true plant", None),
        "lq_cost_plant": ("exact LQ cost averaged over x0 ~ N(0, I), true plant", None),
        "h2_plant": ("H2 norm from d (on u) to [x; F x], true plant", None),
        "lq_cost_model": ("exact LQ cost averaged over x0 ~ N(0, I), design moments", None),
        "h2_model": ("H2 norm from d to [x; F x], design moments", None),
        "lam_box": ("robust_box's certified rate over the box of xi (NaN for other methods)", "1/step"),
        "lam_box_lower": ("robust_box: proven lower bound on the box rate of every gain (NaN for other methods)",
                          "1/step"),
        "max_width": ("robust_box with find_max_width: largest box width with a certified rate (NaN otherwise)",
                      None),
        "min_infeasible_width": ("robust_box with find_max_width: smallest width proven infeasible (NaN otherwise)",
                                 None),
        "F[i,j]": ("gain entry (row i = input, column j = state), u = F x; NaN without a gain", None),
        "rate_model_median": ("a data run: median exact rate of F over the draws of the identified moments", "1/step"),
        "rate_model_q05": ("a data run: 5% quantile of F's exact rate over the moments' draws", "1/step"),
        "rate_model_q95": ("a data run: 95% quantile of F's exact rate over the moments' draws", "1/step"),
        "rate_model_worst": ("a data run: the largest exact rate of F over the moments' draws", "1/step"),
    },
    "validation": {
        "law": ("the law of xi the EnKF draws from: modeled (the identified moments) or nominal (xi at their "
                "mean)", None),
        "output": ("the output component i of y, or all (the mean over components)", None),
        "crps": ("mean CRPS of the one-step-ahead predictive ensemble of y_k on the held-out paths (lower is "
                 "better)", "output"),
        "coverage_50": ("fraction of held-out y_k inside the ensemble's central 50% interval (calibrated: 0.5)",
                        None),
        "coverage_90": ("fraction of held-out y_k inside the ensemble's central 90% interval (calibrated: 0.9)",
                        None),
        "steps": ("steps scored per path (k = max(K0, 1)..K)", None),
        "paths": ("held-out recorded paths", None),
    },
    "metrics": {
        "experiment": _TRAJECTORY["experiment"],
        "verdict": ("stable (the rate's 95% interval below 1, and the ideal loop's exact rate over the same steps "
                    "below 1), unstable (the interval above 1; the loop at rest grows; in the open loop, a plant state "
                    "diverged), undetermined (the interval contains 1, the exact rate contradicts a decay, the loop is "
                    "at its floor from the window's start, or no window above it), failed (some path diverged, or the "
                    "loop at rest did)", None),
        "verdict_reason": ("the verdict in words, with the evidence it was decided on", None),
        "status": ("ok, partially_failed or failed (every path): whether paths diverged", None),
        "rate": ("empirical rate (E|q_k_to|^2 / E|q_k_from|^2)^(1/(2 (k_to - k_from)))", "1/step"),
        "rate_low": ("lower end of the rate's interval at `level` (hull of a BCa and a lognormal bootstrap over "
                     "paths)", "1/step"),
        "rate_high": ("upper end of the rate's interval at `level`", "1/step"),
        "k_from": ("first step of the rate window (config, or auto: after the disturbance)", "step"),
        "k_to": ("last step of the rate window (auto: the ideal loop still 10 floors up)", "step"),
        "verdict_rate": ("the rate the verdict was decided on: ((E|q_k_end|^2 - f) / (E|q_k_from|^2 - f))^(1/(2 "
                         "(k_end - k_from))), f the noise floor's mean square (0 for the open loop); NaN when no rate "
                         "decided", "1/step"),
        "verdict_rate_low": ("lower end of verdict_rate's interval at `level`", "1/step"),
        "verdict_rate_high": ("upper end of verdict_rate's interval at `level`", "1/step"),
        "k_end": ("last step of verdict_rate: k_to, or the step before the loop is at rest (its mean square "
                  "below 2 noise floors'); -1 without a rate", "step"),
        "exact_rate": ("the ideal loop's (state feedback, true plant) exact rate over the same window", "1/step"),
        "floor_rms": ("the noise floor the loop is judged against: sqrt(E|q|^2) of the closed loop at rest (0 for "
                      "the open loop; the online loop takes the closed loop's where it holds; inf if the loop at "
                      "rest diverged; NaN: none)", "state"),
        "rms_k_to": ("sqrt(E|q_k_to|^2), compared with the floor", "state"),
        "tail_khat": ("Pareto k-hat of the paths' |q_k_to|^2 (`verdict.tail_index`, as PSIS computes it): above 0.7 "
                      "a few paths carry the mean square and the rate's interval needs more paths (closed_loop.paths "
                      "auto runs more); NaN below 20 paths", None),
        "paths": ("number of sample paths (closed_loop.paths auto: the last look's)", None),
        "level": ("the level of the rate intervals: 0.95, or with closed_loop.paths auto 1 - 0.05 / looks (the looks "
                  "share the 5%)", None),
        "paths_needed": ("undetermined by an interval that holds 1: about how many paths would separate the rate "
                         "from 1 (NaN otherwise)", None),
        "failed_fraction": ("fraction of paths that failed", None),
        "x_error_rms": ("RMS of x_{k|k-1} - q_k over steps and paths", "state"),
        "q_rms_final": ("sqrt(E|q_K|^2) at the last step", "state"),
        "x_rmse": ("RMSE of x_{k|k} against q_k, k = 1..K", "state"),
        "x_spread_error": ("spread/error ratio of x (1: spread matches error)", None),
        "xi_rmse": ("RMSE of xi_{k|k} against the true xi (NaN if not defined)", "xi"),
        "xi_spread_error": ("spread/error ratio of xi", None),
        "final_rate_plant_q10": ("online: 10% quantile over paths of the final gain's exact rate, true plant",
                                 "1/step"),
        "final_rate_plant_median": ("online: median over paths of the final gain's exact rate, true plant",
                                    "1/step"),
        "final_rate_plant_q90": ("online: 90% quantile over paths of the final gain's exact rate", "1/step"),
        "final_stable_fraction": ("online: fraction of paths whose final gain has exact rate < 1", None),
        "first_stable_k_median": ("online: median step from which a path holds a gain of exact rate < 1",
                                  "step"),
        "never_stable_fraction": ("online: fraction of paths that never held such a gain", None),
        "adoptions_per_path": ("online: adopted re-designs per path", None),
        "rate_not_diverged": ("online: empirical rate over the paths that did not diverge", "1/step"),
        "offline_rate_plant": ("online: exact rate of the offline design of the same seed, true plant", "1/step"),
        "optimal_rate_plant": ("online: optimal exact rate on the true plant (policy iteration)", "1/step"),
        "lost_online_only": ("online: paths the online loop lost and the offline loop (same plant samples) kept",
                             None),
        "lost_offline_only": ("online: paths the offline loop lost and the online loop kept", None),
        "lost_more_p": ("online: exact paired sign test of the online loop losing more paths than the offline "
                        "loop, P(Bin(only online + only offline, 1/2) >= only online)", None),
        "lost_held_unstable": ("online: lost paths that held, before their loss, a gain whose exact rate on the true "
                               "plant is >= 1 (NaN: no path lost)", None),
        "lost_held_rate_max": ("online: the largest exact rate on the true plant of a gain a lost path held before "
                               "its loss (NaN: no path lost)", "1/step"),
    },
    "controller": {
        "path": _TRAJECTORY["path"],
        "k": ("step after whose filtering the gain was re-designed (-1: the initial gain, in use from k = 0)",
              "step"),
        "adopted": ("whether the path adopted the designed gain (from step k + 1 on)", None),
        "reason": ("initial, adopted, adopted_unchecked, or why not: not_stabilizing, no_improvement, not_robust "
                   "(fails on a bootstrap resample), waiting (passes, but the window holds fewer than "
                   "controller.min_blocks blocks, and the gain in use is not unstable both at every resample and at "
                   "the prior guess), failed: ... "
                   "(the design's status)", None),
        "gain_index": ("index of the gain among the path's adopted gains (0: initial; -1: not adopted)", None),
        "rate_model": ("exact mean-square rate of the designed F on the current modeled moments", "1/step"),
        "rate_current": ("exact rate of the gain in use on the current modeled moments", "1/step"),
        "rate_worst": ("largest exact rate of the designed F over the bootstrap resamples of the window "
                       "(controller.resamples > 0; NaN without)", "1/step"),
        "rate_current_worst": ("largest exact rate of the gain in use over the same resamples", "1/step"),
        "rate_current_best": ("smallest exact rate of the gain in use over the same resamples (>= 1: it fails "
                              "at every resample)", "1/step"),
        "rate_current_guess": ("exact rate of the gain in use on the plant at the prior guess xi_guess (>= 1 with "
                               "rate_current_best >= 1: a window of fewer than controller.min_blocks blocks acts)",
                               "1/step"),
        "estimates": ("estimates xi_{k|k} in the modeling window (0 for the initial gain)", None),
        "rate_plant": ("exact rate of the designed F on the true plant distribution", "1/step"),
        "mean[i]": ("modeled mean of xi from the path's own estimates, component i", "xi"),
        "cov[i,j]": ("modeled covariance of xi, entry (i, j)", "xi^2"),
        "F[i,j]": ("designed gain entry (row i = input, column j = state), u = F x", None),
    },
    "exact": {
        "experiment": ("closed_loop (selected gain) or open_loop (F = 0), ideal state feedback", None),
        "k": _TRAJECTORY["k"],
        "rms": ("exact sqrt(E|q_k|^2) on the true plant distribution", "state"),
    },
}
# run.json's `summary`: every key a run can write, what it holds and its unit. {loop} stands for closed_loop,
# open_loop and online (the loops of the metrics table). A key a stage adds goes here too (a test runs
# several configurations and checks every key they write against this dictionary).
RUN_SUMMARY_KEYS: dict[str, tuple[str, str | None]] = {
    "plant": ("the plant's name (its file's `name:`, else the file name)", None),
    "model": ("the model's name (the structure identified: A_i, B_i, C, D, and xi's prior)", None),
    "gain_method": ("the synthesis method whose gain the loop uses (after gain.fallback, or identification_gain "
                    "when the loop kept the identification's gain)", None),
    "prior": ("the prior guess of xi (identification.xi_guess, the plant file's xi), where it came from (given, "
              "nominal: the plant file's nominal:, zero: none stated, model: a data run's model.xi, oracle: the mean "
              "of the law the plant is simulated from, not blind) and which stages use it", "xi"),
    "identification_feedback": ("the identification run's loop: open or under a feedback gain F (the rule that "
                                "chose it, F, its exact rates)", None),
    "identification_passes": ("the iterated identification: passes, the last change of the moments, the "
                              "tolerance, converged or not", None),
    "modeling_status": ("ok (the moments settled), unsettled (the iterated identification did not settle within "
                        "its tolerance, or too few simulated replicates were identified), at_prior_edge (the simulated "
                        "estimator's posterior stopped by its prior box), weakly_identified (a component whose prior "
                        "box the data hardly narrowed), or why no model was made",
                        None),
    "modeling_estimator": ("the estimator of the moments (identification.estimator): paper, or simulated with its "
                           "replicates and their laws (identification.replicate_laws), how many were identified, "
                           "the effective number of its posterior draws, the prior box's width, the paper "
                           "estimator's moments it matched, and (correlations) why xi's correlations were left to "
                           "their prior box", None),
    "modeling_covariance": ("how the modeled covariance was formed (identification.covariance)", None),
    "modeling_uncertainty": ("the modeled moments' spread over their draws (the simulated estimator's posterior, "
                             "or block-bootstrap draws of the paper's modeling window): resamples, block, what "
                             "was drawn over, sd of xi's mean and std per component and of each correlation "
                             "(p > 1)", "xi"),
    "nbar": ("size of the LMI's basis Gbar (eq. Gbar)", None),
    "noise_sensitivity": ("the moments modeled again with the EnKF's assumed noise (enkf.Q's x block and enkf.R) "
                          "scaled by identification.noise_sensitivity's factors: the factors (1 among them), xi mean "
                          "and std at each, their statuses, and the largest range over the factors in bootstrap "
                          "sds (range_over_sd)", "xi"),
    "xi_mean": ("modeled mean of xi (the modeling window's sample mean of the EnKF's xi)", "xi"),
    "xi_std": ("modeled standard deviation of xi, per component", "xi"),
    "xi_corr": ("modeled correlation of each pair (i, j), i > j, of xi's components (p > 1), row by row", None),
    "plant_xi_mean": ("the plant file's xi law's mean, mapped into the model's xi", "xi"),
    "plant_xi_std": ("the plant file's xi law's standard deviation, mapped into the model's xi", "xi"),
    "plant_xi_corr": ("the plant file's xi law's correlations, mapped into the model's xi (as xi_corr)", None),
    "xi_mean_error": ("RMS over components of xi_mean - plant_xi_mean", "xi"),
    "xi_std_error": ("RMS over components of xi_std - plant_xi_std", "xi"),
    "xi_crps": ("CRPS of the modeled marginals against the plant's xi, mean over components", "xi"),
    "synthesis_status": ("the loop's design status (data dictionary of gains: design statuses)", None),
    "lam": ("the loop's design's decay rate lambda on its moments", "1/step"),
    "rate_plant": ("the exact mean-square rate of the loop's gain on the true plant (state feedback)", "1/step"),
    "designs": ("status of every design on the identified moments, by method", None),
    "gain_fallback": ("the method the loop used instead of the one asked for, which and why", None),
    "gain_choice": ("the designed gain against the identification's gain over the moments' draws: the exact rate's "
                    "95% quantile (which decides), median and worst of each, and which the loop kept", "1/step"),
    "rate_window": ("[k_from, k_to] of the rate window", "step"),
    "rate_window_source": ("where the window came from: config, auto, or none", None),
    "noise_floor": ("RMS of the loop started at rest (the EnKF's noise floor; NaN: not measured, inf: diverged)",
                    "state"),
    "loop": ("the closed loop's feedback: the estimate fed back, whether the observer carries xi, whether the EnKF "
             "is told the disturbance", None),
    "loop_looks": ("closed_loop.paths auto: every look, in order: its paths, its intervals' level and per loop the "
                   "verdict, [rate, low, high], tail k-hat and paths_needed", None),
    "loop_paths_asking": ("closed_loop.paths auto: the loops whose verdict still asked for paths when "
                          "closed_loop.max_paths was reached (empty: the looks settled every verdict)", None),
    "{loop}_status": ("ok, partially_failed or failed (every path): whether paths diverged", None),
    "{loop}_verdict": ("stable, unstable, undetermined or failed (metrics table's verdict)", None),
    "{loop}_verdict_reason": ("the verdict in words, with its evidence", None),
    "{loop}_exact_rate": ("exact rate of the ideal loop over the same window", "1/step"),
    "{loop}_tail_khat": ("Pareto k-hat of the paths' |q_k_to|^2 (metrics `tail_khat`): above 0.7 a few paths carry "
                         "the mean square", None),
    "{loop}_paths": ("the paths the loop was judged on (closed_loop.paths auto: the last look's)", None),
    "{loop}_estimation": ("the estimate fed back, the RMS of its error, the loop's RMS at k_to", "state"),
    "{loop}_rate": ("[rate, low, high]: the plain empirical rate over the window with its interval (metrics `level`)",
                    "1/step"),
    "{loop}_failed": ("failed paths: fraction, first and median step, reasons (only where a path failed)", None),
    "closed_loop_through_y": ("where the loop is not found stable although its gain stabilizes the true plant: the "
                              "exact rate of the loop through y with the best linear observer found", "1/step"),
    "online_initial": ("the online controller's initial gain and where it came from (nominal_law: start, the law "
                       "its EnKF starts from, or guess, xi_guess alone; rate_on_law: the gain's exact rate there), "
                       "its EnKF's start before a path's first model (controller.start; start_scale: the fraction of "
                       "its law's spread kept, < 1 where no gain is mean-square stable at the full one), smoothing lag "
                       "(controller.lag), the steps after which each xi first reaches an output and, with "
                       "controller.probe, [probe, probe_until]", None),
    "online": ("the online controller's key numbers (adoptions, final gains' exact rates, ...)", None),
    "reference": ("the paper's reported numbers for this experiment, where it is the paper's", None),
    "data": ("a data run's data file: name, sha256, rows, paths, steps, identification and held-out paths", None),
    "no_plant": ("a data run: there is no true plant; every rate is exact on the identified model", None),
    "rate_model": ("a data run: the exact mean-square rate of the loop's gain on the identified moments", "1/step"),
    "design_rates": ("a data run: every design's status, exact rate on the identified moments and its spread over "
                     "the moments' draws (median, 5%, 95%, worst)", "1/step"),
    "identification_failed_paths": ("identification paths (recorded, or identification.paths simulated) whose EnKF "
                                    "estimate failed, left out of the modeling: count, of how many, reasons", None),
    "loops_on_model": ("a data run with data.loops: the closed and open loops simulated on the identified model "
                       "(xi ~ N of its moments), labelled 'simulated on the model, not the plant': rate window, "
                       "verdict, rate with its interval, the ideal loop's exact rate on the model", "1/step"),
    "validation": ("a data run with data.holdout: CRPS and 50%/90% coverage of the one-step-ahead predictive "
                   "distribution of y on the held-out paths, modeled law against the nominal model", None),
}
LOOPS = ("closed_loop", "open_loop", "online")


def summary_entry(key: str) -> tuple[str, str | None] | None:
    """(description, unit) of a summary key (a {loop}_... key for any loop of LOOPS; else a metric the registry
    declares, read from the summary: its label and unit), None if undocumented."""
    if key in RUN_SUMMARY_KEYS:
        return RUN_SUMMARY_KEYS[key]
    loop = next((name for name in LOOPS if key.startswith(f"{name}_")), None)
    entry = None if loop is None else RUN_SUMMARY_KEYS.get("{loop}_" + key.removeprefix(f"{loop}_"))
    metric = metrics.REGISTRY.get(key)
    if entry is None and metric is not None and metric.source == metrics.SUMMARY:
        return metric.label, metric.unit
    return entry


# a value column: QUANTITY[i] (a vector component) or QUANTITY[i,j] (a matrix entry)
VALUE_COLUMN = re.compile(r"^(?P<quantity>.+?)\[(?:(?P<row>\d+),)?(?P<index>\d+)\]$")


def split_column(column: str) -> tuple[str, int] | None:
    """The long form (quantity, index) of a value column, None for a key column: "x_pred_mean[3]" ->
    ("x_pred_mean", 3); a matrix entry "F[1,2]" -> ("F1", 2) (row i of F as the quantity)."""
    match = VALUE_COLUMN.match(column)
    return None if match is None else (match["quantity"] + (match["row"] or ""), int(match["index"]))


def describe(table: str, column: str) -> dict:
    """{"description", "unit"} of a column of table `table` (q[3] is described as q[i], F[0,2] as F[i,j])."""
    match = VALUE_COLUMN.match(column)
    generic = column if match is None else match["quantity"] + ("[i,j]" if match["row"] else "[i]")
    description, unit = COLUMNS.get(table, {}).get(generic, (None, None))
    return {"description": description, "unit": unit}


def attach(table: str, frame: pd.DataFrame, run: str) -> pd.DataFrame:
    """frame with its schema metadata (run id, table name, column descriptions) in frame.attrs."""
    frame.attrs = {"rdsexp": {"run": run, "table": table,
                              "columns": {c: describe(table, c) for c in frame.columns}}}
    return frame


def markdown() -> str:
    """docs/data_dictionary.md: every table's columns, descriptions and units, every design status, run.json's
    summary keys and the catalog's metrics (the registry, `metrics.markdown`)."""
    from ..numerics.synthesis.base import STATUSES  # here: the synthesis package imports cvxpy
    lines = ["# Data dictionary of a run's tables", "",
             "Generated by `python -m rdsexp.experiment.schema` from `rdsexp/experiment/schema.py`; every",
             "table also carries these descriptions and the run id in its parquet schema metadata",
             "(`pd.read_parquet(path).attrs[\"rdsexp\"]`). `rdsexp.runs.load(run, table)` adds the run id",
             "as a column `run`. Vector quantities are one column per component `q[i]`; the gain F (m x n) is",
             "one column per entry `F[i,j]` (u = F x). Missing values are null (NaN for numbers).", ""]
    for table, columns in COLUMNS.items():
        if table in ("identification", "members"):
            continue
        title = "trajectories, identification, members" if table == "trajectories" else table
        lines += [f"## {title}", "", "| column | description | unit |", "|---|---|---|"]
        lines += [f"| `{c}` | {d} | {u or ''} |" for c, (d, u) in columns.items()]
        lines.append("")
        if table == "gains":
            lines += ["Design statuses (nominal_lmi appends `_on_mean_model`: what it certifies is the LTI model",
                      "with xi at its mean):", "", "| status | meaning |", "|---|---|"]
            lines += [f"| `{status}` | {meaning} |" for status, meaning in STATUSES.items()]
            lines.append("")
    lines += ["## run.json summary", "",
              "The `summary` of run.json (key numbers of a run; `rdsexp-runs list` flattens them into `metrics.*`",
              "columns). `{loop}` is closed_loop, open_loop or online.", "",
              "| key | description | unit |", "|---|---|---|"]
    lines += [f"| `{k}` | {d} | {u or ''} |" for k, (d, u) in RUN_SUMMARY_KEYS.items()]
    lines.append("")
    lines += metrics.markdown()
    return "\n".join(lines)


if __name__ == "__main__":
    print(markdown(), end="")
