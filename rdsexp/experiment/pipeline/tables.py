"""The run's tables (docs/data_dictionary.md): one row per (path, k) of every loop, per path, the modeled
distribution, the designs and the ideal loops' exact RMS curves, built from the stages' results.
"""
from __future__ import annotations

import numpy as np
import pandas as pd

from ...numerics.analysis import exact_costs, second_moments
from ...numerics.simulation import Trajectories
from ..config import Experiment
from ..montecarlo import LoopSummary
from .design import safe_rate
from .results import DesignSet


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


def with_gains(rows: pd.DataFrame, F: np.ndarray) -> pd.DataFrame:
    """rows with the gain in use as columns F[i,j] (u_i = sum_j F[i,j] x_j).

    F: (len(rows), m, n), one gain per row, or (m, n), the same gain on every row."""
    F = np.asarray(F, dtype=float)
    F = F if F.ndim == 3 else np.broadcast_to(F, (len(rows), *F.shape))
    return rows.assign(**gain_columns(F))


def gain_columns(F: np.ndarray) -> dict[str, np.ndarray]:
    """{"F[i,j]": F[:, i, j]} of gains F (rows, m, n), the gains table's naming."""
    return {f"F[{i},{j}]": F[:, i, j] for i in range(F.shape[1]) for j in range(F.shape[2])}


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


def gains_table(exp: Experiment, designs: DesignSet, spread: dict | None = None) -> pd.DataFrame:
    """Per (distribution, method): status, lam (design), bracket, nbar, exact rates, LQ costs and H2
    norms on the design moments and on the true plant (`performance`), robust_box's certified box rate
    (lam_box), its proven lower end (lam_box_lower) and, with find_max_width, the largest certified and
    smallest proven-infeasible box widths (max_width, min_infeasible_width; NaN otherwise), F.
    `selected` is the (source, method) the closed loop used (gain.source; ("fixed", "fixed") for a given F).
    spread: a data run's rates over the moments' draws per design (`design.design_spread`), as columns
    rate_model_median, _q05, _q95, _worst.

    Only reproducible numbers go into tables; synthesis times are in run.json's timings."""
    rows = []
    for (source, method), (moments, res) in designs.designs.items():
        found = res.F is not None
        F = res.F if found else np.full((exp.model.m, exp.model.n), np.nan)
        rows.append({"distribution": source, "method": method,
                     "selected": (source, method) == designs.selected,
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
    table = pd.DataFrame(rows, columns=columns)
    for column in ("rate_model_median", "rate_model_q05", "rate_model_q95", "rate_model_worst") if spread is not None \
            else ():
        table[column] = [spread.get((row.distribution, row.method), {}).get(column, np.nan)
                         for row in table.itertuples()]
    return table


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


def exact_table(exp: Experiment, F: np.ndarray | None) -> pd.DataFrame:
    """sqrt(E||q_k||^2) of the ideal loops (state feedback F (m, n), true plant distribution), exactly."""
    frames = []
    gains = ([("closed_loop", F)] if F is not None else []) + \
        [("open_loop", np.zeros((exp.plant.m, exp.plant.n)))]
    for name, gain in gains:
        with np.errstate(all="ignore"):     # a growing loop overflows: its curve is inf or NaN there
            _, second = second_moments(exp.plant, None, gain, exp.q0, exp.loop.disturbance)
            rms = np.sqrt(np.trace(second, axis1=1, axis2=2))
        frames.append(pd.DataFrame({"experiment": name, "k": np.arange(second.shape[0]), "rms": rms}))
    return pd.concat(frames, ignore_index=True)
