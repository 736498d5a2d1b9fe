"""Mean-square LQ: the optimal state feedback for E sum_k (x_k^T Q x_k + u_k^T R u_k) of the random system.

With xi_k i.i.d. and independent of x_k, the optimal cost x0^T P x0 solves the generalized Riccati equation
    P = Q + E[A^T P A] - E[A^T P B] (R + E[B^T P B])^-1 E[B^T P A],   F = -(R + E[B^T P B])^-1 E[B^T P A],
where E[M^T P N] = sum_r Mbar_r^T P Nbar_r over the moment factors (Abar_r, Bbar_r) of Gbar (the same
moments as Theorem 2). With the covariance 0 it is the discrete algebraic Riccati equation of the mean model.
It is solved by Newton's method (Hewer's iteration): from a mean-square stabilizing F, P = the exact cost
matrix of F (generalized Lyapunov equation, `analysis.cost_matrix`), then F from P; every iterate is
mean-square stabilizing and P decreases monotonically to the stabilizing solution.

Beyond analysis.DENSE_SOLVE_MAX_N the Lyapunov equations are solved matrix-free (`analysis.stein_solve`)
and inexactly: the step P_{k+1} - P_k = D solves D - E[Acl_k^T D Acl_k] = Res(P_k), the Riccati
residual at P_k, and is solved only to the relative accuracy min(1e-2, |Res(P_k)| / |P_k|), which keeps
Newton's quadratic convergence at a fraction of the GMRES steps (inexact Newton).
"""
from __future__ import annotations

import numpy as np

from ..analysis import DENSE_SOLVE_MAX_N, DominantTerm, certified_stein, lyapunov, ms_rate, stein_solve, weight
from ..systems import AffineRandomSystem
from .base import SynthesisResult
from .riccati import policy_iteration

START_RTOL = 1e-2            # relative accuracy of the first (matrix-free) cost matrix
START_GMRES = 60             # GMRES steps allowed for it (a gain that is not stabilizing does not converge)
START_VALUE_STEPS = 64       # value-iteration steps tried for a stabilizing start


def riccati_residual(Abar, Bbar, P, Q, R) -> tuple[np.ndarray, np.ndarray]:
    """(residual (n, n) of the generalized Riccati equation at P, the gain F (m, n) it defines).

    Abar (nbar, n, n), Bbar (nbar, n, m): moment factors (`AffineRandomSystem.moment_factors`).
    sum_r M_r^T P N_r is one product of the stacked (nbar n, .) factors."""
    n, m = Abar.shape[1], Bbar.shape[2]
    PA, PB = (P @ Abar).reshape(-1, n), (P @ Bbar).reshape(-1, m)
    A, B = Abar.reshape(-1, n), Bbar.reshape(-1, m)
    APA, BPA, BPB = A.T @ PA, B.T @ PA, B.T @ PB
    F = -np.linalg.solve(R + BPB, BPA)
    return Q + APA + BPA.T @ F - P, F


def ms_lqr(system, dist, *, state_weight=1.0, input_weight=1.0, tol: float = 1e-13, max_iter: int = 50):
    """Mean-square LQ optimal gain; lam is its exact mean-square rate on `dist`.

    state_weight Q, input_weight R: a number w > 0 (w I) or a symmetric positive definite matrix.
    Newton starts from the open loop when it is mean-square stable, else from the rate-optimal gain of
    `policy_iteration` (beyond DENSE_SOLVE_MAX_N first from a value-iteration gain whose cost matrix
    certifies it stabilizing, `_ms_lqr_matrix_free`); if policy iteration's certified lower bound on
    the optimal rate is >= 1 no finite cost exists (status `not_ms_stabilizable`, F None;
    `not_converged` where no stabilizing start was found but none is proven impossible). Status
    `optimal` when Newton's step falls below tol max|P|.
    info: cost_trace = trace(P) (the cost averaged over x0 ~ N(0, I)), riccati_residual
    (max |residual| / max |P| at the returned P, the certificate of the cost), iterations.
    """
    n, m = system.n, system.m
    Q, R = weight("state_weight", state_weight, n), weight("input_weight", input_weight, m)
    Abar, Bbar = system.moment_factors(dist)
    if n > DENSE_SOLVE_MAX_N:
        return _ms_lqr_matrix_free(system, dist, Abar, Bbar, Q, R, tol, max_iter)
    F = np.zeros((m, n))
    if ms_rate(system, dist, F) >= 1:
        start = policy_iteration(system, dist)
        if start.lam >= 1:
            return _no_stabilizing_start(system, dist, start)
        F = start.F
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
    return _result(system, dist, Abar, Bbar, P, Q, R, status, iterations)


def _no_stabilizing_start(system, dist, start) -> SynthesisResult:
    """No finite cost only where the optimal rate is proven >= 1 (policy iteration's lower end is proven)."""
    return SynthesisResult("ms_lqr", None, float("nan"), "not_ms_stabilizable" if start.lam_lower >= 1 else
                           "not_converged", system.Gbar(dist).shape[0],
                           info={"rate_optimal": start.lam, "rate_optimal_lower": start.lam_lower})


def _result(system, dist, Abar, Bbar, P, Q, R, status, iterations) -> SynthesisResult:
    """The gain of the last P, its exact rate (`solver_failed` if >= 1) and the Riccati residual at P."""
    residual, F = riccati_residual(Abar, Bbar, P, Q, R)
    lam = ms_rate(system, dist, F)
    if lam >= 1:                                          # the gain of the last P must itself be stabilizing
        status = "solver_failed"
    return SynthesisResult("ms_lqr", F, lam, status, len(Abar),
                           info={"cost_trace": float(np.trace(P)), "iterations": iterations,
                                 "riccati_residual": float(np.abs(residual).max() / np.abs(P).max())})


def _certified_cost(Abar, Bbar, F, Q, R) -> np.ndarray | None:
    """The cost matrix of F to relative residual START_RTOL, or None unless it certifies F mean-square
    stabilizing (P > 0 and Q + F^T R F + E > 0 for the computed residual E, `analysis.lyapunov`)."""
    return certified_stein(Abar + Bbar @ F, Q + F.T @ R @ F, rtol=START_RTOL, max_iter=START_GMRES)


def _ms_lqr_matrix_free(system, dist, Abar, Bbar, Q, R, tol, max_iter) -> SynthesisResult:
    """`ms_lqr` beyond DENSE_SOLVE_MAX_N: inexact Newton on matrix-free Lyapunov solves (module docstring).

    Start: the gain of value iteration P <- Q + E[A^T P A] - E[A^T P B] (R + E[B^T P B])^-1 E[B^T P A]
    from P = Q (the k-step optimal cost) after 1, 2, 4, ... START_VALUE_STEPS steps, the first whose
    cost matrix certifies it stabilizing (usually within a few steps, and closer to the optimum than
    F = 0); else the rate-optimal gain of `policy_iteration`, as for small n."""
    P, steps, checked = Q, 0, None
    while steps < START_VALUE_STEPS:
        residual, F = riccati_residual(Abar, Bbar, P, Q, R)
        if steps in (1, 2, 4, 8, 16, 32, 64) and (checked := _certified_cost(Abar, Bbar, F, Q, R)) is not None:
            break
        P, steps = P + residual, steps + 1
        if not np.all(np.isfinite(P)) or np.abs(P).max() > 1e12 * np.abs(Q).max():    # diverging: no such gain
            break
    P = checked
    if P is None:
        start = policy_iteration(system, dist)
        if start.lam >= 1:
            return _no_stabilizing_start(system, dist, start)
        P = _certified_cost(Abar, Bbar, start.F, Q, R)
        if P is None:
            return SynthesisResult("ms_lqr", None, float("nan"), "solver_failed", len(Abar))
    status, iterations, dominant, built = "solver_failed", 0, None, None
    while iterations < max_iter:
        iterations += 1
        residual, F = riccati_residual(Abar, Bbar, P, Q, R)
        Acl = Abar + Bbar @ F
        if built is None or np.abs(F - built).max() > 1e-3 * np.abs(built).max():
            dominant, built = DominantTerm(Acl.transpose(0, 2, 1)), F     # else the last loop's preconditioner
            if not dominant.rho0 < 1:
                break
        rtol = min(1e-2, np.abs(residual).max() / np.abs(P).max())
        D, _ = stein_solve(Acl, residual, rtol=rtol, dominant=dominant)   # Newton's step (module docstring)
        P_new = P + D
        try:
            np.linalg.cholesky(P_new)
        except np.linalg.LinAlgError:                     # Newton iterates stay stabilizing in exact arithmetic
            break
        P = P_new
        if np.abs(D).max() <= tol * np.abs(P).max():
            status = "optimal"
            break
    return _result(system, dist, Abar, Bbar, P, Q, R, status, iterations)


def _check(options: dict, system: AffineRandomSystem) -> None:
    """One-line ValueError for bad ms_lqr options (before any work)."""
    weight("state_weight", options.get("state_weight", 1.0), system.n)
    weight("input_weight", options.get("input_weight", 1.0), system.m)
    for name in ("tol", "max_iter"):
        v = options.get(name, 1)
        if not (isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) and v > 0):
            raise ValueError(f"{name}: {v!r} is not allowed, expected a number > 0")


ms_lqr.check_options = _check
