"""Riccati-type designs: SDP-free optimal mean-square rate (policy iteration) and LQR on the mean model."""
from __future__ import annotations

import numpy as np
import scipy.linalg

from ..analysis import ms_rate
from .base import SynthesisResult, designed, mean_model


def policy_iteration(system, dist, *, max_iter: int = 200, tol: float = 1e-13, F0=None):
    """Optimal mean-square rate without an SDP.

    Alternate (i) P = Perron eigenvector of the positive map P -> E[Acl^T P Acl] for the current F,
    (ii) F = argmin_F E[(A + B F)^T P (A + B F)] = -E[B^T P B]^{-1} E[B^T P A].
    Since E[Acl_new^T P Acl_new] <= E[Acl^T P Acl] = lam^2 P with P > 0, the rate never increases.
    """
    Abar, Bbar = system.moment_factors(dist)
    n, m = system.n, system.m
    F = np.zeros((m, n)) if F0 is None else system.check_gain(F0)
    lam, history = np.inf, []
    for it in range(max_iter):
        Acl = Abar + Bbar @ F
        # row-major vec(A^T P A) = (A^T (x) A^T) vec(P)
        L = np.einsum("rji,rlk->ikjl", Acl, Acl).reshape(n * n, n * n)
        w, V = np.linalg.eig(L)
        i = np.argmax(w.real)
        new_lam = float(np.sqrt(max(w[i].real, 0.0)))
        P = V[:, i].real.reshape(n, n)
        P = (P + P.T) / 2
        P *= np.sign(np.trace(P)) / np.abs(P).max()
        history.append(new_lam)
        if lam - new_lam <= tol * max(new_lam, 1e-300) and it > 0:
            lam = min(lam, new_lam)
            break
        lam = new_lam
        BPB = np.einsum("rji,jk,rkl->il", Bbar, P, Bbar)
        BPA = np.einsum("rji,jk,rkl->il", Bbar, P, Abar)
        F = -np.linalg.lstsq(BPB, BPA, rcond=None)[0]          # minimum-norm minimiser if singular
    lam = ms_rate(system, dist, F)
    status = "optimal" if lam < 1 else "not_ms_stabilizable"
    return SynthesisResult("policy_iteration", F, lam, status, Abar.shape[0],
                           info={"iterations": len(history)})


def lqr_mean(system, dist, *, state_weight: float = 1.0, input_weight: float = 1.0):
    """Discrete LQR on the mean model with weights state_weight I_n, input_weight I_m (F = -K)."""
    A, B = mean_model(system, dist)
    Rw = input_weight * np.eye(system.m)
    P = scipy.linalg.solve_discrete_are(A, B, state_weight * np.eye(system.n), Rw)
    F = -np.linalg.solve(Rw + B.T @ P @ B, B.T @ P @ A)
    return designed("lqr_mean", system, dist, F)
