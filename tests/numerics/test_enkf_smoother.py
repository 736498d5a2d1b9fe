"""The EnKF's fixed-lag smoother of xi (EnKF.lag): past draws kept in the ensemble and updated by later outputs."""
import numpy as np
import pytest

import rdsexp as rx
from rdsexp.numerics.enkf import EnKF


def unmeasured_coupling(xi_scale=1.0):
    """n = 2, p = 1: x1 measured, xi couples x1 into the unmeasured x2 (A_1 = [[0, 0], [1, 0]]), so y_{k+1}
    (x1_{k+1} = 0.5 x1 + 0.4 x2 + u) does not depend on xi_k; y_{k+2} does, through x2_{k+1}."""
    return rx.AffineRandomSystem(A=[[[0.5, 0.4], [0.0, 0.3]], [[0.0, 0.0], [xi_scale, 0.0]]],
                                 B=[[[1.0], [0.0]], [[0.0], [0.0]]], C=[[[1.0, 0.0]], [[0.0, 0.0]]])


def assert_update_is_the_kalman_formula(enkf, pred, u, y, e_v, R):
    """enkf.update (stochastic, output y = x1) of pred (P, M, width) against the formula written path by path:
    z = x1 + sqrt(R) e_v, K = Cov(psi, z) Cov(z)^-1 from the members, every component psi + K (y - z)."""
    a, M = enkf.update(pred, u, y, e_v), pred.shape[1]
    for j in range(pred.shape[0]):
        z = pred[j, :, :1] + np.sqrt(R) * e_v[j]
        dpsi, dz = pred[j] - pred[j].mean(0), z - z.mean(0)
        K = (dpsi.T @ dz / (M - 1)) @ np.linalg.inv(dz.T @ dz / (M - 1))
        np.testing.assert_allclose(a.psi[j], pred[j] + (y[j] - z) @ K.T, rtol=1e-10, atol=1e-10)


def test_smoother_step_equals_per_member_equations():
    """predict with lag 2 and a disturbance: x moves with the drawn xi, d walks, the first past-draw slot takes
    the filtered xi and the second the first's, both without noise; the update is the same Kalman formula on
    every component (written member by member); the box projection clips the past draws too."""
    rng = np.random.default_rng(11)
    model, n, p, m, L = unmeasured_coupling(), 2, 1, 1, 2
    prior = rx.MomentModel(mean=[0.6], cov=[[0.09]])
    enkf = EnKF(model, 0.01, 0.02, xi_prior=prior, disturbance=0.05, lag=L)
    w = n + p + m + L * p
    assert (enkf.dim, enkf.width, enkf.d_slice, enkf.xi_estimate) == (3, w, slice(3, 4), slice(w - 1, w))
    P, M = 3, 8
    psi = rng.normal(size=(P, M, w))
    u, y = rng.normal(size=(P, m)), rng.normal(size=(P, 1))
    e_w, e_v = rng.normal(size=(P, M, w)), rng.normal(size=(P, M, 1))
    pred = enkf.predict(psi, u, e_w)
    draws = 0.6 + 0.3 * e_w[..., n]
    for j in range(P):
        for i in range(M):
            x, d = psi[j, i, :n], psi[j, i, n + p]
            A, B, _, _ = model.at(draws[j, i:i + 1])
            ref = np.concatenate([A @ x + B @ (u[j] + d) + 0.1 * e_w[j, i, :n], draws[j, i:i + 1],
                                  [d + np.sqrt(0.05) * e_w[j, i, n + p]], psi[j, i, n:n + p], psi[j, i, 4:5]])
            np.testing.assert_allclose(pred[j, i], ref, rtol=1e-13, atol=1e-13)
    assert_update_is_the_kalman_formula(enkf, pred, u, y, e_v, R=0.02)
    boxed = EnKF(model, 0.01, 0.02, xi_prior=prior, lag=L, xi_bounds=([0.0], [1.0]))
    b = boxed.update(3.0 * boxed.predict(psi[..., :-1], u, e_w[..., :-1]), u, y, e_v)
    assert np.all((b.psi[..., 2:] >= 0) & (b.psi[..., 2:] <= 1))
    np.testing.assert_allclose(b.filt_mean[..., 2:], b.psi[..., 2:].mean(-2), rtol=1e-13)
    with pytest.raises(ValueError, match="lag: -1 is not allowed"):
        EnKF(model, 0.01, 0.02, lag=-1)


def smoothed_estimates(lag, K=60, P=40, M=200, seed=3):
    """The unmeasured-coupling plant (xi_k ~ N(0.5, 0.3^2) i.i.d., inputs u_k ~ N(0, 1) the filter is told),
    observed by the EnKF drawing xi from those moments with `lag`: (true xi_j, the EnKF's estimate of xi_j
    (`xi_estimate` lag + 1 steps later), its filtered variance), over steps j and paths, flattened."""
    rng = np.random.default_rng(seed)
    model = unmeasured_coupling()
    prior = rx.MomentModel(mean=[0.5], cov=[[0.09]])
    enkf = EnKF(model, np.diag([1e-4, 1e-4, 0.0]), 0.01, xi_prior=prior, lag=lag)
    x = np.zeros((P, 2))
    xi = 0.5 + 0.3 * rng.normal(size=(K, P))
    psi = np.zeros((P, M, enkf.width))
    psi[..., enkf.xi_estimate] = 0.5
    truth, estimate, var = [], [], []
    for k in range(K):
        u = rng.normal(size=(P, 1))
        a = enkf.update(psi, u, x[:, :1] + 0.1 * rng.normal(size=(P, 1)), rng.normal(size=(P, M, 1)))
        j = k - 1 - lag                                    # the step whose coefficient the estimate is of
        if j >= 5:
            s = enkf.xi_estimate
            truth.append(xi[j]), estimate.append(a.filt_mean[:, s][:, 0]), var.append(a.filt_std[:, s][:, 0] ** 2)
        A, B, _, _ = model.at(xi[k][:, None])
        x = (A @ x[..., None])[..., 0] + (B @ u[..., None])[..., 0]
        psi = enkf.predict(a.psi, u, rng.normal(size=(P, M, enkf.width)))
    return np.concatenate(truth), np.concatenate(estimate), np.concatenate(var)


def test_smoother_learns_a_component_the_next_output_does_not_see():
    """xi_k acts on the unmeasured x2, so y_{k+1} carries nothing of it: drawn i.i.d. and filtered once
    (lag 0), its estimate is uncorrelated with the truth (its posterior is its prior); kept one more step
    (lag 1), y_{k+2} estimates it. With the true prior the smoothed moments also recover the plant's by the
    law of total variance, mean of the estimates and their variance plus the mean smoothed variance (the
    controller's `total` covariance), and the smoothed variance is the estimates' mean squared error: checked
    to the Monte Carlo error of N estimates and 5% for the EnKF's sampling of the cross-covariances."""
    truth, filtered, _ = smoothed_estimates(lag=0)
    N = truth.size
    assert abs(np.corrcoef(truth, filtered)[0, 1]) < 4 / np.sqrt(N)
    truth, smoothed, var = smoothed_estimates(lag=1)
    r = np.corrcoef(truth, smoothed)[0, 1]
    assert r > 0.5, r                                                # lag 0: |r| < 0.09
    mse = np.mean((smoothed - truth) ** 2)
    assert mse < 0.7 * 0.09, mse                                     # the prior's variance: 0.09
    assert abs(mse / var.mean() - 1) < 4 * np.sqrt(2 / N) + 0.05     # the smoothed variance is the error's
    assert abs(smoothed.mean() - 0.5) < 4 * 0.3 / np.sqrt(N) + 0.01
    total = smoothed.var() + var.mean()
    assert abs(total / 0.09 - 1) < 4 * np.sqrt(2 / N) + 0.05, total


def test_output_delay_against_the_propagated_derivative():
    """output_delay (from the nonzero patterns) against the derivative of y_{k+1+j} in xi_i at random points:
    C(xi') x_{k+1} + D(xi') u with C_i, D_i for j = 0, then C(xi'') A(xi'_j) ... A(xi'_1) (A_i x_k + B_i u_k)
    with a fresh random xi' per step, on 600 random sparse systems; exact zeros are structural (no
    cancellation among random entries). The cases cover the delays -1 (never), 0, 1 and 2."""
    from rdsexp.numerics.enkf import output_delay
    rng = np.random.default_rng(21)
    seen = set()
    for _ in range(600):
        n, m, ny, p = int(rng.integers(1, 6)), int(rng.integers(1, 3)), int(rng.integers(1, 3)), int(rng.integers(1, 4))
        sparse = lambda *shape, keep=0.3: rng.normal(size=shape) * (rng.random(shape) < keep)
        A, B = sparse(p + 1, n, n, keep=0.12), sparse(p + 1, n, m)
        C, D = sparse(p + 1, ny, n, keep=0.15), sparse(p + 1, ny, m, keep=0.05)
        C[0, :, int(rng.integers(n))] = 0.0                                    # some states unmeasured
        system = rx.AffineRandomSystem(A=A, B=B, C=C, D=D)
        delay = output_delay(system)
        at = lambda M, p=p: M[0] + np.tensordot(rng.normal(size=p), M[1:], 1)    # M(xi') at a random xi'
        for i in range(p):
            x, u = rng.normal(size=n), rng.normal(size=m)
            v = A[1 + i] @ x + B[1 + i] @ u                                   # d x_{k+1} / d xi_i
            dy = [C[1 + i] @ rng.normal(size=n) + D[1 + i] @ rng.normal(size=m) + at(C) @ v]
            for _ in range(n - 1):
                v = at(A) @ v
                dy.append(at(C) @ v)
            hits = [j for j, d in enumerate(dy) if np.any(d != 0)]
            assert delay[i] == (hits[0] if hits else -1), (delay, i, dy)
            seen.add(int(delay[i]))
    assert {-1, 0, 1, 2} <= seen, seen
