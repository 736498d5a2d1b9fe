"""ms_lqr's paths (value-iteration start, Newton on the symmetric entries of P up to n = 16, the rate on
symmetric matrices up to n = 10, the preconditioned Anderson iteration beyond n = 16, its fallback to
inexact Newton) against an independent dense computation written here.

The reference: Newton's (Hewer's) iteration on the generalized Riccati equation with full n^2 x n^2
Kronecker solves, the expectations taken with W = E[[1; xi][1; xi]^T] (not through the moment factors),
from F = 0 when the open loop is mean-square stable, else from policy iteration's gain; the rate from
the dense eigenvalues of the n^2 x n^2 second-moment matrix.
"""
import numpy as np
import pytest
import scipy.linalg

import rdsexp as rx
from rdsexp.numerics.synthesis import lq


def system_of(rng, n, m, p, *, a_scale=0.9, noise=0.3, cov_scale=0.5):
    A = [a_scale * rng.normal(size=(n, n)) / np.sqrt(n)] + [noise * rng.normal(size=(n, n)) / np.sqrt(n)
                                                            for _ in range(p)]
    B = [rng.normal(size=(n, m))] + [noise * rng.normal(size=(n, m)) for _ in range(p)]
    L = rng.normal(size=(p, p)) * cov_scale
    return rx.AffineRandomSystem(A=A, B=B), rx.MomentModel(mean=rng.normal(size=p) * 0.3, cov=L @ L.T)


# (n, m, p, options): nearly deterministic, open-loop stable, open-loop unstable, m > 1, many factors
CASES = {
    "random": dict(),
    "nearly_deterministic": dict(cov_scale=1e-6, noise=1e-4),
    "open_loop_stable": dict(a_scale=0.3, noise=0.1),
    "open_loop_unstable": dict(a_scale=1.6),
    "inputs_3": dict(m=3),
    "factors_7": dict(p=7, noise=0.15),
}


def kron_operator(system, dist, F):
    """sum_ij W_ij Acl_j^T (x) Acl_i^T (column-major vec): vec(E[Acl^T P Acl]) = this @ vec(P), as
    sum_k s_k C_k^T (x) C_k^T with W = U diag(s) U^T and C_k = sum_i U_ik Acl_i (p + 1 products)."""
    s, U = np.linalg.eigh(dist.augmented_second_moment)
    C = np.tensordot(U.T, system.A + system.B @ F, axes=1)
    return sum(s_k * np.kron(C_k.T, C_k.T) for s_k, C_k in zip(s, C))


def expect(M, N, P, W):
    return np.einsum("ij,iba,bc,jcd->ad", W, M, P, N)


def dense_reference(system, dist, Q, R):
    """(F, P, rate) of Newton's iteration with dense Kronecker solves, or None (no stabilizing start)."""
    n, m = system.n, system.m
    W = dist.augmented_second_moment
    A, B = system.A, system.B

    def cost(F):
        """The cost matrix of F, or None when it is not positive definite (F not mean-square stabilizing)."""
        L = kron_operator(system, dist, F)
        P = np.linalg.solve(np.eye(n * n) - L, (Q + F.T @ R @ F).ravel(order="F")).reshape(n, n, order="F")
        P = (P + P.T) / 2
        return P if np.linalg.eigvalsh(P).min() > 0 else None

    F = np.zeros((m, n))
    if cost(F) is None:
        F = rx.synthesize(system, dist, "policy_iteration").F
    P = None
    for _ in range(60):
        P_new = cost(F)
        if P_new is None:
            return None
        F = -np.linalg.solve(R + expect(B, B, P_new, W), expect(B, A, P_new, W))
        done = P is not None and np.abs(P_new - P).max() <= 1e-14 * np.abs(P_new).max()
        P = P_new
        if done:
            break
    rate = np.sqrt(np.abs(np.linalg.eigvals(kron_operator(system, dist, F))).max())
    return F, P, rate


def residual_of(system, dist, P, Q, R):
    W, A, B = dist.augmented_second_moment, system.A, system.B
    return Q + expect(A, A, P, W) - expect(A, B, P, W) @ np.linalg.solve(R + expect(B, B, P, W),
                                                                         expect(B, A, P, W)) - P


def check_against_reference(system, dist, res, Q, R):
    ref = dense_reference(system, dist, Q, R)
    if ref is None:
        assert res.status == "not_ms_stabilizable" and res.F is None
        return
    F, P, rate = ref
    assert res.status == "optimal", res.status
    np.testing.assert_allclose(res.F, F, rtol=0, atol=1e-10 * np.abs(F).max())
    assert res.info["cost_trace"] == pytest.approx(np.trace(P), rel=1e-10)
    assert res.lam == pytest.approx(rate, rel=1e-11)
    assert res.info["riccati_residual"] <= 1e-13
    # the certificate is true: the returned gain's exact cost matrix (Kronecker solve here) solves the equation
    n = system.n
    C = Q + res.F.T @ R @ res.F
    P_F = np.linalg.solve(np.eye(n * n) - kron_operator(system, dist, res.F), C.ravel(order="F")).reshape(
        n, n, order="F")
    assert np.abs(residual_of(system, dist, (P_F + P_F.T) / 2, Q, R)).max() <= 1e-11 * np.abs(P_F).max()


@pytest.mark.parametrize("case", CASES)
def test_ms_lqr_small_n_equals_the_dense_kronecker_newton(case):
    """n = 2 ... 12 (the symmetric Newton path and the rate on symmetric matrices from n = 5), four
    systems per case, diagonal and full weights."""
    rng = np.random.default_rng(list(CASES).index(case))
    for k in range(4):
        options = {"m": int(rng.integers(1, 3)), "p": int(rng.integers(1, 4))} | CASES[case]
        n = int(rng.integers(2, 13))
        system, dist = system_of(rng, n, **options)
        G = rng.normal(size=(n, n))
        Q = np.eye(n) + G @ G.T / n if k % 2 else np.diag(rng.uniform(0.5, 2, n))
        R = 0.5 * np.eye(system.m)
        res = rx.synthesize(system, dist, "ms_lqr", state_weight=Q, input_weight=0.5)
        check_against_reference(system, dist, res, Q, R)


@pytest.mark.parametrize("case", ["random", "nearly_deterministic", "open_loop_unstable", "factors_7"])
@pytest.mark.slow
def test_ms_lqr_preconditioned_anderson_equals_the_dense_kronecker_newton(case):
    """n = 17, 18 (beyond SYM_SOLVE_MAX_N: the accelerated fixed-point iteration): systems drawn until two
    are mean-square stabilizable, each drawn one checked (not stabilizable ones too)."""
    rng = np.random.default_rng(10 + list(CASES).index(case))
    options = {"m": 2, "p": 2} | CASES[case] | ({"a_scale": 1.2} if case == "open_loop_unstable" else {})
    found = 0
    for _ in range(6):
        n = lq.SYM_SOLVE_MAX_N + 1 + found
        system, dist = system_of(rng, n, **options)
        res = rx.synthesize(system, dist, "ms_lqr")
        check_against_reference(system, dist, res, np.eye(n), np.eye(2))
        if res.status == "optimal":
            assert 0 < res.info["iterations"] < lq.ANDERSON_MAX_ITER
            if case == "open_loop_unstable":
                assert rx.ms_rate(system, dist, np.zeros((2, n))) > 1
            found += 1
            if found == 2:
                break
    assert found == 2


def test_ms_lqr_nearly_deterministic_is_the_dare_gain():
    """Covariance and noise factors ~ 0 at n = 8 and n = 18: the DARE of the mean model (scipy)."""
    rng = np.random.default_rng(7)
    for n in (8, lq.SYM_SOLVE_MAX_N + 2):
        system, dist = system_of(rng, n, 2, 2, a_scale=1.3, noise=0.0)
        dist = rx.MomentModel.deterministic(dist.mean)
        res = rx.synthesize(system, dist, "ms_lqr")
        A, B, _, _ = system.at(dist.mean)
        X = scipy.linalg.solve_discrete_are(A, B, np.eye(n), np.eye(2))
        F = -np.linalg.solve(np.eye(2) + B.T @ X @ B, B.T @ X @ A)
        assert res.status == "optimal"
        np.testing.assert_allclose(res.F, F, rtol=0, atol=1e-9 * np.abs(F).max())
        assert res.lam == pytest.approx(np.abs(np.linalg.eigvals(A + B @ res.F)).max(), rel=1e-10)


def test_sym_lyapunov_and_rate_equal_the_full_kronecker_computation():
    """The solve on the n (n + 1) / 2 symmetric entries and the rate on symmetric matrices against the
    full n^2 Kronecker solve and eigenvalues; an unstable loop has no positive definite solution."""
    rng = np.random.default_rng(3)
    for n in (1, 2, 5, 9, 16):
        for scale in (0.5, 0.97, 1.2):
            Acl = rng.normal(size=(3, n, n))
            K = sum(np.kron(a.T, a.T) for a in Acl)                   # row-major vec(A^T P A)
            rho = np.abs(np.linalg.eigvals(K)).max()
            Acl, K = Acl * np.sqrt(scale / rho), K * scale / rho
            Qbar = np.eye(n) + (G := rng.normal(size=(n, n))) @ G.T
            P = lq._sym_lyapunov(Acl, Qbar)
            if scale >= 1:
                assert P is None
                continue
            P_full = np.linalg.solve(np.eye(n * n) - K, Qbar.ravel()).reshape(n, n)
            np.testing.assert_allclose(P, P_full, rtol=0, atol=1e-11 * np.abs(P_full).max())
            rate = np.abs(np.linalg.eigvals(lq._sym_operator(Acl))).max()
            assert rate == pytest.approx(scale, rel=1e-12)


def test_ms_lqr_falls_back_to_inexact_newton(monkeypatch):
    """An accelerated iteration that does not converge hands over to inexact Newton: same gain, and the
    status stays `optimal` only when converged."""
    rng = np.random.default_rng(5)
    n = lq.SYM_SOLVE_MAX_N + 2
    system, dist = system_of(rng, n, 2, 2)
    fast = rx.synthesize(system, dist, "ms_lqr")
    monkeypatch.setattr(lq, "ANDERSON_MAX_ITER", 2)
    slow = rx.synthesize(system, dist, "ms_lqr")
    assert fast.status == slow.status == "optimal"
    np.testing.assert_allclose(slow.F, fast.F, rtol=0, atol=1e-10 * np.abs(fast.F).max())
    assert slow.lam == pytest.approx(fast.lam, rel=1e-12)
    limited = rx.synthesize(system, dist, "ms_lqr", max_iter=1)      # one Newton step: not converged
    assert limited.status == "solver_failed" and limited.info["riccati_residual"] > 1e-13


def test_ms_lqr_statuses_on_the_new_paths():
    """Not stabilizable (an unstable mode no input reaches): `not_ms_stabilizable` from the dense and the
    accelerated paths; a loose tol stops early with a residual below it."""
    rng = np.random.default_rng(11)
    for n in (6, lq.SYM_SOLVE_MAX_N + 1):
        system, dist = system_of(rng, n, 2, 2)
        A, B = system.A.copy(), system.B.copy()
        A[:, 0, :], B[:, 0, :] = 0, 0
        A[0, 0, 0] = 1.05
        stuck = rx.AffineRandomSystem(A=list(A), B=list(B))
        res = rx.synthesize(stuck, dist, "ms_lqr")
        assert (res.status, res.F) == ("not_ms_stabilizable", None) and res.info["rate_optimal_lower"] >= 1
        loose = rx.synthesize(system, dist, "ms_lqr", tol=1e-6)
        assert loose.status == "optimal" and loose.info["riccati_residual"] <= 1e-6
        exact = rx.synthesize(system, dist, "ms_lqr")
        np.testing.assert_allclose(loose.F, exact.F, rtol=0, atol=1e-4 * np.abs(exact.F).max())


def test_anderson_least_squares_equals_lstsq():
    """The Gram-matrix least squares of the accelerated iteration: numpy's lstsq's minimiser on full-rank
    columns; on dependent columns (a repeated direction) the same residual and the minimum-norm gamma."""
    rng = np.random.default_rng(5)
    for k, N in ((1, 30), (3, 400), (5, 2500)):
        D, f = rng.normal(size=(k, N)) * rng.uniform(0.1, 10, (k, 1)), rng.normal(size=N)
        np.testing.assert_allclose(lq._least_squares(D, f), np.linalg.lstsq(D.T, f, rcond=None)[0], rtol=1e-9)
    D = np.vstack([D[:3], 2 * D[1]])
    gamma, ref = lq._least_squares(D, f), np.linalg.lstsq(D.T, f, rcond=None)[0]
    assert np.linalg.norm(f - D.T @ gamma) == pytest.approx(np.linalg.norm(f - D.T @ ref), rel=1e-12)
    np.testing.assert_allclose(gamma, ref, rtol=1e-7, atol=1e-9 * np.abs(ref).max())
