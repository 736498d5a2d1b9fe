"""The stage pipeline: a validated Experiment computed into tables, without touching the file system.

Stages (docs/design.md): identification -> modeling -> synthesis -> closed loop (and open loop) ->
metrics. Seeds: the identification run uses SeedSequence(seed, spawn_key=(0,)), the closed and open
loops SeedSequence(seed, spawn_key=(1,)) (the same plant samples, as in the paper's Figs.
decay_proposed and decay_open); inside each, path j has its own plant and EnKF streams.
"""
from __future__ import annotations

import logging
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from ..numerics.analysis import empirical_rate, h2_norm, lq_cost, ms_rate, second_moments
from ..numerics.enkf import truth_map
from ..numerics.modeling import model_distribution, nominal_gain, one_line
from ..numerics.online import OnlineController, rates
from ..numerics.simulation import Trajectories, simulate
from ..numerics.synthesis import METHODS, SynthesisResult, synthesize
from ..numerics.systems import MomentModel
from .config import Experiment

log = logging.getLogger("rdsexp")
# the online loop shares the closed loop's seeds: the same plant samples and EnKF noise, a paired comparison
SPAWN_KEYS = {"identification": (0,), "closed_loop": (1,), "open_loop": (1,), "online": (1,)}
TABLES = ("trajectories", "identification", "paths", "model", "gains", "metrics", "exact")


@dataclass
class Outcome:
    """What a run computed: tables by name, a flat summary of key numbers, seconds per stage."""

    tables: dict[str, pd.DataFrame]
    summary: dict
    timings: dict = field(default_factory=dict)
    members: pd.DataFrame | None = None


@contextmanager
def timed(timings: dict, stage: str):
    """Time the block into timings[stage] and log the stage with its seconds (rdsexp.log)."""
    start = time.perf_counter()
    log.info("%s ...", stage)
    yield
    timings[stage] = round(time.perf_counter() - start, 4)
    log.info("%s done in %.3f s", stage, timings[stage])


def _progress(desc: str, total: int):
    """A tqdm bar (silent when not on a terminal) and its per-step callback."""
    bar = tqdm(total=total, desc=desc, disable=None, leave=False, file=sys.stderr)
    return bar, lambda k: bar.update(1)


def run_experiment(exp: Experiment) -> Outcome:
    """Compute every stage of the experiment; numerical failures become statuses in the tables."""
    timings, summary = {}, {}
    root = lambda stage: np.random.SeedSequence(exp.seed, spawn_key=SPAWN_KEYS[stage])
    sim = dict(q0=exp.q0, psi0=exp.psi0, P0=exp.P0, ensemble_size=exp.ensemble_size)
    keep = exp.tracking == "full"

    with timed(timings, "identification"):
        F_id, summary["identification_feedback"] = identification_feedback(exp)
        # the identification input is added on top of the feedback; the EnKF is told the applied input
        ident = simulate(exp.plant, exp.enkf, F=F_id, d=exp.identification_input, paths=1,
                         seed=root("identification"), filter_sees_d=True, keep_members=keep, **sim)
    with timed(timings, "modeling"):
        xi = ident.xi(ident.psi_filt_mean)[:, 0]
        if ident.status != "ok" or not np.all(np.isfinite(xi[exp.K0:exp.K0 + exp.K1 + 1])):
            dist = None
            summary["modeling_status"] = f"identification {ident.failure[0]} at k = {ident.failed_at[0]}"
        else:
            dist = model_distribution(xi, exp.K0, exp.K1)
            summary["modeling_status"] = "ok"
    with timed(timings, "synthesis"):
        # every method on the identified moments (the selected one with its configured options) and,
        # when the config gives them, on the moments a paper reports; a design that cannot be applied
        # or fails is a status in the gains table, never the end of the run
        designs = {}
        for source, moments in (("identified", dist), ("reported", exp.reported)):
            for method in METHODS if moments is not None else ():
                options = exp.design_options.get(method, exp.gain_options if method == exp.gain_method else {})
                designs[source, method] = (moments, safe_synthesize(exp.model, moments, method, options))
        selected = (exp.gain_source, exp.gain_method)
        if exp.gain_source == "fixed":      # a given F (e.g. a paper's own gain): no design, its exact rate
            selected, moments = ("fixed", "fixed"), dist if dist is not None else exp.reported
            rate = ms_rate(exp.model, moments, exp.gain_F) if moments is not None else np.nan
            nbar = int(exp.model.Gbar(moments).shape[0]) if moments is not None else 0
            designs[selected] = (moments, SynthesisResult("fixed", exp.gain_F, rate, "fixed", nbar=nbar))
        chosen = designs.get(selected, (None, None))[1]

    loops = {}
    if chosen is not None and chosen.F is not None:
        settings = dict(d=exp.disturbance, paths=exp.paths, filter_sees_d=exp.filter_sees_disturbance,
                        keep_members=keep, **sim)
        runs = [("closed_loop", chosen.F)] + ([("open_loop", None)] if exp.open_loop else [])
        for name, F in runs:
            with timed(timings, name):
                bar, step = _progress(name.replace("_", " "), exp.disturbance.shape[0])
                with bar, logging_redirect_tqdm():
                    loops[name] = simulate(exp.plant, exp.enkf, F=F, seed=root(name), progress=step, **settings)

    online = None
    if exp.controller == "online":
        with timed(timings, "online"):
            online, summary["online_initial"] = online_loop(exp, root("online"), keep, sim)
            loops["online"] = online[0]

    with timed(timings, "metrics"):
        tables = {
            "trajectories": pd.concat([trajectory_table(name, tr) for name, tr in loops.items()],
                                      ignore_index=True) if loops else trajectory_table("closed_loop", None, exp),
            "identification": trajectory_table("identification", ident),
            "paths": path_table({"identification": ident, **loops}),
            "model": model_table(exp, dist),
            "gains": gains_table(exp, designs, selected),
            "metrics": metrics_table(exp, loops),
            "exact": exact_table(exp, chosen),
        }
    if online is not None:
        add_online_tables(exp, tables, online, chosen, summary)
    summary.update(_summary(exp, dist, chosen, tables))
    timings["synthesis_by_method"] = {f"{source}/{method}": round(res.seconds, 4)
                                      for (source, method), (_, res) in designs.items()}
    members = None
    if keep:
        members = pd.concat([members_table(name, tr, exp) for name, tr in {"identification": ident, **loops}.items()],
                            ignore_index=True)
    return Outcome(tables=tables, summary=summary, timings=timings, members=members)


def online_loop(exp: Experiment, seed, keep: bool, sim: dict) -> tuple[tuple[Trajectories, OnlineController], dict]:
    """The online (learning-type) closed loop: per-path gains re-designed from the path's own xi_{k|k}."""
    m, n = exp.model.m, exp.model.n
    info = {"initial": exp.online_initial if isinstance(exp.online_initial, str) else "given"}
    F0 = exp.online_initial if not isinstance(exp.online_initial, str) else np.zeros((m, n))
    if exp.online_initial == "nominal":
        res = nominal_gain(exp.plant, exp.xi_guess)
        info |= {"method": res.method, "status": res.status, "rate_at_guess": res.lam}
        if res.F is not None and np.all(np.isfinite(res.F)) and res.lam < 1:
            F0 = res.F
        else:
            info["used"] = "zero (no stabilizing nominal gain)"
    K = exp.disturbance.shape[0] - 1
    controller = OnlineController(exp.model, exp.online, F0, paths=exp.paths, horizon=K)
    bar, step = _progress("online", K + 1)
    with bar, logging_redirect_tqdm():
        tr = simulate(exp.plant, exp.enkf, F=F0, d=exp.disturbance, paths=exp.paths, seed=seed,
                      filter_sees_d=exp.filter_sees_disturbance, keep_members=keep, progress=step,
                      controller=controller, **sim)
    return (tr, controller), info


def add_online_tables(exp: Experiment, tables: dict, online, chosen, summary: dict) -> None:
    """The `controller` table, the gain index in `trajectories`, per-path and summary metrics of the
    online loop against the offline design of the same seed and the optimum on the true plant."""
    tr, controller = online
    d = controller.decisions()
    P, p, m, n = controller.P, exp.model.p, exp.model.m, exp.model.n
    Abar, Bbar = exp.plant.moment_factors(None)
    with np.errstate(all="ignore"):
        rate_plant = rates(Abar, Bbar, np.nan_to_num(d.F, nan=np.inf)) if len(d.k) else np.zeros(0)
        rate_plant[~np.all(np.isfinite(d.F), axis=(1, 2))] = np.nan
        initial_plant = rates(Abar, Bbar, controller.F0)
    rows = {"path": np.concatenate([np.arange(P), d.path]), "k": np.concatenate([np.full(P, -1), d.k]),
            "adopted": np.concatenate([np.ones(P, bool), d.adopted]),
            "reason": np.concatenate([np.full(P, "initial", dtype=object), d.reason]),
            "rate_model": np.concatenate([np.full(P, np.nan), d.rate_model]),
            "rate_current": np.concatenate([np.full(P, np.nan), d.rate_current]),
            "rate_plant": np.concatenate([initial_plant, rate_plant])}
    rows |= _columns("mean", np.concatenate([np.full((P, p), np.nan), d.mean]))
    rows |= {f"cov[{i},{j}]": np.concatenate([np.full(P, np.nan), d.cov[:, i, j]]) for i in range(p) for j in range(p)}
    rows |= _columns("F", np.concatenate([controller.F0, d.F]).reshape(-1, m * n))
    table = pd.DataFrame(rows)          # the initial gains (k = -1: in use from k = 0), then in order of k
    # gain index: the initial gain is 0, then a path's adopted gains in order (-1: not adopted)
    table.insert(4, "gain_index", np.where(table["adopted"], table.groupby("path")["adopted"].cumsum() - 1, -1))
    table = table.sort_values(["path", "k"], kind="stable", ignore_index=True)
    tables["controller"] = table

    # the gain in use per (k, path) as F[i] columns (the recording draws them as the gain history):
    # online rows from the gain index, the offline closed loop its fixed F, the open loop 0
    traj = tables["trajectories"]
    gains = np.zeros((len(traj), m * n))
    experiment = traj["experiment"].to_numpy()
    on = experiment == "online"
    history = controller.gain_history()
    paths_k = traj["path"].to_numpy()[on]
    gains[on] = np.stack([history[j][i].ravel() for j, i in zip(paths_k, tr.gain_index.ravel())]) if on.any() else 0
    if chosen is not None and chosen.F is not None:
        gains[experiment == "closed_loop"] = chosen.F.ravel()
    traj[[f"F[{i}]" for i in range(m * n)]] = gains
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
    optimum = min((safe_synthesize(exp.plant, truth, method, {}) for method in ("proposed", "policy_iteration")),
                  key=lambda res: res.lam if np.isfinite(res.lam) else np.inf)
    offline = safe_rate(exp.plant, None, chosen.F) if chosen is not None and chosen.F is not None else np.nan
    q = np.nanpercentile(final, [10, 50, 90]) if np.isfinite(final).any() else [np.nan] * 3
    online_metrics = {"final_rate_plant_q10": q[0], "final_rate_plant_median": q[1], "final_rate_plant_q90": q[2],
                      "final_stable_fraction": float(np.mean(final < 1)),
                      "first_stable_k_median": float(np.median(first[first >= 0])) if (first >= 0).any() else np.nan,
                      "never_stable_fraction": float(np.mean(first < 0)),
                      "adoptions_per_path": float(d.adopted.sum() / P),
                      # the k-window rate over the paths that did not diverge (the `rate` column is NaN
                      # as soon as one path diverged)
                      "rate_not_diverged": empirical_rate(tr.q[:, tr.failed_at < 0], *exp.rate_window)[0]
                      if (tr.failed_at < 0).any() else np.nan,
                      "offline_rate_plant": offline, "optimal_rate_plant": optimum.lam}
    metrics = tables["metrics"]
    for name, value in online_metrics.items():
        metrics[name] = np.where(metrics["experiment"] == "online", value, np.nan)
    summary["online"] = {k: (None if not np.isfinite(v) else float(v)) for k, v in online_metrics.items()}


def safe_synthesize(model, moments, method: str, options: dict) -> SynthesisResult:
    """`synthesize`, with every way a design can fail on this system as a status, never an exception.

    not_applicable: pole placement without poles in the config. failed: <reason>: the method raised
    (e.g. a Riccati equation without a solution) or returned a gain that is not finite."""
    if method == "pole_placement" and options.get("poles") is None:
        return SynthesisResult(method, None, float("nan"), "not_applicable", nbar=0,
                               info={"reason": "no poles in the config (plant.poles or gain.options.poles)"})
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


def identification_feedback(exp: Experiment) -> tuple[np.ndarray | None, dict]:
    """The gain of the identification run (None: open loop) and what was decided, for the summary.

    auto: open loop when the plant at the nominal guess xi_guess (prior knowledge, by default the mean
    of the plant's distribution) is mean-square stable in open loop, else nominal: a stabilizing
    gain designed on the plant at xi_guess (`nominal_gain`)."""
    mode = exp.identification_feedback
    info = {"mode": mode}
    if mode == "none":
        return None, info
    if mode == "given":
        return exp.identification_gain, info | {"used": "given"}
    guess = MomentModel.deterministic(exp.xi_guess)
    with np.errstate(all="ignore"):
        info["open_loop_rate_at_guess"] = safe_rate(exp.plant, guess, np.zeros((exp.plant.m, exp.plant.n)))
    if mode == "auto" and info["open_loop_rate_at_guess"] < 1:
        return None, info | {"used": "open_loop"}
    res = nominal_gain(exp.plant, exp.xi_guess)
    info |= {"used": "nominal", "method": res.method, "status": res.status, "rate_at_guess": res.lam}
    if res.F is None or not np.all(np.isfinite(res.F)) or not res.lam < 1:
        info["used"] = "open_loop (no stabilizing nominal gain)"
        return None, info
    with np.errstate(all="ignore"):
        info["rate_plant"] = safe_rate(exp.plant, None, res.F)
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
    """{"name[i]": values[..., i].ravel()} for the last axis of values."""
    return {f"{name}[{i}]": values[..., i].ravel() for i in range(values.shape[-1])}


def trajectory_table(experiment: str, tr: Trajectories | None, exp: Experiment | None = None) -> pd.DataFrame:
    """One row per (k, path): plant q, y, u and EnKF mean/spread of x and xi before/after filtering."""
    if tr is None:                       # no gain to simulate: an empty table with the usual columns
        n, p, ny, m = exp.model.n, exp.model.p, exp.model.ny, exp.model.m
        shape = lambda d: np.zeros((0, 0, d))
        tr = Trajectories(q=shape(n), y=shape(ny), u=shape(m), psi_pred_mean=shape(n + p),
                          psi_pred_std=shape(n + p), psi_filt_mean=shape(n + p), psi_filt_std=shape(n + p),
                          failed_at=np.zeros(0, int), failure=np.zeros(0, object), n=n)
    steps, P = tr.q.shape[:2]
    cols = {"experiment": np.full(steps * P, experiment), "k": np.repeat(np.arange(steps), P),
            "path": np.tile(np.arange(P), steps)}
    cols.update(_columns("q", tr.q) | _columns("y", tr.y) | _columns("u", tr.u))
    for stage in ("pred", "filt"):
        for stat in ("mean", "std"):
            psi = getattr(tr, f"psi_{stage}_{stat}")
            cols.update(_columns(f"x_{stage}_{stat}", tr.x(psi)) | _columns(f"xi_{stage}_{stat}", tr.xi(psi)))
    return pd.DataFrame(cols)


def members_table(experiment: str, tr: Trajectories, exp: Experiment) -> pd.DataFrame:
    """Every filtered ensemble member: one row per (k, path, member) (tracking level `full`)."""
    steps, P, M, _ = tr.members.shape
    cols = {"experiment": np.full(steps * P * M, experiment), "k": np.repeat(np.arange(steps), P * M),
            "path": np.tile(np.repeat(np.arange(P), M), steps), "member": np.tile(np.arange(M), steps * P)}
    cols.update(_columns("x_filt", tr.x(tr.members)) | _columns("xi_filt", tr.xi(tr.members)))
    return pd.DataFrame(cols)


def path_table(runs: dict[str, Trajectories]) -> pd.DataFrame:
    """Per path: the step it failed at (-1: never) and why."""
    return pd.DataFrame([{"experiment": name, "path": j, "failed_at": int(tr.failed_at[j]),
                          "failure": str(tr.failure[j])}
                         for name, tr in runs.items() for j in range(tr.failed_at.size)])


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
    (lam_box, NaN for other methods), F. designs: {(source, method): (moments, SynthesisResult)};
    `selected` is the (source, method) the closed loop used (gain.source; ("fixed", "fixed") for a given F).

    Only reproducible numbers go into tables; synthesis times are in run.json's timings."""
    rows = []
    for (source, method), (moments, res) in designs.items():
        found = res.F is not None
        F = res.F if found else np.full((exp.model.m, exp.model.n), np.nan)
        rows.append({"distribution": source, "method": method,
                     "selected": (source, method) == selected,
                     "status": res.status, "lam": res.lam, "lam_lower": res.lam_lower,
                     "lower_certified": res.lower_certified, "nbar": res.nbar,
                     "rate_model": safe_rate(exp.model, moments, F) if found and moments is not None else np.nan,
                     "rate_plant": safe_rate(exp.plant, None, F) if found else np.nan,
                     **performance(exp, moments, F if found and moments is not None else None),
                     "lam_box": res.info.get("lam_box", np.nan),
                     **{f"F[{i}]": v for i, v in enumerate(F.ravel())}})
    return pd.DataFrame(rows)


def performance(exp: Experiment, moments, F) -> dict:
    """Exact LQ cost (weights I, I) from the plant's q0 and averaged over x0 ~ N(0, I), and the H2 norm
    from d (added on u) to [x; F x], on the true plant and on the design moments; inf where not
    mean-square stable, NaN without a gain."""
    keys = ("lq_cost_q0_plant", "lq_cost_plant", "h2_plant", "lq_cost_model", "h2_model")
    if F is None or not np.all(np.isfinite(F)):
        return dict.fromkeys(keys, np.nan)
    return {"lq_cost_q0_plant": lq_cost(exp.plant, None, F, exp.q0), "lq_cost_plant": lq_cost(exp.plant, None, F),
            "h2_plant": h2_norm(exp.plant, None, F), "lq_cost_model": lq_cost(exp.model, moments, F),
            "h2_model": h2_norm(exp.model, moments, F)}


def metrics_table(exp: Experiment, loops: dict[str, Trajectories]) -> pd.DataFrame:
    """Per loop: empirical rate over rate_window with its 95% interval, failures, estimation error."""
    k_from, k_to = exp.rate_window
    rows = []
    for name, tr in loops.items():
        rate, low, high = empirical_rate(tr.q, k_from, k_to)
        err = tr.x(tr.psi_pred_mean) - tr.q
        rows.append({"experiment": name, "status": tr.status, "rate": rate, "rate_low": low, "rate_high": high,
                     "k_from": k_from, "k_to": k_to, "paths": tr.q.shape[1],
                     "failed_fraction": float(np.mean(tr.failed_at >= 0)),
                     "x_error_rms": float(np.sqrt(np.nanmean(np.sum(err ** 2, axis=-1)))),
                     "q_rms_final": float(np.sqrt(np.mean(np.sum(tr.q[-1] ** 2, axis=-1)))),
                     **estimation_quality(exp, tr)})
    return pd.DataFrame(rows, columns=["experiment", "status", "rate", "rate_low", "rate_high", "k_from", "k_to",
                                       "paths", "failed_fraction", "x_error_rms", "q_rms_final", *ESTIMATION])


ESTIMATION = ("x_rmse", "x_spread_error", "xi_rmse", "xi_spread_error")


def estimation_quality(exp: Experiment, tr: Trajectories) -> dict:
    """RMSE sqrt(mean ||e||^2) of the filtered x_{k|k} against q_k and of xi_{k|k} against the true
    xi, over steps k = 1..K and paths not failed, and the spread/error ratio sqrt(mean sum std^2) / RMSE
    (1: the ensemble spread matches its error). The true xi at k is T s_{k-1} + t, the coefficients
    that moved the plant into q_k, with (T, t) from `truth_map` (NaN when the model's xi has no
    value in the plant's terms)."""
    def rmse_ratio(err, std):
        rmse = np.sqrt(np.nanmean(np.sum(err ** 2, axis=-1)))
        return float(rmse), float(np.sqrt(np.nanmean(np.sum(std ** 2, axis=-1))) / rmse)
    out = dict.fromkeys(ESTIMATION, np.nan)
    if tr.q.shape[0] < 2:
        return out
    with np.errstate(all="ignore"):
        out["x_rmse"], out["x_spread_error"] = rmse_ratio(tr.x(tr.psi_filt_mean)[1:] - tr.q[1:],
                                                         tr.x(tr.psi_filt_std)[1:])
        truth = truth_map(exp.model, exp.plant) if tr.s is not None else None
        if truth is not None:
            T, t = truth
            out["xi_rmse"], out["xi_spread_error"] = rmse_ratio(tr.xi(tr.psi_filt_mean)[1:] - (tr.s[:-1] @ T.T + t),
                                                               tr.xi(tr.psi_filt_std)[1:])
    return out


def exact_table(exp: Experiment, chosen: SynthesisResult | None) -> pd.DataFrame:
    """sqrt(E||q_k||^2) of the ideal loops (state feedback, true plant distribution), exactly."""
    frames = []
    gains = ([("closed_loop", chosen.F)] if chosen is not None and chosen.F is not None else []) + \
        [("open_loop", np.zeros((exp.plant.m, exp.plant.n)))]
    for name, F in gains:
        with np.errstate(all="ignore"):
            _, second = second_moments(exp.plant, None, F, exp.q0, exp.disturbance)
        frames.append(pd.DataFrame({"experiment": name, "k": np.arange(second.shape[0]),
                                    "rms": np.sqrt(np.trace(second, axis1=1, axis2=2))}))
    return pd.concat(frames, ignore_index=True)


def _summary(exp: Experiment, dist, chosen, tables: dict) -> dict:
    """Key numbers of the run (run.json `summary`); what print_summary shows."""
    s = {"plant": exp.plant_name, "model": exp.model_name, "gain_method": exp.gain_method,
         "rate_window": list(exp.rate_window)}
    if dist is not None:
        s.update(nbar=int(exp.model.Gbar(dist).shape[0]), xi_mean=dist.mean.tolist())
    if chosen is not None:
        s.update(synthesis_status=chosen.status, lam=chosen.lam,
                 rate_plant=safe_rate(exp.plant, None, chosen.F) if chosen.F is not None else None)
    gains = tables["gains"]
    s["designs"] = {row.method: row.status for row in gains.itertuples() if row.distribution == "identified"}
    paths = tables["paths"]
    for row in tables["metrics"].itertuples():
        s[f"{row.experiment}_status"] = row.status
        s[f"{row.experiment}_rate"] = [row.rate, row.rate_low, row.rate_high]
        failed = paths[(paths["experiment"] == row.experiment) & (paths["failed_at"] >= 0)]["failed_at"]
        if len(failed):
            s[f"{row.experiment}_failed"] = {"fraction": row.failed_fraction, "first_k": int(failed.min()),
                                             "median_k": float(failed.median())}
    if exp.reference is not None:
        s["reference"] = exp.reference
    return s


