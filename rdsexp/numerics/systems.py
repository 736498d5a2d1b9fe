"""Affine random linear systems and moment models of their parameter xi (paper Sec. II, III-B).

    x_{k+1} = A(xi_k) x_k + B(xi_k) u_k,    y_k = C(xi_k) x_k + D(xi_k) u_k     eqs. (1), (fr-sys-output)
    A(xi) = A_0 + sum_j xi_j A_j   (same for B, C, D),  xi_k i.i.d.  (Assumption 1)

Everything here is plain numpy; arrays of basis matrices carry the basis index first:
A has shape (p+1, n, n), B (p+1, n, m), C (p+1, ny, n), D (p+1, ny, m).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

RANK_RTOL = 1e-10  # eigenvalues of E[g^T g] below RANK_RTOL * largest count as zero (nbar)


def _finite_array(name: str, value, ndim: int) -> np.ndarray:
    """`value` as a float array of `ndim` dimensions with finite entries, or a one-line ValueError."""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a rectangular numeric array, got {value!r}") from None
    if arr.ndim != ndim:
        raise ValueError(f"{name}: expected {ndim} dimensions, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains NaN or inf")
    return arr


def _basis(name: str, mats, rows: int | None, cols: int | None) -> np.ndarray:
    """Stack a list of basis matrices [M_0, ..., M_p] into shape (p+1, rows, cols)."""
    if isinstance(mats, np.ndarray) and mats.ndim == 2:
        raise ValueError(f"{name}: expected a list [{name}0, {name}1, ...] of matrices, got one matrix")
    try:
        stack = [np.atleast_2d(np.asarray(M, dtype=float)) for M in mats]
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a list of numeric matrices with equal rows") from None
    if not stack:
        raise ValueError(f"{name}: needs at least the constant term {name}0")
    shapes = {M.shape for M in stack}
    if len(shapes) != 1:
        raise ValueError(f"{name}: basis matrices have different shapes {sorted(shapes)}")
    arr = _finite_array(name, stack, 3)
    want = (rows if rows is not None else arr.shape[1], cols if cols is not None else arr.shape[2])
    if arr.shape[1:] != want:
        raise ValueError(f"{name}: basis matrices have shape {arr.shape[1:]}, expected {want}")
    return arr


@dataclass(frozen=True, eq=False)
class MomentModel:
    """Distribution of xi in R^p by its mean (p,) and covariance (p, p).

    Everything rdsexp computes from it (Gbar, nbar, mean-square rates, second moments) depends on
    these two moments only (Theorem 2). `sample` draws the Gaussian with these moments, which is
    exactly the paper's plant distribution (s1, s2 i.i.d. normal).
    """

    mean: np.ndarray
    cov: np.ndarray

    def __post_init__(self):
        mean = _finite_array("mean", np.atleast_1d(self.mean), 1)
        cov = _finite_array("cov", np.atleast_2d(self.cov) if mean.size else np.zeros((0, 0)), 2)
        if cov.shape != (mean.size, mean.size):
            raise ValueError(f"cov: shape {cov.shape} does not match mean of length {mean.size}")
        if not np.allclose(cov, cov.T, rtol=1e-9, atol=1e-12):
            raise ValueError("cov: must be symmetric")
        if mean.size and np.linalg.eigvalsh(cov).min() < -1e-10 * max(1.0, np.abs(cov).max()):
            raise ValueError("cov: must be positive semidefinite")
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "cov", (cov + cov.T) / 2)

    @classmethod
    def from_samples(cls, xis) -> MomentModel:
        """Empirical moments of samples xis (N, p), rows = samples.

        The covariance is normalised by 1/N (not 1/(N-1)), so that the second moment
        cov + mean mean^T equals the paper's sample average of eq. (sample-mean) exactly.
        """
        xis = _finite_array("xis", xis, 2)
        if xis.shape[0] < 1:
            raise ValueError("xis: needs at least one sample row")
        mean = xis.mean(axis=0)
        dev = xis - mean
        return cls(mean=mean, cov=dev.T @ dev / xis.shape[0])

    @classmethod
    def deterministic(cls, mean) -> MomentModel:
        """xi fixed to `mean` (covariance discarded): the LTI special case."""
        mean = np.atleast_1d(np.asarray(mean, dtype=float))
        return cls(mean=mean, cov=np.zeros((mean.size, mean.size)))

    @property
    def p(self) -> int:
        return self.mean.size

    support = property(lambda self: (np.full(self.p, -np.inf), np.full(self.p, np.inf)))   # Gaussian: unbounded

    @property
    def second_moment(self) -> np.ndarray:
        """E[xi xi^T], shape (p, p)."""
        return self.cov + np.outer(self.mean, self.mean)

    @property
    def augmented_second_moment(self) -> np.ndarray:
        """W = E[[1; xi][1; xi]^T], shape (p+1, p+1): the weights of E[M(xi) (x) M(xi)] in the basis."""
        c = np.concatenate([[1.0], self.mean])
        W = np.outer(c, c)
        W[1:, 1:] += self.cov
        return W

    def sample(self, rng: np.random.Generator, size: tuple[int, ...]) -> np.ndarray:
        """Gaussian draws with these moments, shape size + (p,). Works for singular covariances."""
        return self.mean + rng.standard_normal(tuple(size) + (self.p,)) @ self.cov_sqrt.T

    @property
    def cov_sqrt(self) -> np.ndarray:
        """S^(1/2) with S^(1/2) S^(1/2)^T = cov (symmetric square root, valid when cov is singular)."""
        w, V = np.linalg.eigh(self.cov)
        return (V * np.sqrt(np.clip(w, 0.0, None))) @ V.T


@dataclass(frozen=True, eq=False)
class AffineRandomSystem:
    """x+ = A(xi) x + B(xi) u, y = C(xi) x + D(xi) u with A(xi) = A[0] + sum_j xi_j A[j].

    A: (p+1, n, n), B: (p+1, n, m), C: (p+1, ny, n) (default I), D: (p+1, ny, m) (default 0).
    A list shorter than p+1 is padded with zeros (a constant C may be given as [C0]).
    xi_dist: distribution of xi when it is known (a plant): a MomentModel (Gaussian) or a family of
    `distributions` (exact moments for the analysis, its own sampler for the Monte Carlo); None for
    a model to be identified.
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray | None = None
    D: np.ndarray | None = None
    xi_dist: object | None = field(default=None)

    def __post_init__(self):
        A = _basis("A", self.A, None, None)
        n = A.shape[1]
        if A.shape[2] != n:
            raise ValueError(f"A: basis matrices must be square, got {A.shape[1:]}")
        B = _basis("B", self.B, n, None)
        C = _basis("C", self.C if self.C is not None else [np.eye(n)], None, n)
        D = _basis("D", self.D if self.D is not None else [np.zeros((C.shape[1], B.shape[2]))],
                   C.shape[1], B.shape[2])
        p1 = max(len(A), len(B), len(C), len(D))
        pad = lambda M: np.concatenate([M, np.zeros((p1 - len(M),) + M.shape[1:])])
        for name, M in (("A", A), ("B", B), ("C", C), ("D", D)):
            object.__setattr__(self, name, pad(M))
        if self.xi_dist is not None and self.xi_dist.p != p1 - 1:
            raise ValueError(f"xi_dist: has dimension {self.xi_dist.p}, the system has p = {p1 - 1}")

    # sizes in the paper's notation
    n = property(lambda self: self.A.shape[1], doc="state dimension")
    m = property(lambda self: self.B.shape[2], doc="input dimension")
    ny = property(lambda self: self.C.shape[1], doc="output dimension")
    p = property(lambda self: self.A.shape[0] - 1, doc="dimension Z of xi")

    def at(self, xi) -> tuple[np.ndarray, ...]:
        """(A(xi), B(xi), C(xi), D(xi)) for xi of shape (..., p); results carry the leading axes."""
        c = _coefficients(np.asarray(xi, dtype=float), self.p)
        return tuple(np.tensordot(c, M, axes=(-1, 0)) for M in (self.A, self.B, self.C, self.D))

    def closed_loop_basis(self, F) -> np.ndarray:
        """Basis of Acl(xi) = A(xi) + B(xi) F (eq. closed-loop), shape (p+1, n, n)."""
        return self.A + self.B @ self.check_gain(F)

    def check_gain(self, F) -> np.ndarray:
        """F as an (m, n) float array, or a one-line ValueError."""
        F = _finite_array("F", np.atleast_2d(F), 2)
        if F.shape != (self.m, self.n):
            raise ValueError(f"F: shape {F.shape}, expected (m, n) = {(self.m, self.n)}")
        return F

    def check_distribution(self, dist: MomentModel | None) -> MomentModel:
        """`dist`, or the system's own xi_dist when None, as moments; checked against p.

        A distribution family (see `distributions`) stands for its exact MomentModel."""
        dist = self.xi_dist if dist is None else dist
        if dist is None:
            raise ValueError("dist: no distribution of xi given and the system has no xi_dist")
        if not isinstance(dist, MomentModel):
            dist = dist.moments
        if dist.p != self.p:
            raise ValueError(f"dist: has dimension {dist.p}, the system has p = {self.p}")
        return dist

    def Gbar(self, dist: MomentModel | None = None) -> np.ndarray:
        """Gbar (nbar, (n+m) n) with Gbar^T Gbar = E[g(xi)^T g(xi)], g = [row(A(xi)), row(B(xi))].

        eq. (equiv-rep-decom-syn). g(xi) = [1, xi^T] Gamma is affine, so E[g^T g] = Gamma^T W Gamma
        with W = E[[1; xi][1; xi]^T] = U S U^T, i.e. K^T K with K = S^(1/2) U^T Gamma ((p+1, (n+m) n)).
        Gbar = diag(sigma) V^T from the SVD of K (the eigenpairs (sigma^2, V) of E[g^T g], at the cost of
        a (p+1)-row SVD instead of an (n+m) n square eigenproblem),
        keeping the nbar rows with sigma^2 above RANK_RTOL times the largest (the numerical rank).
        Row r of Gbar is [row(Abar_r), row(Bbar_r)] (see `moment_factors`).
        """
        dist = self.check_distribution(dist)
        n, m = self.n, self.m
        Gamma = np.concatenate([self.A.reshape(self.p + 1, n * n),
                                self.B.reshape(self.p + 1, n * m)], axis=1)
        s, U = np.linalg.eigh(dist.augmented_second_moment)
        K = np.sqrt(np.maximum(s, 0.0))[:, None] * (U.T @ Gamma)        # W >= 0: clip its rounding
        _, sigma, Vt = np.linalg.svd(K, full_matrices=False)             # sigma descending
        keep = sigma ** 2 > RANK_RTOL * max(sigma[0] ** 2 if sigma.size else 0.0, 1e-300)
        return sigma[keep, None] * Vt[keep]

    def moment_factors(self, dist: MomentModel | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(Abar (nbar, n, n), Bbar (nbar, n, m)) from the rows of Gbar.

        For every P and F:  E[Acl^T P Acl] = sum_r (Abar_r + Bbar_r F)^T P (Abar_r + Bbar_r F)
        and E[Acl (x) Acl] = sum_r (Abar_r + Bbar_r F) (x) (Abar_r + Bbar_r F).
        """
        G = self.Gbar(dist)
        n, m = self.n, self.m
        return G[:, :n * n].reshape(-1, n, n), G[:, n * n:].reshape(-1, n, m)


def _coefficients(xi: np.ndarray, p: int) -> np.ndarray:
    """[1, xi] along the last axis: shape (..., p+1) for xi of shape (..., p)."""
    if xi.shape[-1:] != (p,) and not (p == 0 and xi.ndim == 0):
        raise ValueError(f"xi: last axis must have length p = {p}, got shape {xi.shape}")
    xi = xi.reshape(xi.shape[:-1] + (p,)) if xi.ndim else np.zeros((0,))
    return np.concatenate([np.ones(xi.shape[:-1] + (1,)), xi], axis=-1)


def affine_apply(basis: np.ndarray, xi: np.ndarray, v: np.ndarray) -> np.ndarray:
    """M(xi) v batched: basis[0] @ v + sum_j xi[..., j-1] basis[j] @ v.

    basis (p+1, r, s), xi (..., p), v (..., s) broadcastable against xi -> (..., r); when v is
    broadcast against xi and M(xi) = basis[0] is constant, a read-only broadcast view.
    basis[0] and only the non-zero rows of basis[1:] (in the paper's model 3 rows of A's, none of
    B's, C's or D's) are stacked into one matrix, so a single matrix product gives basis[0] v and
    every non-zero row i of basis[j] v, which is then weighted by xi_j and added to row i.
    The product is one BLAS call over all leading axes; its result is stored component-major (a view
    of an (r + rows, ...) array, like the EnKF's ensembles), so the row updates run over contiguous memory.
    """
    r, v = basis.shape[1], np.asarray(v)
    shape = np.broadcast_shapes(xi.shape[:-1], v.shape[:-1]) + (r,)
    j, i = np.nonzero(np.any(basis[1:] != 0, axis=2))             # row i of basis[j + 1] is non-zero
    G = np.concatenate([basis[0], basis[j + 1, i]])                 # (r + rows, s)
    Gv = np.moveaxis(np.tensordot(G, v, axes=(1, -1)), 0, -1)      # (..., r + rows)
    if Gv.shape[:-1] != shape[:-1]:                                 # v broadcast along axes of xi
        if not len(i):
            return np.broadcast_to(Gv, shape)                       # M(xi) = basis[0] for every xi
        Gv = np.broadcast_to(Gv, shape[:-1] + Gv.shape[-1:]).copy()
    out = Gv[..., :r]
    for row, (jk, ik) in enumerate(zip(j, i), start=r):
        Gv[..., row] *= xi[..., jk]                                 # in place: no temporary
        out[..., ik] += Gv[..., row]
    return out
