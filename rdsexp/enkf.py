"""Ensemble Kalman filter on the augmented state psi = [x; xi] (paper Sec. III-A, III-B).

Simulation model (eqs. f-A-B, h-C-D): psi_k = [A(xi) x + B(xi) u; xi] + w_k, z_k = C(xi) x + D(xi) u + v_k,
w ~ N(0, Q), v ~ N(0, R). Ensembles are arrays (..., M, n+p) with any leading batch axes
(paths); every step is a few batched matrix products, never a loop over members. Noise comes in
as standard normal draws so that the caller owns the random streams (one per path).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .systems import AffineRandomSystem, _finite_array, affine_apply

# an innovation covariance V with condition number above this is treated as singular
V_COND_LIMIT = 1e12


def check_covariance(name: str, value, dim: int) -> np.ndarray:
    """A symmetric positive semidefinite (dim, dim) matrix (a scalar means value * I), or ValueError."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        arr = arr * np.eye(dim)
    elif arr.ndim == 1 and arr.size == dim:
        arr = np.diag(arr)
    arr = _finite_array(name, arr, 2)
    if arr.shape != (dim, dim):
        raise ValueError(f"{name}: shape {arr.shape}, expected ({dim}, {dim}) (or a scalar, or a diagonal)")
    if not np.allclose(arr, arr.T, rtol=1e-9, atol=1e-12):
        raise ValueError(f"{name}: must be symmetric")
    if np.linalg.eigvalsh(arr).min() < -1e-10 * max(1.0, np.abs(arr).max()):
        raise ValueError(f"{name}: must be positive semidefinite")
    return (arr + arr.T) / 2


def sqrtm_psd(S: np.ndarray) -> np.ndarray:
    """Symmetric square root of a PSD matrix (valid when S is singular)."""
    w, V = np.linalg.eigh(S)
    return (V * np.sqrt(np.clip(w, 0.0, None))) @ V.T


@dataclass(frozen=True, eq=False)
class EnKF:
    """The paper's EnKF with perturbed outputs for `model`, process noise Q (n+p, n+p), output noise R (ny, ny).

    Q and R may be given as scalars (times I) or diagonals.
    """

    model: AffineRandomSystem
    Q: np.ndarray
    R: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "Q", check_covariance("Q", self.Q, self.dim))
        object.__setattr__(self, "R", check_covariance("R", self.R, self.model.ny))
        object.__setattr__(self, "_Q_sqrt", sqrtm_psd(self.Q))
        object.__setattr__(self, "_R_sqrt", sqrtm_psd(self.R))

    @property
    def dim(self) -> int:
        """Dimension n + p of psi."""
        return self.model.n + self.model.p

    def split(self, psi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(x, xi) parts of psi (..., n+p), eqs. (psi-x-xi), (psi-x-xi-i)."""
        return psi[..., :self.model.n], psi[..., self.model.n:]

    def predict(self, psi: np.ndarray, u: np.ndarray, e_w: np.ndarray) -> np.ndarray:
        """State prediction, eq. (state-pred2): psi_{k|k-1}^(i) = f(psi_{k-1|k-1}^(i), u_{k-1}) + w_k^(i).

        psi: (..., M, n+p) filtered ensemble, u: (..., m) input applied at k-1 (same for all members),
        e_w: (..., M, n+p) standard normal draws (w = Q^(1/2) e_w). Returns (..., M, n+p).
        """
        x, xi = self.split(psi)
        out = e_w @ self._Q_sqrt
        out[..., :self.model.n] += affine_apply(self.model.A, xi, x) + affine_apply(self.model.B, xi, u[..., None, :])
        out[..., self.model.n:] += xi
        return out

    def update(self, psi: np.ndarray, u: np.ndarray, y: np.ndarray, e_v: np.ndarray,
               psi_mean: np.ndarray | None = None) -> "Analysis":
        """Output prediction and filtering, eqs. (output-pred2), (filtering)-(kalman-v).

        psi: (..., M, n+p) predicted ensemble psi_{k|k-1}, u: (..., m) input at k, y: (..., ny)
        measured output, e_v: (..., M, ny) standard normal draws (v = R^(1/2) e_v), psi_mean: the
        ensemble mean (eq. state-pred1) if already computed. Where the innovation covariance V_k is
        singular, `ok` is False and the ensemble is returned unfiltered.
        """
        x, xi = self.split(psi)
        z = (affine_apply(self.model.C, xi, x) + affine_apply(self.model.D, xi, u[..., None, :])
             + e_v @ self._R_sqrt)                                                  # eq. (output-pred2)
        M = psi.shape[-2]
        psi_mean = ensemble_mean(psi) if psi_mean is None else psi_mean            # eq. (state-pred1)
        z_mean = ensemble_mean(z)                                                   # eq. (output-pred1)
        dpsi = psi - psi_mean[..., None, :]
        dz = z - z_mean[..., None, :]
        dpsi_T = dpsi.swapaxes(-1, -2)
        U = dpsi_T @ dz / (M - 1)                                                   # eq. (kalman-u)
        V = dz.swapaxes(-1, -2) @ dz / (M - 1)                                      # eq. (kalman-v)
        ok = np.linalg.cond(V) < V_COND_LIMIT
        V = np.where(ok[..., None, None], V, np.eye(V.shape[-1]))
        KT = np.linalg.solve(V, U.swapaxes(-1, -2)) * ok[..., None, None]           # K^T = V^-1 U^T, eq. (kalman-gain)
        filtered = psi + (y[..., None, :] - z) @ KT                                 # eq. (filtering)
        # moments of both ensembles from the same products: psi_{k|k} - mean = dpsi - dz K^T, so its
        # sample covariance is Cov(psi_{k|k-1}) - U K^T (exactly, for the sample moments)
        cov_pred = dpsi_T @ dpsi / (M - 1)
        cov_filt = cov_pred - U @ KT
        return Analysis(psi=filtered, ok=ok, pred_mean=psi_mean,
                        pred_std=np.sqrt(np.clip(np.diagonal(cov_pred, axis1=-2, axis2=-1), 0, None)),
                        filt_mean=psi_mean + ((y - z_mean)[..., None, :] @ KT)[..., 0, :],
                        filt_std=np.sqrt(np.clip(np.diagonal(cov_filt, axis1=-2, axis2=-1), 0, None)))


class Analysis(NamedTuple):
    """Result of one EnKF update: filtered ensemble (..., M, n+p), ok (...,), and the ensemble
    mean and spread (std over members, ddof 1) before (pred_*) and after (filt_*) filtering, (..., n+p)."""

    psi: np.ndarray
    ok: np.ndarray
    pred_mean: np.ndarray
    pred_std: np.ndarray
    filt_mean: np.ndarray
    filt_std: np.ndarray


def ensemble_mean(a: np.ndarray) -> np.ndarray:
    """Mean over the member axis: (..., M, d) -> (..., d), as one batched matrix-vector product."""
    M = a.shape[-2]
    return (np.full((1, M), 1.0 / M) @ a)[..., 0, :]
