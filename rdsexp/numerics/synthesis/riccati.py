"""Riccati-type designs: SDP-free optimal mean-square rate (policy iteration) and LQR on the mean model."""
from __future__ import annotations

import numpy as np
import scipy.linalg

from ..analysis import DENSE_MAX_N, PERRON_TOL, perron
from .base import SynthesisResult, designed, mean_model

BRACKET_TOL = 1e-7           # status `optimal` when (lam - lam_lower) / lam is below this
KERNEL_TOL = 1e-12           # relative size below which an eigenvalue of S + diag(P, 0) counts as 0
STALL_TOL = 1e-13            # policy iteration stops when the rate decreases by less than this (relative)
LOWER_MARGIN = 1e-9          # relative back-off of c before its independent check (rounding of S)


def scaled_blocks(Abar: np.ndarray, Bbar: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(S / (g g^T), g): S = E[[A B]^T P [A B]] = sum_r [Abar_r Bbar_r]^T P [Abar_r Bbar_r] (..., n+m, n+m)
    and the column sizes g_i = sqrt(sum_r ||[Abar_r Bbar_r] e_i||^2) (0 -> 1) (..., n+m), for Abar
    (..., r, n, n), Bbar (..., r, n, m), P (..., n, n) (leading axes: a batch of models).

    Scaled so, an entry's rounding error is about eps ||P|| whatever the sizes of A and B (A huge and B
    small, say); that sets which eigenvalues count as exact zeros (KERNEL_TOL * ||P||). The scaling
    is a congruence: it changes neither the minimiser over F (rescaled back) nor the pencil below."""
    G = np.concatenate([Abar, Bbar], axis=-1)                     # (..., nbar, n, n+m)
    g = np.sqrt(np.sum(G ** 2, axis=(-3, -2)))
    g[g == 0] = 1.0
    G = G / g[..., None, None, :]
    lead, k = G.shape[:-3], G.shape[-1]
    S = (G.reshape(lead + (-1, k)).swapaxes(-1, -2)                 # sum_r G_r^T P G_r: one product per model
         @ (P[..., None, :, :] @ G).reshape(lead + (-1, k)))
    return (S + S.swapaxes(-1, -2)) / 2, g


def greedy_gain(Abar: np.ndarray, Bbar: np.ndarray, P: np.ndarray) -> np.ndarray:
    """argmin_F E[(A + B F)^T P (A + B F)] = -S_bb^+ S_ba (..., m, n), the minimum-norm minimiser
    (`scaled_blocks`' batch axes).

    Eigenvalues of (scaled) S_bb below KERNEL_TOL ||P|| are rounding of exact zeros (inputs that P
    does not see, e.g. an uncontrollable mode): inverting them would give gains with huge entries
    that change nothing in exact arithmetic but ruin every computation with them, so they are dropped."""
    n = Abar.shape[-1]
    S, g = scaled_blocks(Abar, Bbar, P)
    w, U = np.linalg.eigh(S[..., n:, n:])
    keep = w > KERNEL_TOL * np.abs(P).max(axis=(-2, -1))[..., None]
    Uw = np.where(keep[..., None, :], U / np.where(keep, w, 1.0)[..., None, :], 0.0)   # dropped eigenvalues: 0
    Ft = -Uw @ (U.swapaxes(-1, -2) @ S[..., n:, :n])             # the minimiser in scaled variables
    return Ft / g[..., n:, None] * g[..., None, :n]


def rate_lower_bound(Abar: np.ndarray, Bbar: np.ndarray, P: np.ndarray) -> float:
    """A lower bound on the optimal mean-square rate over all gains, from any P >= 0, P != 0 (SDP-free).

    With S = E[[A B]^T P [A B]] and R(P) = S_aa - S_ab S_bb^+ S_ba, completing the square gives
    E[(A + B F)^T P (A + B F)] >= R(P) for every F; so R(P) >= c P makes the positive map
    P -> E[Acl^T P Acl] satisfy T(P) >= c P, hence rho(T) >= c (iterate: T^k(P) >= c^k P) and
    lambda* >= sqrt(c). R(P) >= c P iff S - c diag(P, 0) >= 0 (Schur complement), a pencil of two PSD
    matrices: on the complement of their common kernel W = S + diag(P, 0) > 0 and
    S - c D >= 0 iff S >= c/(1+c) W, so c = mu/(1-mu) with mu = lambda_min(W^-1/2 S W^-1/2).
    c is backed off by LOWER_MARGIN and checked independently (lambda_min(S - c D) >= 0 on that
    complement), the back-off growing until the check holds. At policy iteration's fixed point
    R(P) = lambda*^2 P and the bound is tight, also for singular P (its kernel is in the common
    kernel). Returns 0.0 when nothing positive is certified.
    """
    n = Abar.shape[1]
    w, U = np.linalg.eigh((P + P.T) / 2)
    P = (U * np.clip(w, 0.0, None)) @ U.T                         # the PSD part: the bound holds for it
    if not np.all(np.isfinite(P)) or np.abs(P).max() == 0:
        return 0.0
    P = P / np.abs(P).max()
    S, g = scaled_blocks(Abar, Bbar, P)
    D = np.zeros_like(S)
    D[:n, :n] = P / np.outer(g[:n], g[:n])
    unit = np.trace(S) / np.trace(D)              # S - c D >= 0 iff S - (c / unit) (unit D) >= 0: c / unit ~ 1
    if not np.isfinite(unit) or unit <= 0:
        return 0.0
    D *= unit
    w, U = np.linalg.eigh(S + D)
    kept = w > KERNEL_TOL * max(1.0, w.max())     # entries are O(||P||) = O(1): rounding O(eps)
    U = U[:, kept]                                # the complement of the common kernel
    Sk, Dk, wk = U.T @ S @ U, U.T @ D @ U, w[kept]
    half = 1 / np.sqrt(wk)
    mu = float(np.linalg.eigvalsh(half[:, None] * Sk * half[None, :]).min())
    if not 0 < mu < 1:
        return 0.0
    margin = LOWER_MARGIN
    while margin < 1:
        c = mu / (1 - mu) * (1 - margin)
        if np.linalg.eigvalsh(Sk - c * Dk).min() >= 0:
            return float(np.sqrt(c * unit))
        margin *= 4
    return 0.0


def policy_steps(Abar: np.ndarray, Bbar: np.ndarray, F: np.ndarray, *, tol: float = PERRON_TOL):
    """Policy iteration's steps from F (m, n): yields (F, rho, P) with rho and P (n, n) the Perron root and
    PSD vector of T_F(P) = E[Acl^T P Acl] (to relative residual tol, `analysis.perron`), then moves to
    F = `greedy_gain` of P; ends at a gain that is not finite. Each Perron solve starts from the previous P."""
    P = None
    while np.all(np.isfinite(F)):
        rho, P = perron(Abar + Bbar @ F, adjoint=True, v0=P, tol=tol)
        yield F, rho, P
        F = greedy_gain(Abar, Bbar, P)


def policy_iteration(system, dist, *, max_iter: int = 200, tol: float = 1e-9, F0=None):
    """Optimal mean-square rate without an SDP, with a certified bracket [lam_lower, lam].

    Alternate (i) P = Perron eigenvector (PSD) of T_F(P) = E[Acl^T P Acl] for the current F,
    (ii) F = argmin_F E[(A + B F)^T P (A + B F)] = -E[B^T P B]^+ E[B^T P A] (`greedy_gain`).
    Since T_new(P) <= T_F(P) = lam^2 P, the rate does not increase (with P > 0); every P also gives
    a certified lower bound on the optimum (`rate_lower_bound`), tight at the fixed point.

    Returned: the gain with the smallest exact rate seen (F = 0 or F0 included; never None), lam
    its rate (the Perron root of its second-moment map, computed on the balanced closed loop),
    lam_lower the best certified lower bound (a finite number >= 0). The iteration stops when
    (lam - lam_lower) / lam <= tol or the rate stops decreasing. Status: `optimal` (lam < 1,
    relative bracket width below BRACKET_TOL), `not_ms_stabilizable` (lam_lower >= 1 proves it, or
    lam >= 1 with a closed bracket), `not_converged` (the bracket stays open after max_iter or once
    F stops improving: e.g. an infimum that no gain attains; lam and lam_lower say how far apart).
    info: iterations, rate_error.
    """
    Abar, Bbar = system.moment_factors(dist)
    n, m = system.n, system.m
    start = np.zeros((m, n)) if F0 is None else system.check_gain(F0)
    best_F, best_P, lam, lower, it = start, None, np.inf, 0.0, 0
    for it, (F, rho, P) in enumerate(policy_steps(Abar, Bbar, start), start=1):
        rate = float(np.sqrt(rho))
        improved = rate < lam * (1 - STALL_TOL)
        if rate < lam:
            best_F, best_P, lam = F, P, rate
        lower = max(lower, rate_lower_bound(Abar, Bbar, P))
        if lam - lower <= tol * lam or (not improved and it > 1) or it >= max_iter:
            break
    # accuracy of lam: the Perron root's condition number ||X|| ||P|| / <X, P> (right and left
    # eigenvectors) times the backward error of the computed pair; near dead beat (a nilpotent closed
    # loop, Jordan blocks) <X, P> -> 0 and no floating-point rate, upper or lower, is accurate
    Acl = Abar + Bbar @ best_F
    _, X = perron(Acl)
    P = best_P
    overlap = float(np.sum(X * P))
    kappa = np.linalg.norm(X) * np.linalg.norm(P) / overlap if overlap > 0 else np.inf
    eps = np.finfo(float).eps
    if n <= DENSE_MAX_N:         # the dense eigensolver on the n^2 x n^2 matrix: rounding ~ its entries
        error = 64 * eps * float(np.sum(np.abs(Acl).sum(axis=(1, 2)) ** 2)) * kappa    # absolute, of rho = lam^2
    else:   # the matrix-free pair: its residual, PERRON_TOL rho, and the rounding of T(X) = sum_r Acl_r X Acl_r^T,
        # |fl(T(X)) - T(X)| <= 2 (n + nbar) eps sum_r |Acl_r| |X| |Acl_r|^T (norm <= that times ||Acl_r||_F^2)
        size = float(np.sum(Acl ** 2))
        error = kappa * (PERRON_TOL * lam ** 2 + 2 * (n + len(Acl)) * eps * size)
    info = {"iterations": it, "rate_error": float(np.sqrt(lam ** 2 + error) - lam) if np.isfinite(error) else np.inf}
    lower = min(lower, lam)
    if info["rate_error"] > BRACKET_TOL / 10 * lam:
        lower = float(np.sqrt(max(lower ** 2 - error, 0.0))) if np.isfinite(error) else 0.0
    tight = lam - lower <= BRACKET_TOL * lam
    if lower >= 1 or (lam >= 1 and tight):
        status = "not_ms_stabilizable"
    elif tight:
        status = "optimal"
    else:
        status = "not_converged"
    return SynthesisResult("policy_iteration", best_F, lam, status, Abar.shape[0], lam_lower=lower, info=info)


def lqr_mean(system, dist, *, state_weight: float = 1.0, input_weight: float = 1.0):
    """Discrete LQR on the mean model with weights state_weight I_n, input_weight I_m (F = -K).

    Status `not_applicable` (F None) when the Riccati equation has no stabilizing solution, i.e. the
    mean model (A(mean), B(mean)) is not stabilizable."""
    A, B = mean_model(system, dist)
    Rw = input_weight * np.eye(system.m)
    try:
        P = scipy.linalg.solve_discrete_are(A, B, state_weight * np.eye(system.n), Rw)
    except (np.linalg.LinAlgError, ValueError) as err:
        return SynthesisResult("lqr_mean", None, float("nan"), "not_applicable", nbar=1,
                               info={"reason": f"no stabilizing Riccati solution on the mean model ({err})"})
    F = -np.linalg.solve(Rw + B.T @ P @ B, B.T @ P @ A)
    return designed("lqr_mean", system, dist, F)
