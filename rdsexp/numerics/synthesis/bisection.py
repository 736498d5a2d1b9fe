"""Certified bisection on the decay rate lambda, shared by every LMI design.

An LMI design offers `solve(lam) -> Trial`: a candidate gain from the LMI at that lambda and
whether the solver found the LMI infeasible there. The bisection keeps the upper end certified
by the exact mean-square rate (`ms_rate`) of a gain in hand; the lower end is a proven bound from
policy iteration's SDP-free certificate (`rate_lower_bound`), either the seed's or, where the
solver's infeasibility set it, a check of it, so every number it reports is true of what it returns.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..analysis import ms_rate
from ..systems import AffineRandomSystem, MomentModel
from .base import SynthesisResult
from .riccati import policy_iteration

SEED_MARGIN = 3e-8           # above the seed's upper end: the trial lambda of the confirming solve


@dataclass
class Trial:
    """Outcome of one LMI solve at a trial lambda.

    F: (m, n) gain from the solve (None if the solver returned nothing usable); X: (n, n) its
    Lyapunov certificate; infeasible: the solver proved the LMI infeasible at this lambda."""

    F: np.ndarray | None
    X: np.ndarray | None
    infeasible: bool


def certified_bisection(system: AffineRandomSystem, dist: MomentModel, solve: Callable[[float], Trial], *,
                        method: str, nbar: int, tol: float = 1e-7, max_iter: int = 60,
                        x_cond_limit: float = 1e6, bracket: tuple[float, float] | None = None) -> SynthesisResult:
    """Minimise lambda over an LMI family by bisection on lambda^2 with a certified upper end.

    The upper end `lam` is always the exact rate (`ms_rate`) on `dist` of a gain in hand: F = 0
    (the open loop) to start, then the best gain any solve returned. A solve slightly above the
    optimum returns a nearly optimal gain, so after each trial whose gain confirms it (exact rate
    <= trial) the next one probes just below the upper end (lam - tol/2); otherwise the interval
    is halved in lambda^2. A trial whose gain does not confirm it raises the lower end (checked at
    the end).

    bracket (lower, upper): a certified bracket of the optimum from elsewhere (policy iteration's,
    whose lower end is proven without an SDP): the lower end is taken as proven, and one solve at
    upper + SEED_MARGIN returns a gain whose exact rate confirms the upper end, closing the bracket
    in one solve; where it does not, the bisection goes on from [lower, best rate in hand].
    (A solve just below the lower end cannot prove the LMI infeasible there: the solver's margin t
    is within its accuracy of 0 on both sides of the optimum, see `lmi.T_PROOF`.)

    A lower end the bisection set is checked: a trial whose gain does not confirm it need not be
    infeasible, and the solver's margin is a floating-point number near its accuracy where the
    certificate X is ill-conditioned, so neither proves a lower end. Policy iteration started from
    the best gain gives an SDP-free proven lower bound (and its gain, where it proves that gain
    optimal and it is better); the lower end is the largest proven bound (info: lmi_lower, where
    the bisection had put it).

    Returns lam (exact rate of F, so achieved) and lam_lower (proven: the bracket's, policy
    iteration's or 0). Status `optimal` only when this proven bracket is closed (within tol);
    `not_ms_stabilizable` when lam >= 1 and the lower end is >= 1 or the bracket is closed;
    `solver_failed` when no solve gave a gain better than the open loop; `infimum_not_attained`
    when the lower end is <= tol or the certificate X is ill-conditioned (cond > x_cond_limit)
    without the solver's proof of infeasibility at the last unconfirmed trial; `not_converged`
    otherwise. info: solves, cond_X, lmi_lower, gain_from_check.
    """
    best_F = np.zeros((system.m, system.n))
    lam = ms_rate(system, dist, best_F)
    lo, certified, best_X, solves, confirmed = 0.0, True, None, 0, True
    proven = 0.0                              # the largest lower end proven so far
    if bracket is not None and 0 < bracket[0] <= bracket[1] < lam:
        result = solve(bracket[1] + SEED_MARGIN)
        solves += 1
        if result.F is not None and (rate := ms_rate(system, dist, result.F)) < lam:
            lam, best_F, best_X = rate, result.F, result.X
        lo = proven = min(bracket[0], lam)
        confirmed = lam - lo > tol                  # not closed: the bisection probes below lam first
    while lam - lo > tol and solves < max_iter:
        trial = max(lam - tol / 2, 0.0) if confirmed else np.sqrt((lo ** 2 + lam ** 2) / 2)
        solves += 1
        result = solve(trial)
        confirmed = False
        if result.F is not None:
            rate = ms_rate(system, dist, result.F)
            confirmed = rate <= trial
            if rate < lam:                                               # any gain certifies its rate
                lam, best_F, best_X = rate, result.F, result.X
        if not confirmed:
            lo = min(trial, lam)
            certified = result.infeasible
    info = {"solves": solves}
    if best_X is not None:
        info["cond_X"] = float(np.linalg.cond(best_X))
    if lo > proven:                           # the bisection moved the lower end: check it
        check = policy_iteration(system, dist, F0=best_F)
        if check.status == "optimal" and (rate := ms_rate(system, dist, check.F)) < lam:
            lam, best_F = rate, check.F       # the optimum the LMI came within tol of: its rate is certified
            info["gain_from_check"] = True
        info["lmi_lower"] = lo
        lo = min(max(proven, check.lam_lower), lam)      # policy iteration's lam_lower is finite, >= 0
    if lam >= 1.0:                            # proven only by a lower end >= 1 or a closed bracket
        status = "not_ms_stabilizable" if lo >= 1.0 or lam - lo <= tol else "not_converged"
    elif best_X is None:
        status = "solver_failed"
    elif lo <= tol or (not certified and info["cond_X"] > x_cond_limit):
        # the certificate X degenerates towards the infimum, which no gain attains
        # (e.g. a deterministic model, where the infimum is the dead-beat rate 0)
        status = "infimum_not_attained"
    elif lam - lo > tol:
        status = "not_converged"            # max_iter solves, or a lower end the check did not confirm
    else:
        status = "optimal"
    # lo is proven (the seed's or policy iteration's bound, or 0); `certified` (the solver's word)
    # only decides whether a degenerate certificate X marks an infimum
    return SynthesisResult(method, best_F, lam, status, nbar, lam_lower=lo, info=info)
