"""What every synthesis method returns, and the mean (LTI) model the classical designs start from."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..analysis import ms_rate
from ..systems import AffineRandomSystem, MomentModel

# every design status, with what it means in one line (the run summary and the data dictionary show it)
STATUSES = {
    "optimal": "the returned gain's rate is within tol of a proven lower bound on the optimal rate",
    "box_optimal": "robust_box: optimal for the box around the moments (certified over every vertex)",
    "designed": "a classical design (pole placement, LQR): lam is its rate on the mean (LTI) model, no optimality",
    "infimum_not_attained": "the optimal rate is an infimum that no gain attains (the certificate degenerates); "
                            "the returned gain's rate is exact but can be improved a little",
    "not_converged": "the iterations stopped (max_iter) before the bracket on the optimal rate closed; the "
                     "returned gain's rate is exact",
    "not_ms_stabilizable": "proven: no gain makes the design moments mean-square stable (lower bound >= 1)",
    "infeasible": "robust_box: no gain is certified over the whole box",
    "solver_failed": "the solver returned no usable gain; the rate is not certified",
    "not_applicable": "the method does not apply to this system or config (pole placement without poles, or an LMI "
                      "design on more states than gain.lmi_max_n)",
    "fixed": "a given gain (gain.source=fixed): no design, its exact rate",
    "kept": "the identification run's own gain, kept: the designed gain's exact rate was at or above 1 at the 95% "
            "quantile of the modeled moments' draws and the identification gain's lower (gain_choice); its exact "
            "rate on the identified moments",
    "failed: <reason>": "the method raised or returned a gain that is not finite; the reason follows",
}
MEAN_MODEL = "_on_mean_model"     # nominal_lmi's suffix: what it certifies is the LTI mean model


def status_meaning(status: str) -> str:
    """One line saying what a design status means (nominal_lmi's `_on_mean_model` statuses included)."""
    if status.startswith("failed"):
        return STATUSES["failed: <reason>"]
    if status.endswith(MEAN_MODEL):
        base = status[:-len(MEAN_MODEL)]
        return f"on the LTI model with xi at its mean (not the random system): {STATUSES.get(base, base)}"
    return STATUSES.get(status, "unknown status")


@dataclass
class SynthesisResult:
    """A gain and how it was obtained.

    F: (m, n) gain for u = F x, or None if no gain was found. lam: the exact mean-square rate of F
    on the design distribution (so lam is certified: it is achieved). lam_lower: a proven lower
    bound on the optimal rate where the method gives one (policy iteration's SDP-free bound, also
    checking the LMI bisections), else NaN. nbar: rank of Gbar. seconds: wall time of `synthesize`.
    """

    method: str
    F: np.ndarray | None
    lam: float
    status: str
    nbar: int
    lam_lower: float = float("nan")
    seconds: float = 0.0
    info: dict = field(default_factory=dict)


def mean_model(system: AffineRandomSystem, dist: MomentModel) -> tuple[np.ndarray, np.ndarray]:
    """(A(mean), B(mean)): the LTI model with xi fixed to its mean, (n, n) and (n, m)."""
    A, B, _, _ = system.at(dist.mean)
    return A, B


def designed(method: str, system: AffineRandomSystem, dist: MomentModel, F: np.ndarray, **info) -> SynthesisResult:
    """A classical design: lam is its exact rate on the LTI mean model (what it was designed for)."""
    lam = ms_rate(system, MomentModel.deterministic(dist.mean), F)
    return SynthesisResult(method, F, lam, "designed", nbar=1, info=info)
