"""Mean-square LQ: the optimal state feedback for E sum_k (x_k^T Q x_k + u_k^T R u_k) of the random system.

With xi_k i.i.d. and independent of x_k, the optimal cost x0^T P x0 solves the generalized Riccati equation
    P = Q + E[A^T P A] - E[A^T P B] (R + E[B^T P B])^-1 E[B^T P A],   F = -(R + E[B^T P B])^-1 E[B^T P A],
where E[M^T P N] = sum_r Mbar_r^T P Nbar_r over the moment factors (Abar_r, Bbar_r) of Gbar (the same
moments as Theorem 2). With the covariance 0 it is the discrete algebraic Riccati equation of the mean model.

Start: value iteration P <- Q + E[A^T P A] - ... from P = Q (the k-step optimal cost, increasing to the
solution when a stabilizing gain exists) until its relative residual is below VALUE_SWITCH, a few steps.
Up to SYM_SOLVE_MAX_N it is then solved by Newton's method (Hewer's iteration): from a mean-square
stabilizing F, P = the exact cost matrix of F (generalized Lyapunov equation, `analysis.cost_matrix`),
then F from P; every iterate is mean-square stabilizing and P decreases monotonically to the stabilizing
solution. The Lyapunov equations are solved densely on the n (n + 1) / 2 entries of the symmetric P
(`_sym_lyapunov`), and Newton stops as soon as the residual at P is below tol (no confirming step).

Beyond SYM_SOLVE_MAX_N, the fixed-point iteration P <- P + (I - T0)^-1 Res(P), Res the Riccati residual
and T0 the dominant Kronecker term of X -> E[Acl^T X Acl] (`analysis.DominantTerm`, O(n^3) per solve), is
accelerated by Anderson mixing of the last ANDERSON_MEMORY iterates (`_preconditioned_anderson`, with a
safeguard). Where it does not converge, inexact Newton as before (`_ms_lqr_matrix_free`): the Lyapunov
equations solved matrix-free (`analysis.stein_solve`) and inexactly: the step P_{k+1} - P_k = D solves
D - E[Acl_k^T D Acl_k] = Res(P_k) only to the relative accuracy min(1e-2, |Res(P_k)| / |P_k|), which keeps
Newton's quadratic convergence at a fraction of the GMRES steps.

The returned gain is the one of the last P; its rate is exact (`_rate`: `analysis.ms_rate`, or the same
Perron root from the dense eigenvalues on symmetric matrices for SYM_RATE_MIN_N <= n <= DENSE_MAX_N; beyond,
preconditioned by the solve's last dominant term) and info["riccati_residual"] is the residual at that P.
Measured (experiments/benchmark_scale_designs.py, README; median CPU s, one thread, stabilizable systems):
0.0020 s at n = 10, 0.012-0.016 at 20, 0.024-0.025 at 50, 0.042-0.046 at 100, 0.41-0.46 at 200, residuals
<= 1e-13; value iteration at its usual stopping rule (relative change 1e-6) takes 0.23 to 0.56 of that up to
n = 100 (1.2 times it at n = 200) with residuals 2e7 times larger. The exact rate of the result costs about
as much as the Riccati solve (0.7 of 2.0 ms at n = 10, 7-9 of 12-16 ms at n = 20, 16-18 of 42-46 ms at 100).
"""
from __future__ import annotations

import numpy as np

from ..analysis import (
    DENSE_MAX_N,
    DENSE_SOLVE_MAX_N,
    DominantTerm,
    certified_stein,
    ms_rate,
    perron,
    stein_solve,
    weight,
)
from ..systems import AffineRandomSystem
from .base import SynthesisResult
from .riccati import policy_iteration

START_RTOL = 1e-2            # relative accuracy of the first (matrix-free) cost matrix
START_GMRES = 60             # GMRES steps allowed for it (a gain that is not stabilizing does not converge)
START_VALUE_STEPS = 64       # value-iteration steps tried for a stabilizing start
VALUE_SWITCH = 0.03          # value iteration hands over below this relative Riccati residual
ANDERSON_MEMORY = 5          # past iterates mixed by the accelerated iteration
ANDERSON_MAX_ITER = 100      # its steps before inexact Newton takes over
ANDERSON_STALL = 10          # or as many steps without halving the residual
ANDERSON_REBUILD = 4         # its steps between rebuilds of the preconditioner while the gain moves
SYM_SOLVE_MAX_N = DENSE_SOLVE_MAX_N   # Newton with dense solves on the n (n + 1) / 2 entries of P up to this n
SYM_RATE_MIN_N = 5           # from this n the rate of the result on symmetric matrices (`_rate`)


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
    Start: value iteration from P = Q until its relative Riccati residual is below VALUE_SWITCH
    (`_value_start`). n <= SYM_SOLVE_MAX_N: Newton's method from its gain when its cost matrix
    certifies it stabilizing (positive definite, `_sym_lyapunov`), else as before from the open loop
    when it is mean-square stable or from the rate-optimal gain of `policy_iteration`. Beyond: the
    preconditioned fixed-point iteration with Anderson acceleration (`_preconditioned_anderson`), else
    inexact Newton (`_ms_lqr_matrix_free`). If policy iteration's certified lower bound on the optimal
    rate is >= 1 no finite cost exists (status `not_ms_stabilizable`, F None; `not_converged` where no
    stabilizing start was found but none is proven impossible). Status `optimal` when the Riccati
    residual or Newton's step falls below tol max|P| (`solver_failed` otherwise, or when the returned
    gain's exact rate is >= 1); max_iter bounds Newton's steps (the accelerated iteration's:
    ANDERSON_MAX_ITER, ANDERSON_STALL).
    info: cost_trace = trace(P) (the cost averaged over x0 ~ N(0, I)), riccati_residual
    (max |residual| / max |P| at the returned P, the certificate of the cost), iterations (of Newton
    or of the accelerated iteration).
    """
    n, m = system.n, system.m
    Q, R = weight("state_weight", state_weight, n), weight("input_weight", input_weight, m)
    Abar, Bbar = system.moment_factors(dist)
    start = _value_start(Abar, Bbar, Q, R)
    if n > SYM_SOLVE_MAX_N:
        if start is not None:
            found = _preconditioned_anderson(Abar, Bbar, Q, R, *start, tol)
            if found is not None:
                return _result(system, dist, Abar, Bbar, *found)
        return _ms_lqr_matrix_free(system, dist, Abar, Bbar, Q, R, tol, max_iter)
    P = None if start is None else _sym_lyapunov(Abar + Bbar @ start[2], Q + start[2].T @ R @ start[2])
    if P is None:                                         # no certified value-iteration start: as before
        F = np.zeros((m, n))
        if ms_rate(system, dist, F) >= 1:
            policy = policy_iteration(system, dist)
            if policy.lam >= 1:
                return _no_stabilizing_start(system, dist, policy)
            F = policy.F
        P = _sym_lyapunov(Abar + Bbar @ F, Q + F.T @ R @ F)  # the exact cost matrix of F (analysis.cost_matrix)
    status, iterations = "solver_failed", 0
    while P is not None and iterations < max_iter:
        residual, F = riccati_residual(Abar, Bbar, P, Q, R)
        if np.abs(residual).max() <= tol * np.abs(P).max():     # the certificate itself: no further step
            status = "optimal"
            break
        iterations += 1
        P_new = _sym_lyapunov(Abar + Bbar @ F, Q + F.T @ R @ F)
        if P_new is None:                                 # Newton iterates stay stabilizing in exact arithmetic
            break
        change = np.abs(P_new - P).max()
        P = P_new
        if change <= tol * np.abs(P).max():
            status = "optimal"
            break
    if P is None:
        return SynthesisResult("ms_lqr", None, float("nan"), "solver_failed", len(Abar))
    return _result(system, dist, Abar, Bbar, P, Q, R, status, iterations)


def _value_start(Abar, Bbar, Q, R):
    """(P, residual, F) of value iteration P <- P + residual(P) from P = Q at the first P whose relative
    Riccati residual is below VALUE_SWITCH, within START_VALUE_STEPS steps; None when it does not get
    there (diverging: no stabilizing gain, or slow)."""
    P, top = Q, np.abs(Q).max()
    for _ in range(START_VALUE_STEPS):
        residual, F = riccati_residual(Abar, Bbar, P, Q, R)
        size = np.abs(P).max()
        if not (np.isfinite(size) and size <= 1e12 * top):
            return None
        if np.abs(residual).max() <= VALUE_SWITCH * size:
            return P, residual, F
        P = P + residual
    return None


def _sym_lyapunov(Acl: np.ndarray, Qbar: np.ndarray) -> np.ndarray | None:
    """`analysis.lyapunov` for n <= DENSE_SOLVE_MAX_N on the n (n + 1) / 2 entries of the symmetric P
    (the solution is symmetric: the upper triangle's equations determine it, an eighth of the LU's work).
    None when the solution is not positive definite (not mean-square stable)."""
    n = Acl.shape[1]
    upper, lower = _sym_index(n)[:2]
    try:
        p = np.linalg.solve(np.eye(len(upper)) - _sym_operator(Acl), Qbar[upper, lower])
        P = np.empty((n, n))
        P[upper, lower] = p
        P[lower, upper] = p
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        return None
    return P


def _sym_operator(Acl: np.ndarray) -> np.ndarray:
    """T*(P) = sum_r Acl_r^T P Acl_r on symmetric P as an (N, N) matrix, N = n (n + 1) / 2: the upper
    triangle of T*(P) from the upper triangle of P (an invariant subspace of T*: its eigenvalues are
    eigenvalues of T*, the Perron root among them, its eigenvector being symmetric)."""
    n = Acl.shape[1]
    upper, lower, full_cols, swapped, off = _sym_index(n)
    # T*(P)[i, k] = sum_jl Acl_r[j, i] P[j, l] Acl_r[l, k]: rows (i, k) of the upper triangle
    At = Acl.transpose(2, 1, 0)                           # At[i, j, r] = Acl_r[j, i]
    L = np.matmul(At[upper], At[lower].transpose(0, 2, 1)).reshape(len(upper), n * n)
    Ls = L[:, full_cols]
    Ls[:, off] += L[:, swapped[off]]                      # P[j, l] = P[l, j]: both columns on one unknown
    return Ls


def _sym_index(n: int):
    """(i, k) of the upper triangle (i <= k), the row-major columns i n + k and k n + i, and i != k."""
    upper, lower = np.triu_indices(n)
    return upper, lower, upper * n + lower, lower * n + upper, upper != lower


def _preconditioned_anderson(Abar, Bbar, Q, R, P, residual, F, tol):
    """(P, Q, R, status `optimal`, iterations, T0) of the fixed-point iteration P <- P + (I - T0)^-1 residual(P)
    with Anderson acceleration (memory ANDERSON_MEMORY), or None when it does not converge.

    T0 is the dominant Kronecker term (`analysis.DominantTerm`) of T*(X) = E[Acl^T X Acl] at the start's
    gain, so the step is Newton's with the Jacobian I - T* replaced by I - T0, rebuilt every
    ANDERSON_REBUILD steps while the gain still moves. Safeguard: an accelerated iterate that is not
    positive definite or whose residual is more than twice the last one is replaced by the plain step
    (the history restarts). Converged: max |residual| <= tol max |P|; any positive semidefinite solution
    of the Riccati equation (Q > 0) is the stabilizing one, and the gain's exact rate is checked after."""
    n = Abar.shape[1]
    dominant, built, since = None, None, 0
    size = np.abs(residual).max()
    best, improved = size, 0
    Xs, Gs = [], []
    for iterations in range(1, ANDERSON_MAX_ITER + 1):
        if dominant is None or (since >= ANDERSON_REBUILD and np.abs(F - built).max() > 1e-3 * np.abs(built).max()):
            dominant, built, since = DominantTerm((Abar + Bbar @ F).transpose(0, 2, 1)), F, 0
            if not dominant.rho0 < 1:
                return None
            Xs, Gs = [], []
        since += 1
        G = P + dominant.solve(residual, 1.0)
        G = (G + G.T) / 2
        Xs, Gs = Xs[-ANDERSON_MEMORY:] + [P.ravel()], Gs[-ANDERSON_MEMORY:] + [G.ravel()]
        P_new = G
        if len(Xs) > 1:                                   # min || sum_i a_i (G_i - X_i) || over sum_i a_i = 1
            Gm = np.array(Gs)
            Fm = Gm - np.array(Xs)
            dF, dG = np.diff(Fm, axis=0), np.diff(Gm, axis=0)
            gamma = _least_squares(dF, Fm[-1])
            P_new = (Gm[-1] - gamma @ dG).reshape(n, n)
            P_new = (P_new + P_new.T) / 2
        residual_new, F_new = _checked_residual(Abar, Bbar, P_new, Q, R)
        if residual_new is None or np.abs(residual_new).max() > 2 * size:
            P_new, Xs, Gs = G, [], []                     # the plain (preconditioned) step
            residual_new, F_new = _checked_residual(Abar, Bbar, P_new, Q, R)
            if residual_new is None:
                return None
        P, residual, F = P_new, residual_new, F_new
        size = np.abs(residual).max()
        if size <= tol * np.abs(P).max():
            return P, Q, R, "optimal", iterations, dominant
        if size < best / 2:
            best, improved = size, iterations
        elif iterations - improved >= ANDERSON_STALL:      # rounding (tol too small) or no convergence
            return None
    return None


def _least_squares(D: np.ndarray, f: np.ndarray) -> np.ndarray:
    """gamma (k,) minimising ||f - D^T gamma|| for D (k, N), k <= ANDERSON_MEMORY << N: from the k x k Gram
    matrix (k N work, an SVD of the N x k matrix costs 5-10 times more at N = n^2). The Gram matrix squares
    the singular values, so directions of singular value below 1e-7 of the largest are dropped as rounding
    (Anderson's columns can be nearly dependent; a poor mixing is caught by the safeguard)."""
    s, U = np.linalg.eigh(D @ D.T)
    keep = s > 1e-14 * s[-1]
    return U[:, keep] @ ((U[:, keep].T @ (D @ f)) / s[keep])


def _checked_residual(Abar, Bbar, P, Q, R):
    """`riccati_residual` at P, or (None, None) unless P is finite and positive definite."""
    try:
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        return None, None
    return riccati_residual(Abar, Bbar, P, Q, R)


def _no_stabilizing_start(system, dist, start) -> SynthesisResult:
    """No finite cost only where the optimal rate is proven >= 1 (policy iteration's lower end is proven)."""
    return SynthesisResult("ms_lqr", None, float("nan"), "not_ms_stabilizable" if start.lam_lower >= 1 else
                           "not_converged", system.Gbar(dist).shape[0],
                           info={"rate_optimal": start.lam, "rate_optimal_lower": start.lam_lower})


def _result(system, dist, Abar, Bbar, P, Q, R, status, iterations, dominant=None) -> SynthesisResult:
    """The gain of the last P, its exact rate (`solver_failed` if >= 1) and the Riccati residual at P.
    dominant: the solve's last preconditioner (`DominantTerm` of the adjoint factors at a nearby gain),
    reused by the rate's eigen-solver."""
    residual, F = riccati_residual(Abar, Bbar, P, Q, R)
    lam = _rate(Abar + Bbar @ F, dominant)
    if lam >= 1:                                          # the gain of the last P must itself be stabilizing
        status = "solver_failed"
    return SynthesisResult("ms_lqr", F, lam, status, len(Abar),
                           info={"cost_trace": float(np.trace(P)), "iterations": iterations,
                                 "riccati_residual": float(np.abs(residual).max() / np.abs(P).max())})


def _rate(Acl: np.ndarray, dominant: DominantTerm | None = None) -> float:
    """The exact mean-square rate of the loop Acl = Abar + Bbar F: `analysis.ms_rate` (on the moment factors
    at hand, bit for bit), except for SYM_RATE_MIN_N <= n <= DENSE_MAX_N the largest eigenvalue modulus of
    T* on symmetric matrices (`_sym_operator`): the same Perron root from the dense eigenvalues of an N x N
    matrix, N = n (n + 1) / 2, instead of n^2 x n^2 (a sixth of the work at n = 10). Beyond DENSE_MAX_N
    given `dominant` (the Riccati solve's preconditioner, built on the adjoint factors at a nearby gain),
    `perron` of T* with it: the same Perron root, the eigendecomposition of the preconditioner not redone."""
    n = Acl.shape[1]
    if not np.all(np.isfinite(Acl)):
        return float("inf")
    if n > DENSE_MAX_N:
        if dominant is not None:
            return float(np.sqrt(perron(Acl, adjoint=True, dominant=dominant)[0]))
        return float(np.sqrt(perron(Acl)[0]))
    if n < SYM_RATE_MIN_N:
        L = np.einsum("rij,rkl->ikjl", Acl, Acl).reshape(n * n, n * n)
        return float(np.sqrt(np.abs(np.linalg.eigvals(L)).max()))
    return float(np.sqrt(np.abs(np.linalg.eigvals(_sym_operator(Acl))).max()))


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
    return _result(system, dist, Abar, Bbar, P, Q, R, status, iterations, dominant)


def _check(options: dict, system: AffineRandomSystem) -> None:
    """One-line ValueError for bad ms_lqr options (before any work)."""
    weight("state_weight", options.get("state_weight", 1.0), system.n)
    weight("input_weight", options.get("input_weight", 1.0), system.m)
    for name in ("tol", "max_iter"):
        v = options.get(name, 1)
        if not (isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) and v > 0):
            raise ValueError(f"{name}: {v!r} is not allowed, expected a number > 0")


ms_lqr.check_options = _check
