"""A data run (exp.data): the recorded (u, y) in place of a plant. Identification filters the recorded paths
(all but the held-out ones), the moments come with their uncertainty (a bootstrap over the recorded paths),
the designs are judged on the identified model only, the held-out paths validate the modeled law, and
(data.loops) the loops are simulated on the identified model, labelled so.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd

from ...numerics.distributions import ensemble_crps, from_spec, interval_hits
from ...numerics.enkf import sqrtm_psd
from ...numerics.simulation import bytes_per_path, path_generators
from ...numerics.systems import AffineRandomSystem, MomentModel
from ..config import Experiment
from ..montecarlo import MEMORY_BUDGET, Simulation
from .identification import two_point_ends
from .loops import Sample, loop_observer, run_loops
from .results import DesignSet, Validation
from .tables import path_table

VALIDATION_KEY = (4,)          # SeedSequence(seed, spawn_key=(4,)): the held-out paths' EnKF (stages use 0-2)
VALIDATION_LEVELS = (0.5, 0.9)  # central intervals whose coverage is reported
VALIDATION_COLUMNS = ("law", "output", "crps", "coverage_50", "coverage_90", "steps", "paths")
ON_MODEL = "_on_model"       # a data run's loops are named closed_loop_on_model, open_loop_on_model everywhere
ON_MODEL_LABEL = "simulated on the model, not the plant"


VALIDATION_SLACK = 0.07     # the coverage off its level that still reads calibrated (the EnKF's predictive on the
                            # true law and noise: 0.48 / 0.88, docs/own-data.md), or 3 standard errors over the paths


def validate_holdout(exp: Experiment, dist: MomentModel) -> Validation:
    """The modeled law on the held-out recorded paths (data.holdout), against the nominal model.

    For each law of xi, the EnKF runs on the held-out (u, y) with its predicted xi drawn i.i.d. from it
    (`EnKF.xi_prior`; a two-point component from its two-point law): `modeled`, the identified moments; `nominal`,
    xi fixed at their mean (zero covariance). The one-step-ahead predictive ensemble of y_k is every member's
    predicted output from psi_{k|k-1} plus output noise N(0, R) (the EnKF's R: the noise the model assumes), the
    same noise draws for both laws and the same EnKF streams (a paired comparison). Scored for
    k = max(K0, 1)..K (after the identification's warm-up) on every held-out path and output: CRPS (mean; lower
    is better) and the fraction of y_k inside the ensemble's central 50% and 90% intervals (calibrated: 0.5 and
    0.9). The table has one row per law and output, and `all`, the mean over outputs. The summary's
    `calibrated` says whether the modeled law's coverage is within VALIDATION_SLACK (or 3 standard errors over
    the held-out paths, if larger) of both levels: a wrong law (a Bernoulli at its mean) is not, nor is noise
    the EnKF assumes far from the data's (`modeling_estimator.noise_scale` estimates it)."""
    held = exp.data.holdout_data
    k_from = max(exp.identification.K0, 1)
    steps, P, ny = held.steps - k_from, held.paths, exp.model.ny
    laws = {"modeled": dist, "nominal": MomentModel(mean=dist.mean, cov=np.zeros_like(dist.cov))}
    rows, summary = [], {"paths": P, "k_from": k_from, "k_to": held.steps - 1, "levels": list(VALIDATION_LEVELS)}
    for law, moments in laws.items():
        sums, failed, per_path = score_holdout(exp, moments, k_from)
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
        if law == "modeled":
            summary |= calibration(total[1:], per_path)
    better = summary["modeled"]["crps"] < summary["nominal"]["crps"]
    summary["crps_gain"] = summary["nominal"]["crps"] - summary["modeled"]["crps"]
    summary["modeled_better"] = bool(better)
    return Validation(pd.DataFrame(rows, columns=list(VALIDATION_COLUMNS)), summary)


def calibration(coverage: np.ndarray, per_path: np.ndarray) -> dict:
    """Whether the coverage (levels,) of the central intervals is within the slack of each level: the larger of
    VALIDATION_SLACK and 3 standard errors of the coverage over the held-out paths (per_path (P, levels), the paths
    independent, the steps within one not)."""
    finite = per_path[np.all(np.isfinite(per_path), axis=1)]
    se = finite.std(axis=0, ddof=1) / np.sqrt(len(finite)) if len(finite) > 1 else np.full(coverage.size, np.inf)
    slack = np.maximum(VALIDATION_SLACK, 3 * se)
    off = np.abs(coverage - np.array(VALIDATION_LEVELS))
    return {"calibrated": bool(np.all(off <= slack)), "coverage_slack": slack.tolist()}


def score_holdout(exp: Experiment, moments: MomentModel, k_from: int) -> tuple[np.ndarray, int, np.ndarray]:
    """The held-out paths filtered with xi drawn from `moments`, in chunks of paths within the memory budget,
    scored as they come: sums (2 + levels, ny) per output of the CRPS and of the interval hits per level, and the
    count of finite (step, path) pairs; the number of paths whose EnKF failed; and each path's coverage per level
    over its outputs (P, levels)."""
    held, enkf = exp.data.holdout_data, exp.filter.enkf
    seed = np.random.SeedSequence(exp.seed, spawn_key=VALIDATION_KEY)
    noise_seed = np.random.SeedSequence(seed.entropy, spawn_key=seed.spawn_key + (2,))   # per path: chunk-free
    steps, P, ny, M = held.steps - k_from, held.paths, exp.model.ny, exp.filter.ensemble_size
    R_sqrt = sqrtm_psd(enkf.R)
    per_path = bytes_per_path(exp.model, enkf, ensemble_size=M, horizon=held.steps - 1) + 8 * 4 * held.steps * M * ny
    size = int(max(1, MEMORY_BUDGET // (3 * per_path)))
    # a two-point component (a Bernoulli link the model file states) drawn from its two-point law, as the data are
    ends = two_point_ends(exp)[0]
    observer = dataclasses.replace(enkf, xi_prior=moments, xi_ends=ends if ends.any() else None)
    sim = Simulation.of(exp, observer, None, seed,
                        d=np.zeros((held.steps, exp.model.m)), q0=np.zeros(exp.model.n), paths=P, filter_sees_d=True,
                        keep_members=False)
    sums = np.zeros((2 + len(VALIDATION_LEVELS), ny))      # crps, hits per level, count
    path_coverage = np.full((P, len(VALIDATION_LEVELS)), np.nan)
    failed = 0
    for first in range(0, P, size):
        count = min(size, P - first)
        part = held.select(slice(first, first + count))
        tr = sim.run(first, count, recorded=part, keep_forecast=True)
        v = np.stack([g.standard_normal((steps, M, ny)) for g in path_generators(noise_seed, 0,
                                                                                 range(first, first + count))],
                     axis=1) @ R_sqrt.T                                          # (T, count, M, ny)
        members = np.moveaxis(tr.y_forecast[k_from:] + v, 2, -1)                 # (T, count, ny, M)
        finite = np.all(np.isfinite(members), axis=-1)
        y = part.y[k_from:]
        with np.errstate(invalid="ignore"):
            sums[0] += np.where(finite, ensemble_crps(np.nan_to_num(members), y), 0.0).sum(axis=(0, 1))
            for j, level in enumerate(VALIDATION_LEVELS):
                hits = finite & interval_hits(np.nan_to_num(members), y, level)
                sums[1 + j] += hits.sum(axis=(0, 1))
                path_coverage[first:first + count, j] = hits.sum(axis=(0, 2)) / finite.sum(axis=(0, 2))
        sums[-1] += finite.sum(axis=(0, 1))
        failed += int(np.sum(tr.failed_at >= 0))
    return sums, failed, path_coverage


def model_system(exp: Experiment, dist: MomentModel) -> AffineRandomSystem:
    """The identified model as a system to simulate: the model's bases with xi ~ N(mean, cov) of the identified
    moments (a Gaussian law of those moments: the moments are all a data run knows of xi)."""
    law = from_spec({"family": "normal", "mean": dist.mean.tolist(), "cov": dist.cov.tolist()})
    return AffineRandomSystem(exp.model.A, exp.model.B, exp.model.C, exp.model.D, xi_dist=law)


def loops_on_model(exp: Experiment, stages, dist: MomentModel, designs: DesignSet, tables: dict, sink,
                   sample: Sample) -> dict:
    """data.loops: the closed loop (and, with closed_loop.open_loop, the open loop) of the loop's gain with the
    EnKF observer, simulated on the identified model (`model_system`, q0 = ones) exactly as a run simulates them
    on a plant (`loops.simulate_loops`: same seeds, chunks, noise floor, rate window and verdicts), named
    closed_loop_on_model and open_loop_on_model in every table and labelled so in the summary: they are evidence
    about the model, not about the system the data came from. Sets the metrics and exact tables and adds the
    loops' paths; returns the summary entry."""
    sexp = dataclasses.replace(exp, plant=model_system(exp, dist), q0=np.ones(exp.model.n), data=None)
    observer = loop_observer(sexp, dist)
    judged, _ = run_loops(sexp, stages, designs.gain, observer, sink, sample, suffix=ON_MODEL)
    loops = judged.loops
    rename = lambda frame: frame.assign(experiment=frame["experiment"] + ON_MODEL)
    tables["metrics"], tables["exact"] = rename(judged.metrics), rename(judged.exact)
    tables["paths"] = pd.concat([tables["paths"], rename(path_table(loops))], ignore_index=True)
    out = {"label": ON_MODEL_LABEL, "rate_window": list(judged.window.k), "xi_law": "normal (the identified moments)"}
    for row in judged.metrics.itertuples():
        out[row.experiment + ON_MODEL] = {"verdict": row.verdict, "verdict_reason": row.verdict_reason,
                                          "rate": [row.rate, row.rate_low, row.rate_high],
                                          "exact_rate": row.exact_rate, "failed_fraction": row.failed_fraction}
    return out
