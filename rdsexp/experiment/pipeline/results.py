"""What each stage of a run returns: typed results, from which the tables and the run summary are derived.

identification + modeling -> `Identified` (the stage cache stores it whole), the moments' bootstrap ->
`Uncertainty`, synthesis -> `DesignSet`, the loops' Monte Carlo judged -> `JudgedLoops`, the online loop ->
`OnlineResult`, a data run's held-out paths -> `Validation`. `record.run_summary` turns them into run.json's
summary in one place.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from ...numerics.modeling import correlations
from ...numerics.simulation import Trajectories
from ...numerics.synthesis import SynthesisResult
from ...numerics.systems import MomentModel
from ...numerics.verdict import Floor
from ..montecarlo import LoopSummary

MODELED = ("ok", "unsettled", "misfit", "at_prior_edge", "weakly_identified")   # the statuses that come with moments
KEPT_GAIN = "identification_gain"     # the method name of the identification's gain when the loop keeps it


@dataclass
class Identified:
    """The identification run(s) and the moments of xi modeled from them (Sec. IV of the paper).

    trajectories: the run the moments come from (the last pass of an iterated identification); moments:
    None where modeling failed, `failure` says why; feedback: how the plant was driven (the gain, or the
    recorded inputs); passes: an iterated identification's passes (None: one pass); covariance: the
    modeling window's covariance (sample | total); estimator: identification.estimator = simulated's account
    (replicates, usable, effective, the summary it matched), with `posterior` its draws of the moments (the prior
    box's where no posterior matched the summary: status unsettled or misfit)."""

    trajectories: Trajectories
    moments: MomentModel | None
    failure: str
    feedback: dict
    passes: dict | None = None
    covariance: str = "sample"
    estimator: dict | None = None
    posterior: Uncertainty | None = None

    @property
    def status(self) -> str:
        """ok; unsettled (passes that stopped before the moments settled, or a simulated estimator left with the
        paper's moments); misfit (no law the simulated estimator tried reproduces what the data read: the window's
        moments kept); at_prior_edge (the simulated estimator's posterior stopped by its prior box);
        weakly_identified (a component whose prior box the data hardly narrowed); or why there is no model."""
        passes, estimator = self.passes or {}, self.estimator or {}
        if self.failure or self.moments is None:
            return self.failure
        if (passes.get("passes") and not passes.get("converged")) or "fallback" in estimator:
            return "unsettled"
        if "misfit" in estimator:
            return "misfit"
        if estimator.get("at_prior_edge"):
            return "at_prior_edge"
        return "weakly_identified" if estimator.get("weakly_identified") else "ok"

    def summary(self) -> dict:
        s = {"identification_feedback": self.feedback, "modeling_status": self.status}
        if self.passes is not None:
            s["identification_passes"] = self.passes
        if self.moments is not None:
            s["modeling_covariance"] = self.covariance
        s["modeling_estimator"] = self.estimator or {"name": "paper"}
        return s


@dataclass
class Uncertainty:
    """Bootstrap draws of the modeled moments: means (B, p) and covariances (B, p, p), over the recorded
    paths (`over` = paths) or over blocks of one path's window (window blocks)."""

    mean: np.ndarray
    cov: np.ndarray
    resamples: int
    block: int
    over: str

    @property
    def draws(self) -> tuple[np.ndarray, np.ndarray]:
        return self.mean, self.cov

    def summary(self) -> dict:
        """The spread over the draws: std of each xi mean, of each xi std and (p > 1) of each correlation."""
        std = np.sqrt(np.clip(np.diagonal(self.cov, axis1=1, axis2=2), 0, None))
        out = {"resamples": self.resamples, "block": self.block, "over": self.over,
               "xi_mean_sd": self.mean.std(axis=0, ddof=1).tolist(), "xi_std_sd": std.std(axis=0, ddof=1).tolist()}
        if self.mean.shape[1] > 1:
            out["xi_corr_sd"] = correlations(self.cov).std(axis=0, ddof=1).tolist()
        return {"modeling_uncertainty": out}


@dataclass
class DesignSet:
    """Every design of the run: {(source, method): (the moments designed on, SynthesisResult)}, source
    identified | reported | fixed; `selected`, the one whose gain the loops use; `fallback`, why the
    configured method gave way to gain.fallback; `choice`, the designed gain against the identification's
    over the moments' draws (`design.safer_gain`)."""

    designs: dict[tuple[str, str], tuple[MomentModel | None, SynthesisResult]]
    selected: tuple[str, str]
    fallback: dict | None = None
    choice: dict | None = None

    @property
    def chosen(self) -> SynthesisResult | None:
        return self.designs.get(self.selected, (None, None))[1]

    @property
    def moments(self) -> MomentModel | None:
        """The moments the selected gain was designed on (the loops' observer draws xi from them)."""
        return self.designs.get(self.selected, (None, None))[0]

    @property
    def gain(self) -> np.ndarray | None:
        """The loops' gain F (m, n), None without one."""
        return None if self.chosen is None else self.chosen.F

    def method(self, configured: str) -> str:
        """The method whose gain the loop uses: gain.fallback's, the identification's kept gain, or `configured`."""
        if (self.choice or {}).get("kept") == "identification":
            return KEPT_GAIN
        return self.fallback["method"] if self.fallback else configured

    def summary(self) -> dict:
        s = {}
        if self.fallback:
            s["gain_fallback"] = self.fallback
        if self.choice:
            s["gain_choice"] = self.choice
        return s


@dataclass(frozen=True)
class RateWindow:
    """The window [k_from, k_to] the loops' rates are measured over: from the config (source
    "config"), or placed on the ideal loop's exact curve above the noise floor ("auto"); placed False
    when no such window exists (k is then the span from the window's start to the horizon, shown but
    not trusted: the verdict is undetermined)."""

    k: tuple[int, int]
    source: str
    placed: bool = True


@dataclass
class JudgedLoops:
    """The loops' Monte Carlo reduced (LoopSummary per loop), the closed loop's noise floor, the ideal loops'
    exact RMS curves (`exact` table), the rate window and the per-loop `metrics` table with its verdicts."""

    loops: dict[str, LoopSummary]
    floor: Floor | None
    exact: pd.DataFrame
    window: RateWindow
    metrics: pd.DataFrame
    looks: list = field(default_factory=list)     # closed_loop.paths auto: each look's paths, level and verdicts
    asking: list = field(default_factory=list)    # and the loops still asking for paths at the budget

    def summary(self) -> dict:
        return {"rate_window": list(self.window.k),
                "rate_window_source": self.window.source if self.window.placed else "none",
                "noise_floor": np.nan if self.floor is None else self.floor.rms,
                **({"loop_looks": self.looks, "loop_paths_asking": self.asking} if self.looks else {})}


@dataclass
class OnlineResult:
    """The online loop: its LoopSummary, the chunks' controllers [(first path, OnlineController)] and how
    it started (`initial`); after `online.analyse`, its decisions (`controller` table), per-path columns
    (`paths`: first_stable_k, final_rate_plant) and metrics."""

    loop: LoopSummary
    controllers: list
    initial: dict
    controller: pd.DataFrame | None = None
    paths: pd.DataFrame | None = None
    metrics: dict = field(default_factory=dict)

    def extended(self, more: OnlineResult) -> OnlineResult:
        """This loop's paths followed by `more`'s (a later look of closed_loop.paths auto), before `analyse`."""
        return dataclasses.replace(self, loop=LoopSummary.concat([self.loop, more.loop]),
                                   controllers=self.controllers + more.controllers)


@dataclass
class Validation:
    """A data run's held-out paths: the `validation` table and its summary entry."""

    table: pd.DataFrame
    summary: dict
