"""The loop through the outputs, exactly: the plant with a gain F fed by a linear observer.

The paper's closed loop feeds back an estimate of x_k, not x_k (Sec. IV): u_k = F x_{k|k} (or
F x_{k|k-1}). `analysis.ms_rate` is the rate of the ideal loop u_k = F x_k. With a linear observer on
the mean model (Abar = A(E xi), Bbar, C), gain L,

    x_{k|k} = x_{k|k-1} + L (y_k - C x_{k|k-1}),   x_{k+1|k} = Abar x_{k|k} + Bbar u_k,

the error e_k = x_k - x_{k|k-1} no longer decouples from x_k as it does for a deterministic plant
(separation): the random part (A(xi) - Abar + (B(xi) - Bbar) F) x_k enters e_{k+1}. The loop is an
affine random system on z = [x; e] (2n states) with the same xi (noise-free: its additive noises set a
floor, not the rate), so its exact mean-square rate is the Perron root of its second-moment map, like
the ideal loop's. For u_k = F x_{k|k}, with x_{k|k} = x_k - (I - L C) e_k and delta_c = [c = 0]:

    x_{k+1} = (A(xi) + B(xi) F) x_k - B(xi) F (I - L C) e_k
    e_{k+1} = (A(xi) - Abar + (B(xi) - Bbar) F) x_k + (Abar - (B(xi) - Bbar) F) (I - L C) e_k

and for u_k = F x_{k|k-1} = F (x_k - e_k): x_{k+1} = (A + B F) x_k - B F e_k,
e_{k+1} = (A - Abar + (B - Bbar) F) x_k + (Abar (I - L C) - (B - Bbar) F) e_k.

An observer-based loop with gain F can decay in mean square only if some L makes this rate < 1.
`best_observer` searches L (gradient of the Perron root, from Kalman gains of the mean model): the
rate it returns is the exact rate of the L it returns, an upper bound on the best linear observer's
(the search is local). The EnKF is not a linear observer (its gain follows its ensemble), so this is
evidence, not a verdict: on 250 random plants (experiments/random_plants.py, column y_rate) 10 of the
13 EnKF loops not found stable where it applies had no L below 1, and 2 loops with none were stable.

Applies to plants whose outputs do not depend on xi or u (C constant, D = 0): with a random C the
error equation is quadratic in xi_k. `applies` says why not.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.optimize

from .analysis import perron
from .systems import AffineRandomSystem, MomentModel

ESTIMATES = ("filtered", "predicted")


def applies(system: AffineRandomSystem) -> str | None:
    """None when the loop through y of `system` is an affine random system, else why not (a sentence)."""
    if system.C[1:].any():
        return "the outputs depend on xi (a random C): the observer's error is not affine in xi"
    if system.D.any():
        return "the outputs depend on u (D != 0)"
    return None


def _parts(system: AffineRandomSystem, dist: MomentModel, F: np.ndarray, estimate: str):
    """(Gamma0 (p+1, 2n, 2n): the loop's basis at L = 0, E (p+1, 2n, n): its derivative in L, read as
    d Gamma_c = E_c dL C placed in the e columns, C (ny, n), K ((p+1, p+1): moment factor weights))."""
    Abar, Bbar = system.at(dist.mean)[:2]                          # the mean model
    delta = (np.arange(system.p + 1) == 0)[:, None, None].astype(float)   # delta_c: the constant term only
    Acl = system.A + system.B @ F                                  # (p+1, n, n): A_c + B_c F
    dBF = (system.B - delta * Bbar) @ F                            # (B_c - delta_c Bbar) F
    xx, xe = Acl, -system.B @ F
    ex = Acl - delta * (Abar + Bbar @ F)
    ee = delta * Abar - dBF
    if estimate == "filtered":                                     # both e columns carry (I - L C):
        E = -np.concatenate([xe, ee], axis=1)                      # d[X (I - L C)] = -X dL C
    else:                                                          # only Abar (I - L C) carries L
        E = np.concatenate([np.zeros_like(xe), -delta * Abar], axis=1)
    Gamma0 = np.concatenate([np.concatenate([xx, xe], axis=2), np.concatenate([ex, ee], axis=2)], axis=1)
    # E[[1; xi][1; xi]^T] = U s U^T: the loop's moment factors are sum_c K_rc Gamma_c with K = s^1/2 U^T
    s, U = np.linalg.eigh(dist.augmented_second_moment)
    K = np.sqrt(np.maximum(s, 0.0))[:, None] * U.T
    return Gamma0, E, system.C[0], K, estimate


def _factors(parts, L: np.ndarray) -> np.ndarray:
    """The loop's moment factors (p+1, 2n, 2n) at the observer gain L (n, ny)."""
    Gamma0, E, C, K, estimate = parts
    n = C.shape[1]
    Gamma = Gamma0.copy()
    if estimate == "filtered":
        Gamma[:, :, n:] = Gamma0[:, :, n:] @ (np.eye(n) - L @ C)
    else:
        Gamma[:, n:, n:] += E[:, n:] @ (L @ C)                      # Abar (I - L C) = Abar - Abar L C
    return np.tensordot(K, Gamma, 1)


def _rate_and_gradient(parts, L: np.ndarray) -> tuple[float, np.ndarray]:
    """The loop's exact rate at L and its gradient in L (n, ny) from the Perron pair.

    d rho = <W, dT(V)> / <W, V> for T(Z) = sum_r G_r Z G_r^T with right and left Perron vectors V, W;
    d G_r = Ebar_r dL C S (S selects e), so grad rho = 2 sum_r Ebar_r^T (W G_r V) S^T C^T / <W, V>."""
    _, E, C, K, estimate = parts
    n = C.shape[1]
    G = _factors(parts, L)
    if not np.all(np.isfinite(G)):
        return float("inf"), np.zeros_like(L)
    rho, V = perron(G)
    _, W = perron(G, adjoint=True)
    rate = float(np.sqrt(max(rho, 0.0)))
    Ebar = np.tensordot(K, E, 1)                                   # (p+1, 2n, n)
    WV = float(np.sum(W * V))
    if rate == 0.0 or abs(WV) < 1e-300:
        return rate, np.zeros_like(L)
    Y = W @ G @ V                                                  # (p+1, 2n, 2n)
    grad_rho = 2.0 * np.einsum("rai,raj->ij", Ebar, Y[:, :, n:]) @ C.T / WV
    return rate, grad_rho / (2.0 * rate)


def observer_loop_rate(system: AffineRandomSystem, dist: MomentModel | None, F, L, *,
                       estimate: str = "filtered") -> float:
    """Exact mean-square rate of the plant with u_k = F x_{k|k} (or F x_{k|k-1}: estimate='predicted')
    from the linear observer of gain L (n, ny) on the mean model; F (m, n). ValueError when the loop is
    not affine in xi (`applies`)."""
    why = applies(system)
    if why:
        raise ValueError(f"system: {why}")
    if estimate not in ESTIMATES:
        raise ValueError(f"estimate: {estimate!r}, expected one of {', '.join(ESTIMATES)}")
    dist = system.check_distribution(dist)
    L = np.asarray(L, dtype=float).reshape(system.n, system.ny)
    G = _factors(_parts(system, dist, system.check_gain(F), estimate), L)
    if not np.all(np.isfinite(G)):
        return float("inf")
    return float(np.sqrt(max(perron(G)[0], 0.0)))


def kalman_gain(system: AffineRandomSystem, dist: MomentModel, process: float, output: float = 1.0) -> np.ndarray:
    """Steady-state Kalman gain L (n, ny) of the mean model for the noises process I_n and output I_ny
    (the filter form: x_{k|k} = x_{k|k-1} + L (y_k - C x_{k|k-1}))."""
    Abar, C = system.at(dist.mean)[0], system.C[0]
    S = scipy.linalg.solve_discrete_are(Abar.T, C.T, process * np.eye(system.n), output * np.eye(system.ny))
    return S @ C.T @ np.linalg.inv(C @ S @ C.T + output * np.eye(system.ny))


@dataclass(frozen=True)
class ObserverSearch:
    """`best_observer`'s result: the exact rate of the loop with the gain L found, the Kalman gain it
    started from and that gain's rate, and the search's iterations."""

    rate: float
    L: np.ndarray
    kalman_rate: float
    iterations: int


KALMAN_SCALES = (1e-2, 1.0, 1e2)     # process / output noise ratios of the starting Kalman gains


def best_observer(system: AffineRandomSystem, dist: MomentModel | None, F, *, estimate: str = "filtered",
                  max_iter: int = 200, stop_below: float | None = None) -> ObserverSearch:
    """The linear observer gain L that makes the loop through y with gain F decay fastest, searched
    locally (BFGS on the exact rate with its Perron gradient) from the best of the mean model's Kalman
    gains for KALMAN_SCALES. The returned rate is the exact rate of the returned L (recomputed).
    stop_below: the search ends at the first L whose rate is below it (a question of which side of 1
    the loop is on is answered there; iterations 0 when a Kalman gain already is)."""
    why = applies(system)
    if why:
        raise ValueError(f"system: {why}")
    dist = system.check_distribution(dist)
    F = system.check_gain(F)
    parts = _parts(system, dist, F, estimate)
    starts = []
    for scale in KALMAN_SCALES:
        try:
            L0 = kalman_gain(system, dist, scale)
        except (ValueError, np.linalg.LinAlgError):
            continue
        starts.append((_rate_and_gradient(parts, L0)[0], L0))
    if not starts:
        L0 = np.zeros((system.n, system.ny))
        starts.append((_rate_and_gradient(parts, L0)[0], L0))
    kalman_rate, L0 = min(starts, key=lambda s: s[0])
    shape = L0.shape
    if stop_below is not None and kalman_rate < stop_below:
        return ObserverSearch(rate=observer_loop_rate(system, dist, F, L0, estimate=estimate), L=L0,
                              kalman_rate=kalman_rate, iterations=0)

    def objective(v):
        rate, grad = _rate_and_gradient(parts, v.reshape(shape))
        return (rate, grad.ravel()) if np.isfinite(rate) else (1e6, np.zeros(v.size))

    def below(intermediate_result):
        if stop_below is not None and intermediate_result.fun < stop_below:
            raise StopIteration

    with np.errstate(all="ignore"):
        res = scipy.optimize.minimize(objective, L0.ravel(), jac=True, method="BFGS", callback=below,
                                      options={"maxiter": max_iter, "gtol": 1e-8})
    L = res.x.reshape(shape) if res.fun < kalman_rate else L0
    rate = observer_loop_rate(system, dist, F, L, estimate=estimate)
    return ObserverSearch(rate=rate, L=L, kalman_rate=kalman_rate, iterations=int(res.nit))
