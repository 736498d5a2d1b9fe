"""Matrix-free mean-square numerics (analysis: ms_rate, perron, lyapunov, exact costs) against dense references.

Up to n = 30 every result equals the dense n^2 x n^2 computation (a copy of the code before the
matrix-free path) to 1e-10, on random and degenerate systems; at n = 50 and 100, where the dense
computation is out of reach, the results are checked for internal consistency: eigen-equation
residuals, and a Collatz-Wielandt bracket of the Perron root from an independent power iteration on
the exact second moments.
"""
import numpy as np
import pytest
import scipy.linalg

import rdsexp as rx
from rdsexp.numerics import analysis
from rdsexp.numerics.analysis import (
    DENSE_MAX_N,
    DENSE_SOLVE_MAX_N,
    DominantTerm,
    MomentMap,
    cost_matrix,
    exact_costs,
    h2_norm,
    lq_cost,
    lyapunov,
    perron,
    second_moments,
    stein_solve,
)

KINDS = ("random", "repeated", "zero_noise_factor", "non_normal", "deterministic", "uncontrollable")


# ------------------------------------------------------------------------------- dense references
def kron_T(Acl):
    """sum_r Acl_r (x) Acl_r, (n^2, n^2): row-major vec(T(X)) = this @ vec(X)."""
    return sum(np.kron(a, a) for a in Acl)


def dense_rho(Acl):
    return float(np.abs(np.linalg.eigvals(kron_T(Acl))).max())


def closed_loop(system, dist, F):
    Abar, Bbar = system.moment_factors(dist)
    return Abar + Bbar @ np.asarray(F, float)


def T_of(Acl, X):
    """sum_r Acl_r X Acl_r^T by einsum (independent of MomentMap)."""
    return np.einsum("rij,jk,rlk->il", Acl, X, Acl, optimize=True)


# --------------------------------------------------------------------------------------- systems
def system_of(rng, n, kind="random", m=2, p=2, a_scale=1.0):
    """A random affine system and moments of rdsexp's benchmark kind, or one of the degenerate KINDS
    (a_scale multiplies A_0: > 1 for open loops that are not mean-square stable)."""
    p = 0 if kind == "deterministic" else p
    A = [0.9 * rng.normal(size=(n, n)) / np.sqrt(n)] + [0.3 * rng.normal(size=(n, n)) / np.sqrt(n) for _ in range(p)]
    B = [rng.normal(size=(n, m))] + [0.3 * rng.normal(size=(n, m)) for _ in range(p)]
    if kind == "repeated":                 # a triple eigenvalue 0.9 and a double -0.5 in the mean, symmetric
        Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
        A[0] = Q @ np.diag(np.concatenate([[0.9] * 3, [-0.5] * 2, rng.uniform(-0.6, 0.6, n - 5)])) @ Q.T
    if kind == "zero_noise_factor":        # xi_2 enters nowhere: a zero factor of the moments
        A[2][:], B[2][:] = 0, 0
    if kind == "non_normal":               # eigenvector matrix of condition ~ 1e2
        S = np.eye(n) + np.triu(rng.normal(size=(n, n)), 1) * 0.4
        A[0] = S @ np.diag(rng.uniform(-0.9, 0.9, n)) @ np.linalg.inv(S)
    if kind == "uncontrollable":           # state 0: x0+ = 1.05 x0 whatever F and xi
        for M in A + B:
            M[0, :] = 0
        A[0][0, 0] = 1.05
    L = rng.normal(size=(p, p)) * 0.5
    A[0] = A[0] * a_scale
    return rx.AffineRandomSystem(A=A, B=B), rx.MomentModel(mean=rng.normal(size=p) * 0.3, cov=L @ L.T)


# ------------------------------------------------------------------------- operators, ms_rate, perron
def test_moment_map_and_dominant_term():
    rng = np.random.default_rng(0)
    Acl = rng.normal(size=(3, 13, 13)) / 4
    X = rng.normal(size=(13, 13))
    np.testing.assert_allclose(MomentMap(Acl)(X), T_of(Acl, X), rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(MomentMap(Acl, adjoint=True)(X), T_of(Acl.transpose(0, 2, 1), X), atol=1e-13)
    np.testing.assert_allclose(MomentMap(Acl[:1])(X), Acl[0] @ X @ Acl[0].T, atol=1e-13)
    C = X + X.T
    jordan = np.diag(np.full(13, 0.5)) + np.diag(np.full(12, 0.1), 1)     # defective: the Schur solve
    for M, eigenbasis in ((Acl, True), (jordan[None], False)):
        dom = DominantTerm(M)
        assert dom.eigenbasis is eigenbasis
        M0 = dom.M0
        assert dom.rho0 == pytest.approx(np.abs(np.linalg.eigvals(M0)).max() ** 2)
        # T - T0 maps the PSD cone into itself: it is a sum of Kronecker squares (rotated factors)
        rest = kron_T(M) - np.kron(M0, M0)
        assert np.linalg.eigvalsh(rest.reshape(13, 13, 13, 13).transpose(0, 2, 1, 3).reshape(169, 169)).min() > -1e-12
        sigma = 1.3 * max(dom.rho0, 0.1)
        Y = dom.solve(C, sigma)
        assert np.abs(sigma * Y - M0 @ Y @ M0.T - C).max() <= 1e-12 * np.abs(Y).max()
        # the term of the similar factors D^-1 M_r D / s without a new eigendecomposition
        d, scale = rng.uniform(0.2, 5, 13), 1.7
        before = (dom.M0.copy(), dom.Vr.copy(), dom.ww.copy())
        sim = dom.similar(d, scale)
        M0s = M0 * d[None, :] / d[:, None] / scale
        np.testing.assert_allclose(sim.M0, M0s, rtol=1e-14)
        assert sim.rho0 == pytest.approx(np.abs(np.linalg.eigvals(M0s)).max() ** 2, rel=1e-12)
        Y = sim.solve(C, sigma / scale ** 2)
        assert np.abs(sigma / scale ** 2 * Y - M0s @ Y @ M0s.T - C).max() <= 1e-11 * np.abs(Y).max()
        assert all(np.array_equal(a, b) for a, b in zip(before, (dom.M0, dom.Vr, dom.ww)))   # the original untouched


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.slow
def test_ms_rate_equals_the_dense_eigenvalues(kind):
    """F = 0, a random gain and the rate-optimal gain (the optimization crowds eigenvalues around rho),
    n = 11..16. Not the optimal gain of a deterministic loop: it tends to dead beat, a Jordan block
    whose eigenvalue no floating-point method, dense or not, gets to 1e-10."""
    rng = np.random.default_rng(KINDS.index(kind))
    for n in (DENSE_MAX_N + 1, 13, 16):
        system, dist = system_of(rng, n, kind)
        gains = [np.zeros((2, n)), 0.2 * rng.normal(size=(2, n))]
        if kind != "deterministic":
            gains.append(rx.synthesize(system, dist, "policy_iteration").F)
        for F in gains:
            Acl = closed_loop(system, dist, F)
            rho = dense_rho(Acl)
            assert rx.ms_rate(system, dist, F) == pytest.approx(np.sqrt(rho), rel=1e-10, abs=1e-300)
            for adjoint in (False, True):
                r, X = perron(Acl, adjoint=adjoint)
                assert r == pytest.approx(rho, rel=1e-10)
                M = Acl.transpose(0, 2, 1) if adjoint else Acl
                assert np.abs(T_of(M, X) - r * X).max() <= 1e-10 * r * np.abs(X).max()
                assert np.linalg.eigvalsh(X).min() >= -1e-8 * np.abs(X).max()
            # a caller's preconditioner (ms_lqr's: the adjoint factors at a gain 1% away) changes only the path
            near = DominantTerm((Acl + 0.01 * rng.normal(size=Acl.shape) * np.abs(Acl).max()).transpose(0, 2, 1))
            assert perron(Acl, adjoint=True, dominant=near)[0] == pytest.approx(rho, rel=1e-10)
        if kind == "uncontrollable":
            assert rx.ms_rate(system, dist, gains[-1]) >= 1.05 * (1 - 1e-12)


def test_ms_rate_of_a_rotation_and_a_nilpotent_loop():
    """Complex eigenvalues of the same modulus as rho (deterministic rotations), and rho = 0."""
    n = 16
    A = scipy.linalg.block_diag(*[0.9 * np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
                                  for t in np.linspace(0.3, 1.2, n // 2)])
    dist = rx.MomentModel(mean=np.zeros(0), cov=np.zeros((0, 0)))
    assert rx.ms_rate(rx.AffineRandomSystem(A=[A], B=[np.zeros((n, 1))]), dist, np.zeros((1, n))) == \
        pytest.approx(0.9, rel=1e-12)
    shift = np.diag(np.ones(n - 1), 1)
    assert rx.ms_rate(rx.AffineRandomSystem(A=[shift], B=[np.zeros((n, 1))]), dist, np.zeros((1, n))) < 1e-6


def bracket(Acl, X):
    """Collatz-Wielandt: T(X) >= a X and T(X) <= b X for X > 0 prove a <= rho(T) <= b (written here)."""
    C = np.linalg.cholesky((X + X.T) / 2)
    Y = scipy.linalg.solve_triangular(C, scipy.linalg.solve_triangular(C, T_of(Acl, X), lower=True).T, lower=True)
    w = np.linalg.eigvalsh((Y + Y.T) / 2)
    return w[0], w[-1]


def power_iteration_moments(system, dist, F, steps, rng):
    """E[x_k x_k^T] after `steps` steps of the ideal loop from a random x0 (exact second moments, d = 0):
    the power iteration of T, whose direction tends to the Perron vector."""
    _, second = second_moments(system, dist, F, rng.normal(size=system.n), np.zeros((steps + 1, system.m)))
    return second[-1] / np.abs(second[-1]).max()


@pytest.mark.parametrize("n", [50, 100])
@pytest.mark.slow
def test_ms_rate_at_scale_is_consistent(n):
    """The eigen-equation residual, the Collatz-Wielandt bracket of the returned vector (positive
    definite here, so the bracket proves rho to 1e-8), and a bracket from the exact second moments
    after 200 steps (an independent power iteration) that must contain the rate."""
    rng = np.random.default_rng(n)
    system, dist = system_of(rng, n)
    for F in (np.zeros((2, n)), 0.1 * rng.normal(size=(2, n))):
        Acl = closed_loop(system, dist, F)
        lam = rx.ms_rate(system, dist, F)
        rho, X = perron(Acl)
        assert rho == pytest.approx(lam ** 2, rel=1e-12)
        assert np.linalg.norm(T_of(Acl, X) - rho * X) <= 1e-12 * rho * np.linalg.norm(X)
        low, high = bracket(Acl, X)
        assert low <= rho * (1 + 1e-13) and rho <= high * (1 + 1e-13) and high - low <= 1e-8 * rho
        assert analysis.collatz_wielandt(Acl, X) == pytest.approx((low, high), rel=1e-10)
        low, high = bracket(Acl, power_iteration_moments(system, dist, F, 200, rng))
        assert low <= rho * (1 + 1e-13) and rho <= high * (1 + 1e-13) and high - low <= 5e-2 * rho


# ------------------------------------------------------------ generalized Lyapunov equation, exact costs
def dense_lyapunov(Acl, C):
    """P = C + sum_r Acl_r^T P Acl_r as one dense solve in vec(P) (the computation before the matrix-free one)."""
    n = Acl.shape[1]
    L = sum(np.kron(a.T, a.T) for a in Acl)                 # row-major vec(A^T P A) = (A^T (x) A^T) vec(P)
    return np.linalg.solve(np.eye(n * n) - L, C.ravel()).reshape(n, n)


def stable_gain(system, dist):
    """F = 0 where the open loop is mean-square stable, else the rate-optimal gain (None if not stabilizable)."""
    F = np.zeros((system.m, system.n))
    if rx.ms_rate(system, dist, F) < 1:
        return F
    res = rx.synthesize(system, dist, "policy_iteration")
    return res.F if res.lam < 1 else None


@pytest.mark.parametrize("kind", KINDS)
def test_lyapunov_and_exact_costs_equal_the_dense_solve(kind):
    rng = np.random.default_rng(10 + KINDS.index(kind))
    for n in (DENSE_SOLVE_MAX_N + 1, 20):
        system, dist = system_of(rng, n, kind)
        F = stable_gain(system, dist)
        if F is None:                                       # (uncontrollable: |1.05| whatever the gain)
            assert kind == "uncontrollable"
            F = rng.normal(size=(2, n)) * 0.1
            assert np.all(cost_matrix(system, dist, F) == np.inf) and lq_cost(system, dist, F) == np.inf
            assert lyapunov(closed_loop(system, dist, F), np.eye(n)) is None
            continue
        Q = np.diag(rng.uniform(0.5, 2, n))
        Acl = closed_loop(system, dist, F)
        P = dense_lyapunov(Acl, Q + 3 * F.T @ F)
        np.testing.assert_allclose(cost_matrix(system, dist, F, state_weight=Q, input_weight=3.0), P,
                                   rtol=1e-10, atol=1e-10 * np.abs(P).max())
        x0 = rng.normal(size=n)
        costs = exact_costs(system, dist, F, x0, state_weight=Q, input_weight=3.0)
        _, Bbar = system.moment_factors(dist)
        assert costs["lq_cost_x0"] == pytest.approx(x0 @ P @ x0, rel=1e-10)
        assert costs["lq_cost"] == pytest.approx(np.trace(P), rel=1e-10)
        assert costs["h2"] == pytest.approx(np.sqrt(np.einsum("rji,jk,rki->", Bbar, P, Bbar)), rel=1e-10)
        assert h2_norm(system, dist, F, state_weight=Q, input_weight=3.0) == pytest.approx(costs["h2"], rel=1e-12)
        unstable = 1.2 / np.sqrt(dense_rho(Acl)) * Acl      # the same loop made mean-square unstable
        assert lyapunov(unstable, np.eye(n)) is None


@pytest.mark.parametrize("n", [50, 100])
@pytest.mark.slow
def test_lyapunov_at_scale_is_consistent(n):
    """The residual at working precision, P > 0, and P against the fixed point P <- Qbar + T*(P) iterated
    from 0 (Smith's iteration, written here) on a loop of rate 0.9."""
    rng = np.random.default_rng(n + 1)
    system, dist = system_of(rng, n)
    Acl = closed_loop(system, dist, np.zeros((2, n)))
    Acl *= 0.9 / np.sqrt(perron(Acl)[0])
    C = np.eye(n) + 0.1 * np.ones((n, n))
    P = lyapunov(Acl, C)
    At = Acl.transpose(0, 2, 1)
    assert np.abs(C + T_of(At, P) - P).max() <= 1e-13 * np.abs(P).max()
    assert np.linalg.eigvalsh(P).min() > 0
    smith = np.zeros((n, n))
    for _ in range(400):                                        # 0.81^400 < 1e-36
        smith = C + T_of(At, smith)
    np.testing.assert_allclose(P, smith, rtol=1e-9, atol=1e-11 * np.abs(P).max())
    D, E = stein_solve(Acl, C, rtol=1e-3)                        # a loose solve stops early with its residual
    assert 1e-16 * np.abs(P).max() < np.linalg.norm(E) <= 1e-3 * np.linalg.norm(C)
    np.testing.assert_allclose(E, C + T_of(At, D) - D, atol=1e-12 * np.abs(P).max())


# ---------------------------------------------------------------------------------------- ms_lqr
def expect(M, N, P):
    """sum_r M_r^T P N_r over factors (nbar, n, .) (written here)."""
    return np.einsum("rji,jk,rkl->il", M, P, N, optimize=True)


def dense_ms_lqr(system, dist, Q, R):
    """The gain and cost matrix of Newton's (Hewer's) iteration with dense Lyapunov solves, from F = 0 or
    the rate-optimal gain, until the step is below 1e-13 (the computation before the matrix-free one);
    None where policy iteration finds no stabilizing gain."""
    Abar, Bbar = system.moment_factors(dist)
    F = np.zeros((system.m, system.n))
    if dense_rho(Abar) >= 1:
        F = rx.synthesize(system, dist, "policy_iteration").F
        if dense_rho(Abar + Bbar @ F) >= 1:
            return None
    P = dense_lyapunov(Abar + Bbar @ F, Q + F.T @ R @ F)
    for _ in range(50):
        F = -np.linalg.solve(R + expect(Bbar, Bbar, P), expect(Bbar, Abar, P))
        P_new = dense_lyapunov(Abar + Bbar @ F, Q + F.T @ R @ F)
        step, P = np.abs(P_new - P).max(), P_new
        if step <= 1e-13 * np.abs(P).max():
            break
    return -np.linalg.solve(R + expect(Bbar, Bbar, P), expect(Bbar, Abar, P)), P


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.slow
def test_ms_lqr_equals_the_dense_newton_iteration(kind):
    """n = 17 from the open loop, n = 20 with A_0 scaled by 1.2, an open loop that is not mean-square
    stable (the start is then a value-iteration gain, or none)."""
    rng = np.random.default_rng(20 + KINDS.index(kind))
    for n, a_scale in ((DENSE_SOLVE_MAX_N + 1, 1.0), (20, 1.2)):
        system, dist = system_of(rng, n, kind, a_scale=a_scale)
        assert (dense_rho(system.moment_factors(dist)[0]) >= 1) == (a_scale > 1 or kind == "uncontrollable")
        Q = np.diag(rng.uniform(0.5, 2, n))
        res = rx.synthesize(system, dist, "ms_lqr", state_weight=Q, input_weight=0.5)
        dense = dense_ms_lqr(system, dist, Q, 0.5 * np.eye(2))
        if dense is None:                              # e.g. uncontrollable: |1.05| whatever the gain
            assert (res.status, res.F) == ("not_ms_stabilizable", None) and res.info["rate_optimal_lower"] >= 1
            continue
        F, P = dense
        assert res.status == "optimal"
        np.testing.assert_allclose(res.F, F, rtol=0, atol=1e-10 * np.abs(F).max())
        assert res.info["cost_trace"] == pytest.approx(np.trace(P), rel=1e-10)
        assert res.lam == pytest.approx(np.sqrt(dense_rho(closed_loop(system, dist, F))), rel=1e-10)
        assert res.info["riccati_residual"] < 1e-13
        if kind == "deterministic":                    # the DARE of the one model
            A, B, _, _ = system.at(dist.mean)
            X = scipy.linalg.solve_discrete_are(A, B, Q, 0.5 * np.eye(2))
            assert np.trace(X) == pytest.approx(res.info["cost_trace"], rel=1e-9)


@pytest.mark.parametrize("n", [50, 100])
@pytest.mark.slow
def test_ms_lqr_at_scale_is_consistent(n):
    """The cost matrix of the returned gain by Smith's iteration (written here) solves the generalized
    Riccati equation and has the reported trace; the rate is the gain's (eigen-equation residual)."""
    rng = np.random.default_rng(n + 2)
    system, dist = system_of(rng, n)
    res = rx.synthesize(system, dist, "ms_lqr")
    assert res.status == "optimal" and res.info["riccati_residual"] < 1e-13
    Abar, Bbar = system.moment_factors(dist)
    Acl = Abar + Bbar @ res.F
    C = np.eye(n) + res.F.T @ res.F
    P = np.zeros((n, n))
    for _ in range(5000):
        P, old = C + expect(Acl, Acl, P), P
        if np.abs(P - old).max() <= 1e-15 * np.abs(P).max():
            break
    residual = np.eye(n) + expect(Abar, Abar, P) - expect(Abar, Bbar, P) @ np.linalg.solve(
        np.eye(2) + expect(Bbar, Bbar, P), expect(Bbar, Abar, P)) - P
    assert np.abs(residual).max() <= 1e-11 * np.abs(P).max()
    assert res.info["cost_trace"] == pytest.approx(np.trace(P), rel=1e-11)
    rho, X = perron(Acl)
    assert res.lam == pytest.approx(np.sqrt(rho), rel=1e-14)
    assert np.linalg.norm(T_of(Acl, X) - rho * X) <= 1e-12 * rho * np.linalg.norm(X)


# ------------------------------------------------------------------------------------- policy iteration
def dense_policy_iteration(system, dist, steps=60):
    """Policy iteration with dense Perron vectors (eigenvectors of sum_r Acl_r^T (x) Acl_r^T, written here):
    the optimal rate it reaches."""
    Abar, Bbar = system.moment_factors(dist)
    F, best = np.zeros((system.m, system.n)), np.inf
    for _ in range(steps):
        Acl = Abar + Bbar @ F
        w, V = np.linalg.eig(sum(np.kron(a.T, a.T) for a in Acl))
        i = np.argmax(w.real)
        P = V[:, i].real.reshape(system.n, system.n)
        P = (P + P.T) * np.sign(np.trace(P))
        rate = np.sqrt(w[i].real)
        if rate >= best * (1 - 1e-13):
            break
        best = rate
        F = -np.linalg.pinv(expect(Bbar, Bbar, P)) @ expect(Bbar, Abar, P)
    return best


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.slow
def test_policy_iteration_bracket_at_n_up_to_30(kind):
    """lam is the exact rate of F (dense eigenvalues), lam_lower is below the rate of every gain tried,
    `optimal` only with a bracket below 1e-7, and lam is the optimum a dense policy iteration reaches."""
    rng = np.random.default_rng(30 + KINDS.index(kind))
    for n in (DENSE_MAX_N + 2, 16) if kind != "random" else (DENSE_MAX_N + 2, 16, 30):
        system, dist = system_of(rng, n, kind)
        res = rx.synthesize(system, dist, "policy_iteration")
        assert res.lam == pytest.approx(np.sqrt(dense_rho(closed_loop(system, dist, res.F))), rel=1e-10)
        for F in [res.F] + [res.F + s * rng.normal(size=res.F.shape) for s in (1e-3, 1e-1)]:
            assert res.lam_lower <= np.sqrt(dense_rho(closed_loop(system, dist, F))) * (1 + 1e-12)
        assert res.status in ("optimal", "not_ms_stabilizable", "not_converged")
        if res.status != "not_converged":
            assert res.lam - res.lam_lower <= 1e-7 * res.lam or res.lam_lower >= 1
        if kind == "uncontrollable":
            assert res.status == "not_ms_stabilizable" and res.lam_lower >= 1.05 * (1 - 1e-7)
        if res.status == "optimal" and n <= 16:
            assert dense_policy_iteration(system, dist) == pytest.approx(res.lam, abs=1e-10)


@pytest.mark.parametrize("n", [50, 100])
@pytest.mark.slow
def test_policy_iteration_at_scale(n):
    """A proven bracket of width <= 1e-6 at n = 50, 100: lam is F's rate (its Perron pair's residual and
    a Collatz-Wielandt bracket), lam_lower below the rates of nearby gains."""
    rng = np.random.default_rng(n + 3)
    system, dist = system_of(rng, n)
    res = rx.synthesize(system, dist, "policy_iteration")
    assert res.status == "optimal" and res.lam - res.lam_lower <= 1e-6
    Acl = closed_loop(system, dist, res.F)
    rho, X = perron(Acl)
    assert res.lam == pytest.approx(np.sqrt(rho), rel=1e-12)
    assert np.linalg.norm(T_of(Acl, X) - rho * X) <= 1e-12 * rho * np.linalg.norm(X)
    low, high = bracket(Acl, X)
    assert np.sqrt(low) - 1e-8 <= res.lam <= np.sqrt(high) + 1e-8
    for scale in (1e-3, 1e-2):
        F = res.F + scale * rng.normal(size=res.F.shape)
        assert res.lam_lower <= rx.ms_rate(system, dist, F) * (1 + 1e-12)
