"""Ensemble Kalman filter on the augmented state psi = [x; xi] (paper Sec. III-A, III-B).

Simulation model (eqs. f-A-B, h-C-D): psi_k = [A(xi) x + B(xi) u; xi] + w_k, z_k = C(xi) x + D(xi) u + v_k,
w ~ N(0, Q), v ~ N(0, R). Ensembles are arrays (..., M, n+p) with any leading batch axes
(paths); every step is a few batched matrix products, never a loop over members. Noise comes in
as standard normal draws so that the caller owns the random streams (one per path).

Ensembles returned by `predict` and `update` are stored component-major: they are (..., M, n+p)
views of (n+p, ..., M) arrays, so each component of all paths and members is one contiguous block
and the elementwise work runs as single long loops (with the n+p = 9 numbers of a member
contiguous it is several times slower). Inputs may be stored in any layout.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .systems import AffineRandomSystem, _finite_array, affine_apply

# an innovation covariance V with condition number above this is singular to working precision
# (1 / (45 eps)); a merely large spread of the outputs stays well below it
V_COND_LIMIT = 1e14


def check_covariance(name: str, value, dim: int) -> np.ndarray:
    """A symmetric positive semidefinite (dim, dim) matrix from a scalar (times I), a diagonal of
    dim entries or a matrix; a one-line ValueError otherwise."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        arr = arr * np.eye(dim)
    elif arr.ndim == 1 and arr.size == dim:
        arr = np.diag(arr)
    if arr.shape != (dim, dim):
        raise ValueError(f"{name}: shape {arr.shape} is not allowed, expected a scalar, {dim} diagonal entries "
                         f"or ({dim}, {dim})")
    arr = _finite_array(name, arr, 2)
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
        e_w: (..., M, n+p) standard normal draws (w = Q^(1/2) e_w). Returns (..., M, n+p), component-major.
        """
        return self._predict(psi, u, e_w, out=component_major(e_w.shape))

    def update(self, psi: np.ndarray, u: np.ndarray, y: np.ndarray, e_v: np.ndarray,
               psi_mean: np.ndarray | None = None) -> Analysis:
        """Output prediction and filtering, eqs. (output-pred2), (filtering)-(kalman-v).

        psi: (..., M, n+p) predicted ensemble psi_{k|k-1}, u: (..., m) input at k, y: (..., ny)
        measured output, e_v: (..., M, ny) standard normal draws (v = R^(1/2) e_v), psi_mean: the
        ensemble mean (eq. state-pred1) if already computed. Where the innovation covariance V_k is
        singular, `ok` is False and the ensemble is returned unfiltered (K_k = 0). The filtered
        ensemble is component-major.
        """
        work = component_major(psi.shape[:-1] + (self.dim + self.model.ny + 1,))
        return self._update(psi, u, y, e_v, psi_mean, out=component_major(psi.shape), work=work)

    # `simulate` calls the two steps below with buffers it reuses at every step: allocating the
    # large arrays afresh costs a page fault per 4 kB once the allocator has returned them to the OS.

    def _predict(self, psi: np.ndarray, u: np.ndarray, e_w: np.ndarray, out: np.ndarray) -> np.ndarray:
        """`predict` into `out` (..., M, n+p), component-major, which must not overlap psi; returns out."""
        n = self.model.n
        x, xi = self.split(psi)
        np.matmul(self._Q_sqrt.T, e_w.swapaxes(-1, -2), out=out.swapaxes(-1, -2))    # w = Q^(1/2) e_w
        psi_next = components(out)
        psi_next[:n] += components(affine_apply(self.model.A, xi, x))                 # eq. (f-A-B)
        psi_next[:n] += components(affine_apply(self.model.B, xi, u[..., None, :]))
        psi_next[n:] += components(xi)
        return out

    def _update(self, psi: np.ndarray, u: np.ndarray, y: np.ndarray, e_v: np.ndarray,
                psi_mean: np.ndarray | None, out: np.ndarray, work: np.ndarray) -> Analysis:
        """`update` with the filtered ensemble written into `out` (..., M, n+p) and `work`
        (..., M, n+p+ny+1) as scratch, both component-major; neither may overlap psi."""
        d, ny, M = self.dim, self.model.ny, psi.shape[-2]
        x, xi = self.split(psi)
        # rows [psi - psi_mean; z - z_mean; 1] of all members, as X (d+ny+1, ..., M) for the
        # elementwise work and as Xb (..., d+ny+1, M), a matrix per path, for the products: the
        # Gram matrix of Xb holds U and V, and one more product with it filters every member
        X = components(work)
        Xb = np.moveaxis(X, 0, -2)
        dpsi, dz = X[:d], X[d:-1]
        np.matmul(self._R_sqrt.T, e_v.swapaxes(-1, -2), out=Xb[..., d:-1, :])        # v = R^(1/2) e_v
        dz += components(affine_apply(self.model.C, xi, x))                            # eq. (output-pred2)
        if self.model.D.any():
            dz += components(affine_apply(self.model.D, xi, u[..., None, :]))
        psi_mean = ensemble_mean(psi) if psi_mean is None else psi_mean              # eq. (state-pred1)
        z_mean = ensemble_mean(np.moveaxis(dz, 0, -1))                                # eq. (output-pred1)
        dz -= components(z_mean)[..., None]
        np.subtract(components(psi), components(psi_mean)[..., None], out=dpsi)
        X[-1] = 1.0
        S = Xb[..., :-1, :] @ Xb[..., :-1, :].swapaxes(-1, -2) / (M - 1)   # sample covariance of [psi; z]
        cov_pred, U, V = S[..., :d, :d], S[..., :d, d:], S[..., d:, d:]    # eqs. (kalman-u), (kalman-v)
        lam = np.linalg.eigvalsh(V)                                        # V is symmetric PSD:
        ok = lam[..., 0] * V_COND_LIMIT > lam[..., -1]                     # cond(V) = lam_max / lam_min
        V = np.where(ok[..., None, None], V, np.eye(ny))
        K = np.linalg.solve(V, U.swapaxes(-1, -2)).swapaxes(-1, -2) * ok[..., None, None]   # eq. (kalman-gain)
        correction = (K @ (y - z_mean)[..., None])[..., 0]                 # of the mean
        # eq. (filtering) for all members: psi + K (y - z) = psi + [-K, K (y - z_mean)] [dz; 1]
        np.matmul(np.concatenate([-K, correction[..., None]], axis=-1), Xb[..., d:, :], out=out.swapaxes(-1, -2))
        filtered = components(out)
        filtered += components(psi)
        # moments of psi_{k|k} from the same products: psi_{k|k} - mean = dpsi - K dz, so its sample
        # covariance is Cov(psi_{k|k-1}) - U K^T (exactly, for the sample moments)
        var_pred = np.diagonal(cov_pred, axis1=-2, axis2=-1)
        return Analysis(psi=out, ok=ok, pred_mean=psi_mean, pred_std=np.sqrt(np.clip(var_pred, 0, None)),
                        filt_mean=psi_mean + correction,
                        filt_std=np.sqrt(np.clip(var_pred - np.sum(U * K, axis=-1), 0, None)))


class Analysis(NamedTuple):
    """Result of one EnKF update: filtered ensemble (..., M, n+p), ok (...,), and the ensemble
    mean and spread (std over members, ddof 1) before (pred_*) and after (filt_*) filtering, (..., n+p)."""

    psi: np.ndarray
    ok: np.ndarray
    pred_mean: np.ndarray
    pred_std: np.ndarray
    filt_mean: np.ndarray
    filt_std: np.ndarray


def components(a: np.ndarray) -> np.ndarray:
    """View (c, ...) of an array (..., c): elementwise work in this orientation runs in the memory
    order of component-major arrays (numpy picks a slower one when an operand is broadcast)."""
    return np.moveaxis(a, -1, 0)


def component_major(shape: tuple[int, ...]) -> np.ndarray:
    """An uninitialised array of `shape` (..., M, d), stored component-major: a view of a (d, ..., M) array."""
    return np.moveaxis(np.empty(shape[-1:] + shape[:-1]), 0, -1)


def ensemble_mean(a: np.ndarray) -> np.ndarray:
    """Mean over the member axis: (..., M, d) -> (..., d), as one batched matrix-vector product."""
    M = a.shape[-2]
    return (np.full((1, M), 1.0 / M) @ a)[..., 0, :]
