"""EnKF with an unknown input disturbance in its state, psi = [x; xi; d] (EnKF.disturbance)."""
import numpy as np
import pytest

import rdsexp as rx
from rdsexp.numerics.enkf import EnKF
from rdsexp.numerics.simulation import simulate

paper = rx.paper


def test_augmented_step_equals_per_member_equations():
    """predict/update with d: x_{k+1} = A(xi) x + B(xi) (u + d) + w_x, xi and d random walks, and
    z = C(xi) x + D(xi) (u + d) + v in the gain, written member by member (a model with a random D,
    so that d enters the output too)."""
    rng = np.random.default_rng(1)
    n, m, ny, p = 2, 2, 2, 1
    model = rx.AffineRandomSystem(A=[[[0.5, 0.1], [0.0, 0.7]], [[0.1, 0.0], [0.0, 0.2]]],
                                  B=[np.eye(2), [[0.0, 0.3], [0.0, 0.0]]], C=[np.eye(2), np.zeros((2, 2))],
                                  D=[np.zeros((2, 2)), [[0.5, 0.0], [0.0, 0.0]]])
    Qd = np.array([[0.2, 0.05], [0.05, 0.1]])
    enkf = EnKF(model, 0.01, 0.02, disturbance=Qd)
    assert (enkf.dim, enkf.width) == (n + p, n + p + m)
    P, M, w = 3, 6, n + p + m
    psi = rng.normal(size=(P, M, w))
    u, y = rng.normal(size=(P, m)), rng.normal(size=(P, ny))
    e_w, e_v = rng.normal(size=(P, M, w)), rng.normal(size=(P, M, ny))
    pred = enkf.predict(psi, u, e_w)
    a = enkf.update(pred, u, y, e_v)
    Q_sqrt = np.zeros((w, w))
    Q_sqrt[:n + p, :n + p] = 0.1 * np.eye(n + p)
    vals, vecs = np.linalg.eigh(Qd)
    Q_sqrt[n + p:, n + p:] = (vecs * np.sqrt(vals)) @ vecs.T
    for j in range(P):
        ref, z = np.empty((M, w)), np.empty((M, ny))
        for i in range(M):
            x, xi, d = psi[j, i, :n], psi[j, i, n:n + p], psi[j, i, n + p:]
            A, B, _, _ = model.at(xi)
            ref[i] = np.concatenate([A @ x + B @ (u[j] + d), xi, d]) + Q_sqrt @ e_w[j, i]
            _, _, C, D = model.at(ref[i, n:n + p])
            z[i] = C @ ref[i, :n] + D @ (u[j] + ref[i, n + p:]) + np.sqrt(0.02) * e_v[j, i]
        np.testing.assert_allclose(pred[j], ref, atol=1e-12)
        dpsi, dz = ref - ref.mean(0), z - z.mean(0)
        K = (dpsi.T @ dz) @ np.linalg.inv(dz.T @ dz)
        np.testing.assert_allclose(a.psi[j], ref + (y[j] - z) @ K.T, atol=1e-10)


def test_augmented_enkf_recovers_a_constant_unknown_disturbance():
    """A linear-Gaussian plant (p = 0) driven by u_k + d with d = 2 unknown to the filter: the
    augmented EnKF's mean follows the exact Kalman filter of [x; d] (the 1/M sampling error), and its
    estimate of d at the end is unbiased within the Monte Carlo error of the paths (the KF's posterior
    variance of d over P paths). Without the disturbance state the x estimate stays biased."""
    A, B, C = np.array([[0.9, 0.2], [-0.1, 0.8]]), np.array([[0.0], [1.0]]), np.array([[1.0, 0.0]])
    Qx, R, Qd, d_true = 1e-3, 0.01, 0.01, 2.0
    system = rx.AffineRandomSystem(A=[A], B=[B], C=[C])
    rng = np.random.default_rng(7)
    P, M, K = 200, 100, 40
    plain, augmented = EnKF(system, Qx, R), EnKF(system, Qx, R, disturbance=Qd)
    # augmented KF: state [x; d], d_{k+1} = d_k + w_d, starting at d ~ N(0, Qd) as `simulate` does
    Aa, Ca = np.block([[A, B], [np.zeros((1, 2)), np.eye(1)]]), np.hstack([C, [[0.0]]])
    Qa = np.diag([Qx, Qx, Qd])
    m, Pk = np.zeros((P, 3)), np.diag([0.0, 0.0, Qd])
    x = np.zeros((P, 2))
    ens = {"plain": np.zeros((P, M, 2)), "augmented": np.zeros((P, M, 3))}
    ens["augmented"][..., 2] = rng.normal(size=(P, M)) * np.sqrt(Qd)
    u = np.zeros((P, 1))
    for k in range(K + 1):
        y = x @ C.T + rng.normal(size=(P, 1)) * np.sqrt(R)
        filt = {}
        for name, enkf in (("plain", plain), ("augmented", augmented)):
            a = enkf.update(ens[name], u, y, rng.normal(size=(P, M, 1)))
            filt[name] = a.filt_mean
            ens[name] = enkf.predict(a.psi, u, rng.normal(size=ens[name].shape))
        G = Pk @ Ca.T / (Ca @ Pk @ Ca.T + R)
        m = m + (y - m @ Ca.T) @ G.T
        Pk = Pk - G @ Ca @ Pk
        if k < K:
            m, Pk = m @ Aa.T, Aa @ Pk @ Aa.T + Qa
            x = x @ A.T + (u + d_true) @ B.T + rng.normal(size=(P, 2)) * np.sqrt(Qx)
    d_hat = filt["augmented"][:, 2]
    sigma_d = np.sqrt(Pk[2, 2])                                  # the KF's posterior std of d
    assert abs(d_hat.mean() - d_true) < 4 * sigma_d / np.sqrt(P) + 0.05 * sigma_d   # + the ensemble's bias
    assert np.mean((filt["augmented"] - m) ** 2, axis=0).max() < 0.1 * np.diag(Pk).max()   # EnKF ~ KF
    x_err = lambda name: np.sqrt(np.mean(np.sum((filt[name][:, :2] - x) ** 2, axis=-1)))
    assert x_err("augmented") < 0.5 * x_err("plain"), (x_err("augmented"), x_err("plain"))


def test_paper_loop_with_an_unknown_step_estimates_it():
    """The paper's closed loop, its step d_k = 10 (k < 50) unknown to the EnKF: with the disturbance
    state the filter reads it as d (median estimate near 10 before the step ends, near 0 after), the
    reported psi keeps n + p columns and no path is lost."""
    K = 70
    enkf = EnKF(paper.model(), paper.Q, paper.R, disturbance=1.0)
    tr = simulate(paper.plant(), enkf, F=paper.F_proposed, d=paper.disturbance(K), q0=paper.q0, psi0=paper.psi0,
                  ensemble_size=30, paths=8, seed=0, filter_sees_d=False)
    assert tr.status == "ok"
    assert tr.psi_filt_mean.shape == (K + 1, 8, 9) and tr.d_filt_mean.shape == (K + 1, 8, 1)
    assert abs(np.median(tr.d_filt_mean[30:50]) - 10.0) < 1.0
    assert abs(np.median(tr.d_filt_mean[60:])) < 1.0
    assert np.all(tr.d_filt_std[1:] > 0)


def test_disturbance_off_draws_and_reports_as_before():
    """disturbance=None is the paper's filter: no d columns, width n + p (the same draws as before)."""
    enkf = EnKF(paper.model(), paper.Q, paper.R)
    assert enkf.width == enkf.dim == 9
    tr = simulate(paper.plant(), enkf, F=paper.F_proposed, d=paper.disturbance(5), q0=paper.q0, psi0=paper.psi0,
                  ensemble_size=5, paths=2, seed=0)
    assert tr.d_filt_mean is None and tr.d_filt_std is None


@pytest.mark.parametrize("value, message", [
    (0.0, "disturbance: 0 is not allowed"),
    (-1.0, "disturbance: must be positive semidefinite"),
    ([1.0, 2.0], "disturbance: shape"),
])
def test_bad_disturbance_covariance(value, message):
    with pytest.raises(ValueError, match=message):
        EnKF(paper.model(), paper.Q, paper.R, disturbance=value)
