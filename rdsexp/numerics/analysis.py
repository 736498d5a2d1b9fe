"""Exact mean-square analysis of the ideal closed loop and empirical rates from Monte Carlo.

The ideal closed loop is x_{k+1} = Acl(xi_k) x_k + B(xi_k) d_k with Acl = A + B F (eq. closed-loop)
and full state feedback; its second moments depend on the distribution of xi only through Gbar.
"""
from __future__ import annotations

import warnings

import numpy as np
import scipy.linalg
import scipy.linalg.lapack
import scipy.sparse.linalg
from scipy.special import ndtri

from .systems import AffineRandomSystem, MomentModel


def second_moment_operator(system: AffineRandomSystem, dist: MomentModel | None, F) -> np.ndarray:
    """E[Acl (x) Acl], shape (n^2, n^2): row-major vec(X_{k+1}) = this @ vec(X_k) for d = 0.

    Dense: for small n and for checks; rdsexp's analysis applies it as `MomentMap` beyond DENSE_MAX_N."""
    Abar, Bbar = system.moment_factors(dist)
    Acl = Abar + Bbar @ system.check_gain(F)                 # (nbar, n, n)
    n = system.n
    return np.einsum("rij,rkl->ikjl", Acl, Acl).reshape(n * n, n * n)


# ------------------------------------------------------ the second-moment map without n^2 x n^2 matrices
# E[x_{k+1} x_{k+1}^T] = T(E[x_k x_k^T]) for d = 0 with T(X) = sum_r Acl_r X Acl_r^T over the closed
# loop's moment factors Acl_r = Abar_r + Bbar_r F, and the generalized Lyapunov operator is its adjoint
# T*(P) = sum_r Acl_r^T P Acl_r. Both map the PSD cone into itself. Above the sizes below nothing forms
# the n^2 x n^2 matrix E[Acl (x) Acl]: T is applied in O(nbar n^3), its Perron root found by a
# preconditioned Davidson iteration and P - T*(P) = Qbar solved by preconditioned GMRES, both
# preconditioned by the dominant Kronecker term (`DominantTerm`).
#
# The switches from dense, measured (experiments/benchmark_scale_designs.py --switch: one thread, CPU
# ms, median over 10 random systems of experiments/benchmark_synthesis.py's kind, dense / matrix-free):
#   eigenvalues:  n = 8: 0.78 / 3.4,  n = 10: 2.5 / 2.8,  n = 12: 5.8 / 4.0,  n = 14: 11.7 / 5.5
#   solve (rate 0.9):  n = 14: 0.40 / 1.8,  n = 16: 0.88 / 1.6,  n = 18: 2.6 / 1.7,  n = 20: 4.8 / 2.0
DENSE_MAX_N = 10          # `perron`, `ms_rate`: dense eigenvalues of E[Acl (x) Acl] up to this n
DENSE_SOLVE_MAX_N = 16    # `lyapunov`, `ms_lqr`: dense solve of (I - E[Acl^T (x) Acl^T]) vec P = vec Qbar
PERRON_TOL = 1e-13        # the Perron pair's relative residual ||T(X) - rho X|| / (rho ||X||) (Frobenius)
EIGENBASIS_COND = 1e8     # above this condition of M0's eigenbasis, `DominantTerm` solves in its Schur basis


class MomentMap:
    """X (n, n) -> T(X) = sum_r M_r X M_r^T with M = Acl (nbar, n, n), or M_r = Acl_r^T (adjoint=True).

    T(X) = E[Acl X Acl^T] and T*(P) = E[Acl^T P Acl]. One application is two BLAS products over the
    stacked factors: 2 nbar n^3 multiply-adds and O(nbar n^2) memory (E[Acl (x) Acl] has n^4 entries)."""

    def __init__(self, Acl: np.ndarray, *, adjoint: bool = False):
        M = np.asarray(Acl, dtype=float)
        self.M = M.transpose(0, 2, 1) if adjoint else M                        # T(X) = sum_r M_r X M_r^T
        self.nbar, self.n = self.M.shape[0], self.M.shape[1]
        self.rows = np.ascontiguousarray(self.M.reshape(-1, self.n))                     # [M_1; ...; M_nbar]
        self.cols = np.ascontiguousarray(self.M.transpose(0, 2, 1).reshape(-1, self.n))  # [M_1^T; ...]

    def __call__(self, X: np.ndarray) -> np.ndarray:
        nbar, n = self.nbar, self.n
        Z = self.rows @ X                                                  # blocks M_r X, (nbar n, n)
        if nbar > 1:       # [M_1 X, ..., M_nbar X] (n, nbar n) @ [M_1^T; ...] = sum_r M_r X M_r^T in one product
            Z = Z.reshape(nbar, n, n).transpose(1, 0, 2).reshape(n, nbar * n)
        return Z @ self.cols


class DominantTerm:
    """The dominant Kronecker term T0(X) = M0 X M0^T of T(X) = sum_r M_r X M_r^T, M (nbar, n, n), and
    C -> (sigma - T0)^-1 C in O(n^3) (`solve`).

    Rotating the factors by an orthogonal matrix leaves T unchanged, so with u the top left singular
    vector of the stacked factors (nbar, n^2), M0 = sum_r u_r M_r and the other singular directions
    give T = T0 + T1 with T1 a sum of Kronecker squares: T1 maps the PSD cone into itself, hence
    rho0 = rho(T0) = rho(M0)^2 <= rho(T), and (sigma - T0)^-1 T1 is a regular splitting of sigma - T.
    In M0's eigenbasis (real: [Re v, Im v] for a complex pair) T0 is elementwise, (sigma - T0)^-1
    divides by sigma - w_i w_j: four n x n products. Where that basis is ill-conditioned (a Jordan
    block, cond > EIGENBASIS_COND) a Schur-based Stein solve (scipy) instead."""

    def __init__(self, M: np.ndarray):
        nbar, n, _ = M.shape
        flat = M.reshape(nbar, n * n)
        u = np.linalg.eigh(flat @ flat.T)[1][:, -1]                # top left singular vector of the stack
        self.M0 = np.tensordot(u, M, axes=1)                                  # (n, n)
        w, V = np.linalg.eig(self.M0)
        self.rho0 = float(np.abs(w).max() ** 2) if n else 0.0
        # LAPACK returns a conjugate pair adjacent, positive imaginary part first: put the pairs first
        first = np.flatnonzero(w.imag > 0)
        order = np.concatenate([np.stack([first, first + 1], axis=1).ravel(), np.flatnonzero(w.imag == 0)])
        w, V = w[order], V[:, order]
        self.pairs = 2 * len(first)
        Vr = V.real.copy()
        Vr[:, 1:self.pairs:2] = V[:, 0:self.pairs:2].imag      # V[:, k] = Vr[:, k] + i Vr[:, k+1] for a pair
        try:
            W = np.linalg.inv(Vr)
            cond = np.linalg.norm(Vr, 1) * np.linalg.norm(W, 1)
        except np.linalg.LinAlgError:
            W, cond = None, np.inf
        self.eigenbasis = bool(cond <= EIGENBASIS_COND)
        self.Vr, self.W, self.ww = Vr, W, np.outer(w, w)

    def similar(self, d: np.ndarray, scale: float) -> DominantTerm:
        """The dominant term of the factors D^-1 M_r D / scale, D = diag(d) (`_balanced`), without a new
        eigendecomposition: M0 -> D^-1 M0 D / scale, its eigenvectors D^-1 V, eigenvalues w / scale."""
        out = object.__new__(DominantTerm)
        out.__dict__.update(self.__dict__)
        out.M0 = self.M0 * d[None, :] / d[:, None] / scale
        out.rho0, out.ww = self.rho0 / scale ** 2, self.ww / scale ** 2
        out.Vr = self.Vr / d[:, None]
        out.W = None if self.W is None else self.W * d[None, :]
        return out

    def solve(self, C: np.ndarray, sigma: float) -> np.ndarray:
        """X (n, n) with sigma X - M0 X M0^T = C, sigma > rho0 (C symmetric: X symmetric)."""
        if not self.eigenbasis:
            return scipy.linalg.solve_discrete_lyapunov(self.M0 / np.sqrt(sigma), C / sigma)
        Z = self._pairs(self.W @ C @ self.W.T, _TO_EIG) / (sigma - self.ww)
        return self.Vr @ self._pairs(Z, _FROM_EIG).real @ self.Vr.T

    def _pairs(self, Y: np.ndarray, R: np.ndarray) -> np.ndarray:
        """R Y_k R^T on every pair block (rows, then columns): between the real basis [Re v, Im v]
        and the complex eigenvectors [v, conj v] (`_TO_EIG`, `_FROM_EIG`)."""
        Y = Y.astype(complex)
        q, n = self.pairs, len(Y)
        Y[:q] = (R @ Y[:q].reshape(-1, 2, n)).reshape(q, n)
        Y[:, :q] = (Y[:, :q].reshape(n, -1, 2) @ R.T).reshape(n, q)
        return Y


_TO_EIG = np.array([[0.5, -0.5j], [0.5, 0.5j]])       # [v, conj v] = [Re v, Im v] [[1, 1], [i, -i]]
_FROM_EIG = np.array([[1, 1], [1j, -1j]])


def _balanced(Acl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(D^-1 Acl D, d): a diagonal similarity of every factor (the spectrum of T is unchanged, X = D Xd D)
    that evens out rows and columns, so that gains with large entries do not cost accuracy."""
    n = Acl.shape[1]
    if not np.all(np.isfinite(Acl)):
        return Acl, np.ones(n)
    _, (d, _) = scipy.linalg.matrix_balance(np.abs(Acl).sum(axis=0), permute=False, separate=True)
    return Acl * d[None, None, :] / d[None, :, None], d


def perron(Acl: np.ndarray, *, adjoint: bool = False, v0: np.ndarray | None = None,
           tol: float = PERRON_TOL, dominant: DominantTerm | None = None) -> tuple[float, np.ndarray]:
    """Spectral radius rho and a Perron eigenvector V (n, n) of T(X) = sum_r Acl_r X Acl_r^T.

    Acl: (nbar, n, n). adjoint=True uses T*(P) = sum_r Acl_r^T P Acl_r (same spectrum). T maps the
    PSD cone into itself, so rho is an eigenvalue with a PSD eigenvector (Krein-Rutman); V is
    returned symmetrised with a nonnegative trace (PSD up to rounding).

    n <= DENSE_MAX_N: the eigenvalues of the n^2 x n^2 matrix. Beyond, matrix-free on the balanced
    closed loop, started from v0 (default I) and preconditioned by `dominant` (a caller's `DominantTerm`
    of these factors, adjoint ones if adjoint, or of nearby ones; default built here):
    `_perron_davidson`, else ARPACK's Arnoldi iteration for the eigenvalue of largest real part (every
    eigenvalue has modulus <= rho, so that is rho, also where complex eigenvalues share its modulus). Accuracy:
    the returned pair has ||T(V) - rho V||_F <= tol rho ||V||_F (tol = PERRON_TOL = 1e-13 by default), so rho is
    exact to tol times its condition number (tests/numerics/test_matrix_free.py: the dense eigenvalues to 1e-10
    on random and degenerate systems; beyond, `collatz_wielandt` brackets).
    """
    Acl = np.asarray(Acl, dtype=float)
    n = Acl.shape[1]
    if adjoint:
        Acl = Acl.transpose(0, 2, 1)
    if n > DENSE_MAX_N and np.all(np.isfinite(Acl)):
        return _perron_matrix_free(Acl, v0, tol, dominant)
    L = np.einsum("rij,rkl->ikjl", Acl, Acl).reshape(n * n, n * n)
    w, V = np.linalg.eig(L)
    i = np.argmax(np.abs(w))
    rho = float(np.abs(w[i]))
    # among eigenvalues of modulus rho pick the real one (the Perron root)
    close = np.flatnonzero(np.abs(w) >= rho * (1 - 1e-9))
    i = close[np.argmin(np.abs(w[close].imag))]
    v = V[:, i].real
    if w[i].imag == 0 and rho > 0:
        # LAPACK's balanced eigenvectors can have residuals far above rounding on non-normal maps;
        # two steps of inverse iteration with the computed eigenvalue as shift restore a
        # working-precision eigenvector
        try:
            with warnings.catch_warnings(), np.errstate(all="ignore"):  # an exactly singular shift gives a
                warnings.simplefilter("ignore", scipy.linalg.LinAlgWarning)  # non-finite v, caught below
                lu = scipy.linalg.lu_factor(L - w[i].real * (1 + 1e-13) * np.eye(n * n), check_finite=False)
                for _ in range(2):
                    v = scipy.linalg.lu_solve(lu, v, check_finite=False)
                    v /= np.abs(v).max()
        except (ValueError, np.linalg.LinAlgError):
            v = V[:, i].real
        if not np.all(np.isfinite(v)):
            v = V[:, i].real
    return rho, _normalised(v.reshape(n, n))


def _normalised(X: np.ndarray) -> np.ndarray:
    """X symmetrised, scaled to max |entry| 1 with a nonnegative trace."""
    X = (X + X.T) / 2
    top = np.abs(X).max()
    if top == 0 or not np.isfinite(top):
        return X
    return X / (top * (np.sign(np.trace(X)) or 1.0))


def _perron_matrix_free(Acl: np.ndarray, v0: np.ndarray | None, tol: float,
                        dominant: DominantTerm | None = None) -> tuple[float, np.ndarray]:
    """`perron` beyond DENSE_MAX_N on the balanced loop scaled to ||T|| ~ 1: Davidson, else ARPACK
    (Arnoldi for the eigenvalue of largest real part), else the power iteration (rho = 0)."""
    n = Acl.shape[1]
    if len(Acl) == 1:            # T(X) = A X A^T: rho = rho(A)^2, V = Re(v v^H) for A v = lambda v (exact)
        w, U = np.linalg.eig(Acl[0])
        i = int(np.argmax(np.abs(w)))
        return float(np.abs(w[i]) ** 2), _normalised(np.outer(U[:, i], U[:, i].conj()).real)
    Acl, d = _balanced(Acl)
    unit = float(np.sqrt(np.einsum("rij,rij->", Acl, Acl) / n))      # ~ sqrt(||T||)
    if unit == 0:
        return 0.0, np.eye(n)
    T = MomentMap(Acl / unit)
    start = np.eye(n) if v0 is None else np.asarray(v0, dtype=float) / np.outer(d, d)
    if not np.all(np.isfinite(start)) or not np.any(start):
        start = np.eye(n)
    dom = DominantTerm(T.M) if dominant is None else dominant.similar(d, unit)
    rho, X, done = _perron_davidson(T, dom, (start + start.T) / 2, tol=tol)
    if not done:                                 # each attempt starts from the last one's best Ritz vector
        rho, X, done = _perron_davidson(T, dom, X, anchored=False, tol=tol)
    if not done:
        op = scipy.sparse.linalg.LinearOperator((n * n, n * n), dtype=float,
                                                matvec=lambda x: T(x.reshape(n, n)).ravel())
        try:
            w, V = scipy.sparse.linalg.eigs(op, k=1, which="LR", tol=tol, v0=X.ravel(),
                                            ncv=min(n * n - 2, 24), maxiter=100 * n)
            rho, X = float(w[0].real), V[:, 0].real.reshape(n, n)
        except scipy.sparse.linalg.ArpackError:
            rho, X = _perron_power(T, start)     # T nilpotent (rho = 0): the Ritz values do not settle
    return max(rho, 0.0) * unit ** 2, _normalised(X * np.outer(d, d))       # back from the balanced basis


def _perron_davidson(T: MomentMap, dom: DominantTerm, X: np.ndarray, *, anchored: bool = True,
                     tol: float = PERRON_TOL, basis: int = 20, max_iter: int = 60) -> tuple[float, np.ndarray, bool]:
    """(rho, X (n, n), converged) for T by a Davidson iteration preconditioned by its dominant term `dom`.

    With T = T0 + T1 (`DominantTerm`), T X = rho X iff X = K_rho X for K_sigma = (sigma - T0)^-1 T1, a
    positive map whose Perron root is 1 at sigma = rho and whose other eigenvalues are small where T0
    dominates (random systems: |mu_2| < 0.5). anchored: the basis grows by the power sequence
    z <- K_sigma z (one T, one T0 and one (sigma - T0)^-1 application per step; sigma the current
    estimate), Rayleigh-Ritz of T on the basis accelerates it, and the Ritz pair followed is the one
    closest to z: on a non-normal T the rightmost Ritz value can be a spurious one beyond rho. Not
    anchored (where rho ~ rho0 and K's second eigenvalue is near 1): Davidson's correction
    (sigma - T0)^-1 (T x - theta x) of the rightmost Ritz pair, sigma = max(theta, rho0 (1 + 1e-6)),
    there nearly a shift-and-invert step. Thick restart at `basis` vectors. Not converged: the residual
    is not below tol rho in max_iter steps (then the Ritz pair of smallest residual seen)."""
    n = T.n
    N = n * n
    size = basis + 2
    V, TV, H = np.empty((size, N)), np.empty((size, N)), np.empty((size, size))
    k = 0

    def add(v: np.ndarray) -> np.ndarray | None:
        """Orthonormalise v (N,) against the basis, append it with its T product: v's coefficients (k,)."""
        nonlocal k
        c = V[:k] @ v
        t = v - c @ V[:k]
        norm = np.linalg.norm(t)
        if norm < 0.7 * np.linalg.norm(v):                   # cancellation: once more (DGKS)
            c2 = V[:k] @ t
            t -= c2 @ V[:k]
            c += c2
            norm = np.linalg.norm(t)
        if not (np.isfinite(norm) and norm > 1e-14 * np.linalg.norm(v)):      # in the span already
            return None
        V[k] = t / norm
        TV[k] = T(V[k].reshape(n, n)).ravel()
        H[:k, k] = V[:k] @ TV[k]
        H[k, :k + 1] = TV[:k + 1] @ V[k]
        k += 1
        return np.append(c, norm)

    cz = add(X.ravel() / np.linalg.norm(X))
    best = (np.inf, 0.0, X)
    for _ in range(max_iter):
        w, S = _eig(H[:k, :k])
        j = int(np.argmax(np.abs(cz @ S))) if anchored else int(np.argmax(w.real))   # the pair followed
        s = S[:, j].real if np.any(S[:, j].real) else S[:, j].imag
        s /= np.linalg.norm(s)
        theta = float(w[j].real)
        x, Tx = s @ V[:k], s @ TV[:k]
        R = Tx - theta * x
        rel = np.linalg.norm(R) / max(abs(theta), 1e-300)
        if rel < best[0]:
            best = (rel, theta, x.reshape(n, n))
        if rel <= tol:
            return theta, x.reshape(n, n), True
        sigma = max(theta, dom.rho0 * (1 + 1e-6))
        if anchored:                                                           # K_sigma z
            v = dom.solve((cz @ TV[:k]).reshape(n, n) - dom.M0 @ (cz @ V[:k]).reshape(n, n) @ dom.M0.T, sigma)
        else:                                                                  # Davidson's correction
            v = dom.solve(R.reshape(n, n), sigma)
        if k > basis:              # thick restart on x and the two rightmost Ritz vectors: no new products
            Sk, Rk = np.linalg.qr(np.column_stack([s, S[:, np.argsort(-w.real)[:2]].real]))
            Sk = Sk[:, np.abs(np.diag(Rk)) > 1e-8]
            V[:Sk.shape[1]], TV[:Sk.shape[1]] = Sk.T @ V[:k], Sk.T @ TV[:k]
            H[:Sk.shape[1], :Sk.shape[1]] = Sk.T @ H[:k, :k] @ Sk
            k = Sk.shape[1]
        v = (v + v.T).ravel()
        norm = np.linalg.norm(v)
        cz = add(v / norm) if np.isfinite(norm) and norm > 0 else None
        if cz is None:
            break
    return best[1], best[2], False


def _eig(H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (k,) and unit eigenvectors (k, k) of a small real H (LAPACK dgeev, without numpy's overhead)."""
    wr, wi, _, vr, info = scipy.linalg.lapack.dgeev(H, compute_vl=0)
    if info != 0:
        raise np.linalg.LinAlgError("dgeev did not converge")
    S = vr.astype(complex)
    for j in np.flatnonzero(wi > 0):                    # a conjugate pair: vr[:, j] +- i vr[:, j + 1]
        S[:, j] = vr[:, j] + 1j * vr[:, j + 1]
        S[:, j + 1] = S[:, j].conj()
    return wr + 1j * wi, S / np.linalg.norm(S, axis=0)


def _perron_power(T: MomentMap, X: np.ndarray, steps: int = 5000) -> tuple[float, np.ndarray]:
    """Power iteration X <- T(X) / max |T(X)| from the PSD part of X (I if none): (rho, X)."""
    w, U = np.linalg.eigh((X + X.T) / 2)
    X = (U * np.clip(w, 0, None)) @ U.T if w.max() > 0 else np.eye(len(X))
    X = X / np.abs(X).max()
    rho = 0.0
    for _ in range(steps):
        Y = T(X)
        size = np.abs(Y).max()
        if size == 0:
            return 0.0, X
        change = np.abs(Y / size - X).max()
        rho, X = float(size), Y / size
        if change <= 1e-14:
            break
    return rho, X


def collatz_wielandt(Acl: np.ndarray, X: np.ndarray, *, adjoint: bool = False) -> tuple[float, float]:
    """A proven bracket (lower, upper) of rho(T) from any positive definite X (n, n) (Collatz-Wielandt).

    T(X) >= a X gives T^k(X) >= a^k X, so rho >= a; T(X) <= b X with X > 0 gives rho <= b. a, b are the
    extreme eigenvalues of X^-1/2 T(X) X^-1/2 (Cholesky), so the bracket closes as X approaches the
    Perron vector when that is positive definite. (0, inf) when X is not positive definite."""
    T = MomentMap(Acl, adjoint=adjoint)
    try:
        C = np.linalg.cholesky((X + X.T) / 2)
    except np.linalg.LinAlgError:
        return 0.0, float("inf")
    Y = scipy.linalg.solve_triangular(C, scipy.linalg.solve_triangular(C, T(X), lower=True).T, lower=True)
    w = np.linalg.eigvalsh((Y + Y.T) / 2)
    return float(max(w[0], 0.0)), float(w[-1])


def ms_rate(system: AffineRandomSystem, dist: MomentModel | None, F) -> float:
    """Exact mean-square decay rate sqrt(rho(E[Acl (x) Acl])) of the ideal closed loop.

    This is the smallest lambda of eq. (exp-def) for the gain F (>= 1: not mean-square stable).
    `dist` None uses the system's own xi_dist. Computed by `perron`: dense eigenvalues up to
    DENSE_MAX_N, matrix-free beyond (rho to PERRON_TOL relative residual).
    """
    Abar, Bbar = system.moment_factors(dist)
    Acl = Abar + Bbar @ system.check_gain(F)
    if not np.all(np.isfinite(Acl)):
        return float("inf")
    if system.n <= DENSE_MAX_N:            # the dense eigenvalues, bit for bit as before
        n = system.n
        L = np.einsum("rij,rkl->ikjl", Acl, Acl).reshape(n * n, n * n)
        return float(np.sqrt(np.abs(np.linalg.eigvals(L)).max()))
    return float(np.sqrt(perron(Acl)[0]))


def second_moments(system: AffineRandomSystem, dist: MomentModel | None, F, x0, d) -> tuple[np.ndarray, np.ndarray]:
    """Exact E[x_k] (K+1, n) and E[x_k x_k^T] (K+1, n, n) of the ideal closed loop with input d.

    x_{k+1} = (A(xi_k) + B(xi_k) F) x_k + B(xi_k) d_k, x_0 deterministic, d: (K+1, m) deterministic
    (the last row is unused). Since xi_k is independent of x_k,
        X_{k+1} = sum_r T_r [[X_k, m_k], [m_k^T, 1]] T_r^T,  T_r = [Abar_r + Bbar_r F, Bbar_r d_k].
    """
    dist = system.check_distribution(dist)
    F = system.check_gain(F)
    x0 = np.asarray(x0, dtype=float)
    d = np.atleast_2d(np.asarray(d, dtype=float))
    if x0.shape != (system.n,):
        raise ValueError(f"x0: shape {x0.shape}, expected ({system.n},)")
    if d.ndim != 2 or d.shape[1] != system.m:
        raise ValueError(f"d: shape {d.shape}, expected (K+1, m = {system.m})")
    Abar, Bbar = system.moment_factors(dist)
    Acl_bar = Abar + Bbar @ F
    A_mu, B_mu, _, _ = system.at(dist.mean)
    Acl_mu = A_mu + B_mu @ F
    K = d.shape[0] - 1
    mean = np.empty((K + 1, system.n))
    second = np.empty((K + 1, system.n, system.n))
    mean[0], second[0] = x0, np.outer(x0, x0)
    for k in range(K):                                          # a recursion in time, not over samples
        T = np.concatenate([Acl_bar, (Bbar @ d[k])[:, :, None]], axis=2)       # (nbar, n, n+1)
        Z = np.block([[second[k], mean[k][:, None]], [mean[k][None, :], np.ones((1, 1))]])
        TZ = (T @ Z).transpose(1, 0, 2).reshape(system.n, -1)         # [T_1 Z, ..., T_nbar Z]
        second[k + 1] = TZ @ T.transpose(1, 0, 2).reshape(system.n, -1).T   # sum_r T_r Z T_r^T: one product
        mean[k + 1] = Acl_mu @ mean[k] + B_mu @ d[k]
    return mean, second


def empirical_rate(q: np.ndarray, k_from: int, k_to: int, level: float = 0.95) -> tuple[float, float, float]:
    """Rate (sqrt(E||q_to||^2) / sqrt(E||q_from||^2))^(1/(k_to-k_from)) from sample paths, with a CI.

    q: (K+1, P, n) trajectories. The expectation is the sample mean over the P paths (as in the
    paper, which used k = 60 -> 80); the interval is the one a run's verdict uses
    (`verdict.rate_interval`: bootstrap over paths, calibrated where a few paths carry the mean square).
    Returns (rate, low, high); NaN when a path is not finite at either step.
    """
    return empirical_rate_sq(np.sum(q[k_from] ** 2, axis=-1), np.sum(q[k_to] ** 2, axis=-1), k_to - k_from, level)


def empirical_rate_sq(b: np.ndarray, a: np.ndarray, span: int, level: float = 0.95) -> tuple[float, float, float]:
    """`empirical_rate` from the per-path ||q_{k_from}||^2 = b (P,) and ||q_{k_to}||^2 = a (P,);
    span = k_to - k_from (what a run split into chunks of paths keeps)."""
    from .verdict import rate_interval
    return rate_interval(b, a, span, level=level)


def rms_band(sq: np.ndarray, level: float = 0.95) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """sqrt(E||q_k||^2) over paths with its `level` interval, from sq = ||q_k||^2 (K+1, P) -> 3 x (K+1,).

    At each k the mean is over the paths where ||q_k||^2 is finite. The interval is the delta-method
    interval of log E||q_k||^2 (the standard error of the mean over paths divided by the mean),
    mapped back through exp and the square root: positive on a log axis. A band to draw, per step (the
    rate's interval, `verdict.rate_interval`, is a bootstrap). NaN where fewer than two paths are finite."""
    sq = np.where(np.isfinite(sq), sq, np.nan)
    count = np.sum(np.isfinite(sq), axis=1)
    z = ndtri(0.5 + level / 2)          # the standard normal quantile
    with np.errstate(all="ignore"):       # steps where no path is finite give NaN, silently
        mean = np.nansum(sq, axis=1) / count
        se = np.sqrt(np.nansum((sq - mean[:, None]) ** 2, axis=1) / (count - 1) / count)
        rel = np.where(count > 1, se / mean, np.nan)
        return np.sqrt(mean), np.sqrt(mean * np.exp(-z * rel)), np.sqrt(mean * np.exp(z * rel))


def rms(q: np.ndarray) -> np.ndarray:
    """sqrt(E||q_k||^2) over paths: q (K+1, P, n) -> (K+1,)."""
    return np.sqrt(np.mean(np.sum(q ** 2, axis=-1), axis=1))


# ------------------------------------------------------------ exact LQ cost and H2 norm of a gain
# The ideal closed loop x_{k+1} = Acl(xi_k) x_k (+ B(xi_k) w_k) with the performance output
# z_k = [Q^(1/2) x_k; R^(1/2) F x_k]. Its observability Gramian P solves the generalized Lyapunov equation
#     P = Q + F^T R F + E[Acl^T P Acl] = Q + F^T R F + sum_r Acl_r^T P Acl_r,   Acl_r = Abar_r + Bbar_r F,
# which has a (unique, PSD) solution iff the loop is mean-square stable; then x0^T P x0 = E sum_k z_k^T z_k.

def weight(name: str, value, dim: int) -> np.ndarray:
    """A weight as a (dim, dim) matrix: a scalar w > 0 means w I; a matrix must be symmetric positive definite.

    Positive definite Q and R make a finite cost equivalent to mean-square stability."""
    try:
        W = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: {value!r} is not allowed, expected a number > 0 or a ({dim}, {dim}) "
                         "matrix") from None
    if W.ndim == 0:                 # w I: positive definite iff w > 0 (no eigenvalue check needed)
        if not (np.isfinite(W) and W > 0):
            raise ValueError(f"{name}: must be symmetric positive definite (a number > 0), got {value!r}")
        return float(W) * np.eye(dim)
    if W.shape != (dim, dim) or not np.all(np.isfinite(W)):
        raise ValueError(f"{name}: shape {W.shape} is not allowed, expected a number > 0 or a finite ({dim}, {dim}) "
                         "matrix")
    if not np.allclose(W, W.T, rtol=1e-9, atol=1e-12) or np.linalg.eigvalsh((W + W.T) / 2).min() <= 0:
        raise ValueError(f"{name}: must be symmetric positive definite")
    return (W + W.T) / 2


def cost_matrix(system: AffineRandomSystem, dist: MomentModel | None, F, *, state_weight=1.0,
                input_weight=1.0) -> np.ndarray:
    """P (n, n) with x0^T P x0 = E sum_{k>=0} (x_k^T Q x_k + u_k^T R u_k), u = F x: the exact LQ cost matrix.

    Solves the generalized Lyapunov equation above (`lyapunov`). All entries inf when the loop is not
    mean-square stable (ms_rate >= 1; beyond DENSE_SOLVE_MAX_N: when `lyapunov` finds no positive
    definite solution, which certifies that): then x^T P x grows without bound for every x outside
    a proper subspace.
    """
    dist = system.check_distribution(dist)
    F = system.check_gain(F)
    Q, R = weight("state_weight", state_weight, system.n), weight("input_weight", input_weight, system.m)
    if system.n <= DENSE_SOLVE_MAX_N and ms_rate(system, dist, F) >= 1:
        return np.full((system.n, system.n), np.inf)
    Abar, Bbar = system.moment_factors(dist)
    P = lyapunov(Abar + Bbar @ F, Q + F.T @ R @ F)
    return P if P is not None else np.full((system.n, system.n), np.inf)


def lyapunov(Acl: np.ndarray, Qbar: np.ndarray) -> np.ndarray | None:
    """P (n, n) solving P = Qbar + sum_r Acl_r^T P Acl_r for Acl (nbar, n, n) and Qbar > 0, or None.

    For Qbar > 0 a positive definite solution exists iff the loop is mean-square stable (P is then a
    Lyapunov function: E[Acl^T P Acl] = P - Qbar < P), so None (no positive definite solution) means
    not mean-square stable; the Cholesky test costs less than the spectrum. n <= DENSE_SOLVE_MAX_N:
    one dense solve in vec(P). Beyond, `stein_solve` to working precision, and P is returned only
    with its certificate: P > 0 and Qbar + E > 0 for the computed residual E = Qbar + T*(P) - P.
    """
    n = Acl.shape[1]
    if n > DENSE_SOLVE_MAX_N:
        return certified_stein(Acl, Qbar)
    L = np.einsum("rji,rlk->ikjl", Acl, Acl).reshape(n * n, n * n)   # row-major vec(A^T P A) = (A^T (x) A^T) vec P
    try:
        P = np.linalg.solve(np.eye(n * n) - L, Qbar.ravel()).reshape(n, n)
        P = (P + P.T) / 2
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        return None
    return P


def certified_stein(Acl: np.ndarray, Qbar: np.ndarray, **options) -> np.ndarray | None:
    """`stein_solve`'s P (n, n) (options passed on) only with its certificate of mean-square stability:
    P > 0 and Qbar + E > 0 for the computed residual E = Qbar + T*(P) - P (then P - T*(P) > 0 exactly
    for the returned P); None otherwise, or when the solve did not converge."""
    P, E = stein_solve(Acl, Qbar, **options)
    try:
        np.linalg.cholesky(P)
        np.linalg.cholesky(Qbar + (E + E.T) / 2)
    except (np.linalg.LinAlgError, ValueError, TypeError):      # TypeError: P None
        return None
    return P


def stein_solve(Acl: np.ndarray, C: np.ndarray, *, X0: np.ndarray | None = None, rtol: float = 0.0,
                max_iter: int = 500, dominant: DominantTerm | None = None) -> tuple:
    """(X, E) (n, n) each: X solving X - sum_r Acl_r^T X Acl_r = C (symmetric) matrix-free, E = C + T*(X) - X.

    Acl (nbar, n, n). GMRES on vec(X) with the right preconditioner (1 - T0)^-1 of `DominantTerm`
    (the dominant Kronecker term of T*, a regular splitting), from X0 (default 0), until ||E||_F <=
    rtol ||E0||_F or the rounding level 8 eps (||C|| + 2 ||X|| + ||T*(X)||) (rtol 0: working precision).
    (None, None) when the dominant term alone has spectral radius >= 1: then so has T*, and the loop is
    not mean-square stable. Each iteration: one T* and one preconditioner application, O(nbar n^3).
    dominant: a `DominantTerm` of a nearby loop's T* (Acl^T stacked) to precondition with instead
    (Newton's steps in `ms_lqr`: the loop changes little); no stability check then.
    """
    n = Acl.shape[1]
    L = MomentMap(Acl, adjoint=True)
    dom = DominantTerm(L.M) if dominant is None else dominant
    if dominant is None and not dom.rho0 < 1:
        return None, None
    C = (C + C.T) / 2
    X = np.zeros((n, n)) if X0 is None else np.array(X0, dtype=float)
    residual = lambda X: C + L(X) - X                                      # noqa: E731
    E = residual(X)
    start = np.linalg.norm(E)
    for _ in range(6):                    # each pass gains up to 10 digits (GMRES's own rounding)
        floor = 8 * np.finfo(float).eps * (np.linalg.norm(C) + 2 * np.linalg.norm(X) + np.linalg.norm(E - C + X))
        target = max(rtol * start, floor)
        size = np.linalg.norm(E)
        if size <= target or max_iter <= 0:
            break
        dX, used = _gmres(lambda v: v - L(v.reshape(n, n)).ravel(),
                          lambda v: dom.solve(v.reshape(n, n), 1.0).ravel(),
                          E.ravel(), max(target, 1e-10 * size), max_iter)
        max_iter -= used
        dX = dX.reshape(n, n)
        X = X + (dX + dX.T) / 2
        E_new = residual(X)
        if np.linalg.norm(E_new) > 0.5 * size:       # stagnation: rounding (or no convergence)
            E = E_new
            break
        E = E_new
    return X, E


def _gmres(apply, precond, b: np.ndarray, tol: float, max_iter: int, restart: int = 30) -> tuple[np.ndarray, int]:
    """(x, iterations): ||b - apply(x)|| <= tol (estimated) by restarted right-preconditioned GMRES from 0.

    Vectors (N,); precond may change between steps (flexible GMRES: the preconditioned vectors are kept)."""
    N = b.size
    x, r, used = np.zeros(N), b.copy(), 0
    beta = np.linalg.norm(r)
    while beta > tol and used < max_iter:
        V, Z = np.empty((restart + 1, N)), np.empty((restart, N))
        H = np.zeros((restart + 1, restart))
        cs, sn, g = np.zeros(restart), np.zeros(restart), np.zeros(restart + 1)
        g[0], V[0] = beta, r / beta
        j = 0
        while j < restart and used < max_iter:
            Z[j] = precond(V[j])
            w = apply(Z[j])
            used += 1
            h = V[:j + 1] @ w
            w -= h @ V[:j + 1]
            h2 = V[:j + 1] @ w                              # classical Gram-Schmidt, twice
            w -= h2 @ V[:j + 1]
            H[:j + 1, j], H[j + 1, j] = h + h2, np.linalg.norm(w)
            for i in range(j):                              # the previous Givens rotations on the new column
                H[i, j], H[i + 1, j] = cs[i] * H[i, j] + sn[i] * H[i + 1, j], cs[i] * H[i + 1, j] - sn[i] * H[i, j]
            size = np.hypot(H[j, j], H[j + 1, j])
            cs[j], sn[j] = (H[j, j] / size, H[j + 1, j] / size) if size > 0 else (1.0, 0.0)
            H[j, j], last = size, H[j + 1, j]
            g[j + 1], g[j] = -sn[j] * g[j], cs[j] * g[j]
            j += 1
            if abs(g[j]) <= tol or last == 0:
                break
            V[j] = w / last
        y = scipy.linalg.solve_triangular(H[:j, :j], g[:j], check_finite=False)
        x += y @ Z[:j]
        r = b - apply(x)
        old, beta = beta, np.linalg.norm(r)
        if beta > 0.5 * old:                                # a restart that gains nothing: rounding level
            break
    return x, used


def lq_cost(system: AffineRandomSystem, dist: MomentModel | None, F, x0=None, *, state_weight=1.0,
            input_weight=1.0) -> float:
    """Exact E sum_{k>=0} (x_k^T Q x_k + u_k^T R u_k) of the ideal loop u = F x from x0 (n,).

    x0 None: the average over x0 ~ N(0, I), which is trace(P). inf when not mean-square stable.
    """
    P = cost_matrix(system, dist, F, state_weight=state_weight, input_weight=input_weight)
    if not np.all(np.isfinite(P)):
        return float("inf")
    if x0 is None:
        return float(np.trace(P))
    x0 = np.asarray(x0, dtype=float)
    if x0.shape != (system.n,):
        raise ValueError(f"x0: shape {x0.shape}, expected ({system.n},)")
    return float(x0 @ P @ x0)


def h2_norm(system: AffineRandomSystem, dist: MomentModel | None, F, *, disturbance=None, state_weight=1.0,
            input_weight=1.0) -> float:
    """Exact H2 norm from a disturbance w to z = [Q^(1/2) x; R^(1/2) F x] of the random closed loop.

    x_{k+1} = Acl(xi_k) x_k + Bw(xi_k) w_k. disturbance None: Bw = B(xi), i.e. w is added on the
    plant input as the paper's d_k; else a constant (n, q) matrix Bw. The norm is
    sqrt(sum_i sum_k E||z_k||^2) over unit impulses e_i at k = 0, which equals the stationary
    E||z_k||^2 under unit white noise w: sqrt(trace E[Bw^T P Bw]) with P of `cost_matrix`. inf when
    not mean-square stable.
    """
    P = cost_matrix(system, dist, F, state_weight=state_weight, input_weight=input_weight)
    if not np.all(np.isfinite(P)):
        return float("inf")
    if disturbance is None:
        _, Bw = system.moment_factors(dist)                      # E[B^T P B] = sum_r Bbar_r^T P Bbar_r
    else:
        Bw = np.asarray(disturbance, dtype=float)
        if Bw.ndim != 2 or Bw.shape[0] != system.n or not np.all(np.isfinite(Bw)):
            raise ValueError(f"disturbance: shape {Bw.shape}, expected a finite (n = {system.n}, q) matrix")
        Bw = Bw[None]
    return float(np.sqrt(max(np.einsum("rji,jk,rki->", Bw, P, Bw), 0.0)))


def exact_costs(system: AffineRandomSystem, dist: MomentModel | None, F, x0=None, *, disturbance=None,
                state_weight=1.0, input_weight=1.0) -> dict:
    """{"lq_cost_x0", "lq_cost", "h2"}: `lq_cost` from x0 (NaN if x0 is None) and averaged over
    x0 ~ N(0, I), and `h2_norm`, from one cost matrix P (one linear solve instead of three). inf when
    not mean-square stable."""
    P = cost_matrix(system, dist, F, state_weight=state_weight, input_weight=input_weight)
    if not np.all(np.isfinite(P)):
        return {"lq_cost_x0": float("inf") if x0 is not None else float("nan"), "lq_cost": float("inf"),
                "h2": float("inf")}
    if disturbance is None:
        _, Bw = system.moment_factors(dist)
    else:
        Bw = np.asarray(disturbance, dtype=float)
        if Bw.ndim != 2 or Bw.shape[0] != system.n or not np.all(np.isfinite(Bw)):
            raise ValueError(f"disturbance: shape {Bw.shape}, expected a finite (n = {system.n}, q) matrix")
        Bw = Bw[None]
    out = {"lq_cost_x0": float("nan"), "lq_cost": float(np.trace(P)),
           "h2": float(np.sqrt(max(np.einsum("rji,jk,rki->", Bw, P, Bw), 0.0)))}
    if x0 is not None:
        x0 = np.asarray(x0, dtype=float)
        if x0.shape != (system.n,):
            raise ValueError(f"x0: shape {x0.shape}, expected ({system.n},)")
        out["lq_cost_x0"] = float(x0 @ P @ x0)
    return out


# ----------------------------------------------------------- rate estimators beside empirical_rate
def bootstrap_rate(sq_from: np.ndarray, sq_to: np.ndarray, span: int, *, replicates: int = 2000,
                   level: float = 0.95, seed=0) -> tuple[float, float, float]:
    """Two-point mean-square rate with a studentised bootstrap interval, resampling seeds then paths.

    sq_from, sq_to: (S, P) values of ||q_{k_from}||^2 and ||q_{k_to}||^2 per seed (independent run)
    and path; span = k_to - k_from. The rate is (sum sq_to / sum sq_from)^(1/(2 span)), the paper's
    ratio of sample means pooled over all S*P paths. Each replicate draws S seeds with replacement
    and, within each, P paths with replacement (S = 1: the bootstrap over paths of one run), so the
    interval carries the spread between seeds as well as within.

    The interval is bootstrap-t on log(ratio): each replicate is studentised by its own linearised
    standard error (the ratio estimator's, over seed totals when S > 1, over paths when S = 1).
    ||q_k||^2 is heavy-tailed (a product of random matrices), and the plain percentile interval
    then misses the truth far more often than 1 - level; studentising corrects most of that skew
    (experiments/closed_loop_rate.py reports the coverage measured on the paper's ideal loop).
    NaN if any value is not finite. Returns (rate, low, high).
    """
    a, b = np.atleast_2d(np.asarray(sq_to, float)), np.atleast_2d(np.asarray(sq_from, float))
    if a.shape != b.shape or span < 1:
        raise ValueError(f"sq_from, sq_to: shapes {b.shape}, {a.shape} must match (S, P); span {span} must be >= 1")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))) or b.sum() <= 0 or a.sum() <= 0:
        return float("nan"), float("nan"), float("nan")
    S, P = a.shape
    if S * P < 2:
        return float((a.sum() / b.sum()) ** (1 / (2 * span))), float("nan"), float("nan")

    def log_ratio(a, b):
        """log(sum a / sum b) and its linearised standard error: (..., S, P) -> 2 x (...)."""
        ua, ub = (a.sum(-1), b.sum(-1)) if S > 1 else (a[..., 0, :], b[..., 0, :])   # resampling units
        ma, mb = ua.mean(-1), ub.mean(-1)
        z = ua / ma[..., None] - ub / mb[..., None]
        return np.log(ma / mb), z.std(-1, ddof=1) / np.sqrt(z.shape[-1])

    t0, se0 = log_ratio(a, b)
    rng = np.random.default_rng(seed)
    s = rng.integers(S, size=(replicates, S, 1))
    p = rng.integers(P, size=(replicates, S, P))
    with np.errstate(divide="ignore", invalid="ignore"):
        t, se = log_ratio(a[s, p], b[s, p])                                   # (replicates,) each
        T = (t - t0) / se
    T = T[np.isfinite(T)]              # a replicate of identical units has se 0 (no information)
    if T.size < replicates / 2 or se0 == 0:
        return float(np.exp(t0 / (2 * span))), float("nan"), float("nan")
    q_low, q_high = np.quantile(T, [0.5 - level / 2, 0.5 + level / 2])
    rate = lambda v: float(np.exp(v / (2 * span)))
    return rate(t0), rate(t0 - q_high * se0), rate(t0 - q_low * se0)


def largest_path_share(q: np.ndarray, k: int) -> float:
    """Share of the largest path in the sample mean of ||q_k||^2: q (K+1, P, n) -> in [1/P, 1]."""
    sq = np.sum(q[k] ** 2, axis=-1)
    return float(sq.max() / sq.sum()) if np.all(np.isfinite(sq)) and sq.sum() > 0 else float("nan")


def robust_rate(q: np.ndarray, k_from: int, k_to: int, groups: int = 10) -> float:
    """Median-of-means rate: a rate estimate that no single path can dominate.

    The P paths are split into `groups` interleaved groups (path j in group j mod groups); in each,
    log of the group's mean ||q_k||^2 is fitted by least squares against k = k_from..k_to (every
    step of the window, not only its two ends), the slope halved; the median over groups is
    returned as exp(.). One heavy path moves one group, not the median. It estimates the same
    mean-square rate as the two-point ratio when groups are large enough that each group mean is
    close to its expectation. q: (K+1, P, n). NaN if a path is not finite in the window.
    """
    P = q.shape[1]
    if not 1 <= groups <= P or not 0 <= k_from < k_to < q.shape[0]:
        raise ValueError(f"groups {groups} must be in 1..P = {P}; window {k_from}..{k_to} within 0..{q.shape[0] - 1}")
    sq = np.sum(q[k_from:k_to + 1] ** 2, axis=-1)                            # (W, P)
    if not np.all(np.isfinite(sq)):
        return float("nan")
    member = np.arange(P) % groups
    means = np.stack([sq[:, member == g].mean(axis=1) for g in range(groups)], axis=1)   # (W, groups)
    if np.any(means <= 0):
        return float("nan")
    k = np.arange(k_from, k_to + 1) - (k_from + k_to) / 2
    slopes = k @ np.log(means) / (k @ k)                                   # least-squares slope per group
    return float(np.exp(np.median(slopes) / 2))
