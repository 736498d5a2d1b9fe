"""What every synthesis method returns, and the mean (LTI) model the classical designs start from."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..analysis import ms_rate
from ..systems import AffineRandomSystem, MomentModel

STATUSES = ("optimal", "not_ms_stabilizable", "infimum_not_attained", "solver_failed", "designed", "not_converged",
            "not_applicable", "failed: <reason>")      # nominal_lmi adds `_on_mean_model` to what it certifies


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
