"""Mean-square LQ: the optimal state feedback for E sum_k (x_k^T Q x_k + u_k^T R u_k) of the random system.

With xi_k i.i.d. and independent of x_k, the optimal cost x0^T P x0 solves the generalized Riccati equation
    P = Q + E[A^T P A] - E[A^T P B] (R + E[B^T P B])^-1 E[B^T P A],   F = -(R + E[B^T P B])^-1 E[B^T P A],
where E[M^T P N] = sum_r Mbar_r^T P Nbar_r over the moment factors (Abar_r, Bbar_r) of Gbar (the same
moments as Theorem 2). With the covariance 0 it is the discrete algebraic Riccati equation of the mean model.
It is solved by Newton's method (Hewer's iteration): from a mean-square stabilizing F, P = the exact cost
matrix of F (generalized Lyapunov equation, `analysis.cost_matrix`), then F from P; every iterate is
mean-square stabilizing and P decreases monotonically to the stabilizing solution.
"""
from __future__ import annotations

import numpy as np

from ..analysis import lyapunov, ms_rate, weight
from ..systems import AffineRandomSystem
from .base import SynthesisResult
from .riccati import policy_iteration


def riccati_residual(Abar, Bbar, P, Q, R) -> tuple[np.ndarray, np.ndarray]:
    """(residual (n, n) of the generalized Riccati equation at P, the gain F (m, n) it defines).

    Abar (nbar, n, n), Bbar (nbar, n, m): moment factors (`AffineRandomSystem.moment_factors`)."""
    PA, PB = P @ Abar, P @ Bbar                                  # sum_r M_r^T P N_r = einsum of M and P N
    APA = np.einsum("rji,rjl->il", Abar, PA)
    BPA = np.einsum("rji,rjl->il", Bbar, PA)
    BPB = np.einsum("rji,rjl->il", Bbar, PB)
    F = -np.linalg.solve(R + BPB, BPA)
    return Q + APA + BPA.T @ F - P, F


def ms_lqr(system, dist, *, state_weight=1.0, input_weight=1.0, tol: float = 1e-13, max_iter: int = 50):
    """Mean-square LQ optimal gain; lam is its exact mean-square rate on `dist`.

    state_weight Q, input_weight R: a number w > 0 (w I) or a symmetric positive definite matrix.
    Newton starts from the open loop when it is mean-square stable, else from the rate-optimal gain
    of `policy_iteration`; if its certified lower bound on the optimal rate is >= 1 no finite cost
    exists (status `not_ms_stabilizable`, F None; `not_converged` where no stabilizing start was
    found but none is proven impossible). info: cost_trace = trace(P) (the cost averaged over
    x0 ~ N(0, I)), riccati_residual (max |residual| / max |P|), iterations.
    """
    n, m = system.n, system.m
    Q, R = weight("state_weight", state_weight, n), weight("input_weight", input_weight, m)
    F = np.zeros((m, n))
    if ms_rate(system, dist, F) >= 1:
        start = policy_iteration(system, dist)
        if start.lam >= 1:                # no finite cost only where the optimal rate is proven >= 1
            proven = start.lam_lower >= 1    # policy iteration's lower end is always proven
            return SynthesisResult("ms_lqr", None, float("nan"), "not_ms_stabilizable" if proven else "not_converged",
                                   system.Gbar(dist).shape[0], info={"rate_optimal": start.lam,
                                                                     "rate_optimal_lower": start.lam_lower})
        F = start.F
    Abar, Bbar = system.moment_factors(dist)
    P = lyapunov(Abar + Bbar @ F, Q + F.T @ R @ F)          # the exact cost matrix of F (analysis.cost_matrix)
    status, iterations = "solver_failed", 0
    while iterations < max_iter:
        iterations += 1
        _, F = riccati_residual(Abar, Bbar, P, Q, R)
        P_new = lyapunov(Abar + Bbar @ F, Q + F.T @ R @ F)
        if P_new is None:                                 # Newton iterates stay stabilizing in exact arithmetic
            break
        change = np.abs(P_new - P).max()
        P = P_new
        if change <= tol * np.abs(P).max():
            status = "optimal"
            break
    residual, F = riccati_residual(Abar, Bbar, P, Q, R)
    lam = ms_rate(system, dist, F)
    if lam >= 1:                                          # the gain of the last P must itself be stabilizing
        status = "solver_failed"
    return SynthesisResult("ms_lqr", F, lam, status, len(Abar),
                           info={"cost_trace": float(np.trace(P)), "iterations": iterations,
                                 "riccati_residual": float(np.abs(residual).max() / np.abs(P).max())})


def _check(options: dict, system: AffineRandomSystem) -> None:
    """One-line ValueError for bad ms_lqr options (before any work)."""
    weight("state_weight", options.get("state_weight", 1.0), system.n)
    weight("input_weight", options.get("input_weight", 1.0), system.m)
    for name in ("tol", "max_iter"):
        v = options.get(name, 1)
        if not (isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) and v > 0):
            raise ValueError(f"{name}: {v!r} is not allowed, expected a number > 0")


ms_lqr.check_options = _check
