"""EnKF: the batched equations against a per-member reference, and convergence to the Kalman filter."""
import numpy as np
import pytest

import rdsexp as rx
from rdsexp.numerics.enkf import EnKF


def test_batched_step_equals_per_member_equations():
    """predict/update on (paths, members) equal eqs. (state-pred2), (output-pred2), (filtering)-(kalman-v)
    written member by member (the reference loop lives only in this test)."""
    rng = np.random.default_rng(0)
    model = rx.paper.model()
    enkf = EnKF(model, rx.paper.Q, rx.paper.R)
    P, M = 3, 7
    psi = rng.normal(size=(P, M, 9))
    u, y = rng.normal(size=(P, 1)), rng.normal(size=(P, 3))
    e_w, e_v = rng.normal(size=(P, M, 9)), rng.normal(size=(P, M, 3))
    pred = enkf.predict(psi, u, e_w)
    a = enkf.update(pred, u, y, e_v)
    Qh, Rh = np.sqrt(rx.paper.Q), np.sqrt(rx.paper.R)          # diagonal here
    for j in range(P):
        ref = np.empty((M, 9))
        z = np.empty((M, 3))
        for i in range(M):
            x, xi = psi[j, i, :6], psi[j, i, 6:]
            A, B, C, D = model.at(xi)
            ref[i] = np.concatenate([A @ x + B @ u[j], xi]) + Qh @ e_w[j, i]
        for i in range(M):
            A, B, C, D = model.at(ref[i, 6:])
            z[i] = C @ ref[i, :6] + D @ u[j] + Rh @ e_v[j, i]
        np.testing.assert_allclose(pred[j], ref, atol=1e-12)
        dpsi, dz = ref - ref.mean(0), z - z.mean(0)
        K = (dpsi.T @ dz / (M - 1)) @ np.linalg.inv(dz.T @ dz / (M - 1))
        filt = ref + (y[j] - z) @ K.T
        np.testing.assert_allclose(a.psi[j], filt, atol=1e-10)
        np.testing.assert_allclose(a.filt_mean[j], filt.mean(0), atol=1e-10)
        np.testing.assert_allclose(a.filt_std[j], filt.std(0, ddof=1), atol=1e-10)
        np.testing.assert_allclose(a.pred_std[j], ref.std(0, ddof=1), atol=1e-12)
    assert a.ok.all()


def run_enkf_and_kf(M, paths, seed):
    """A deterministic linear-Gaussian system (p = 0): EnKF mean and exact KF mean, (K+1, paths, n)."""
    A = np.array([[0.9, 0.2], [-0.1, 0.8]])
    C = np.array([[1.0, 0.0]])
    Q, R = 0.05 * np.eye(2), np.array([[0.1]])
    system = rx.AffineRandomSystem(A=[A], B=[np.zeros((2, 1))], C=[C])
    enkf = EnKF(system, Q, R)
    rng = np.random.default_rng(seed)
    K, m0, P0 = 30, np.array([1.0, -1.0]), np.eye(2)
    x = m0 + rng.normal(size=(paths, 2)) @ np.linalg.cholesky(P0).T
    ens = m0 + rng.normal(size=(paths, M, 2)) @ np.linalg.cholesky(P0).T
    m, Pk = np.broadcast_to(m0, (paths, 2)).copy(), P0.copy()
    u = np.zeros((paths, 1))
    diff = []
    for _ in range(K):
        y = x @ C.T + rng.normal(size=(paths, 1)) * np.sqrt(R[0, 0])
        a = enkf.update(ens, u, y, rng.normal(size=(paths, M, 1)))
        S = C @ Pk @ C.T + R
        G = Pk @ C.T @ np.linalg.inv(S)
        m = m + (y - m @ C.T) @ G.T
        Pk = Pk - G @ C @ Pk
        diff.append(a.filt_mean - m)
        ens = enkf.predict(a.psi, u, rng.normal(size=(paths, M, 2)))
        m, Pk = m @ A.T, A @ Pk @ A.T + Q
        x = x @ A.T + rng.normal(size=(paths, 2)) @ np.linalg.cholesky(Q).T
    return np.array(diff), Pk


def test_enkf_mean_approaches_kalman_filter():
    """E||mean_EnKF - mean_KF||^2 shrinks like 1/M (sampling error of an M-member ensemble)."""
    err = {}
    for M in (25, 400):
        diff, _ = run_enkf_and_kf(M, paths=200, seed=M)
        err[M] = np.mean(np.sum(diff[5:] ** 2, axis=-1))        # after the initial transient
    # 16x the members: the squared error should drop ~16x; allow a factor 2 either way
    ratio = err[25] / err[400]
    assert 8 < ratio < 32, (err, ratio)
    assert err[400] < 0.01


def test_singular_innovation_is_reported_not_raised():
    model = rx.AffineRandomSystem(A=[np.eye(2)], B=[np.zeros((2, 1))], C=[np.eye(2)])
    enkf = EnKF(model, np.zeros((2, 2)), np.zeros((2, 2)))
    psi = np.ones((2, 5, 2))                                      # no spread, no noise: V = 0
    psi[1] += np.random.default_rng(0).normal(size=(5, 2))
    a = enkf.update(psi, np.zeros((2, 1)), np.zeros((2, 2)), np.zeros((2, 5, 2)))
    assert a.ok.tolist() == [False, True]
    np.testing.assert_array_equal(a.psi[0], psi[0])


@pytest.mark.parametrize("Q, R, message", [
    (np.eye(8), 0.01, "Q: shape"),
    (-np.eye(9), 0.01, "Q: must be positive semidefinite"),
    (0.01, np.ones((3, 3)) + np.diag([0, 0, -2.0]), "R: must be positive semidefinite"),
    (0.01, [[0.1, 0.2], [0.2, 0.1]], "R: shape"),
    (np.nan, 0.01, "Q: contains NaN"),
])
def test_bad_noise_covariances(Q, R, message):
    with pytest.raises(ValueError, match=message):
        EnKF(rx.paper.model(), Q, R)


def test_xi_projected_onto_the_support_box():
    """With xi_bounds the analysed members' xi lie in the box, equal the unprojected update clipped,
    and the reported filtered mean and spread are the projected ensemble's; infinite bounds change nothing."""
    rng = np.random.default_rng(3)
    model = rx.paper.model()
    P, M = 4, 9
    pred = rng.normal(size=(P, M, 9)) * 2
    u, y, e_v = rng.normal(size=(P, 1)), rng.normal(size=(P, 3)) * 3, rng.normal(size=(P, M, 3))
    free = EnKF(model, rx.paper.Q, rx.paper.R).update(pred, u, y, e_v)
    low, high = np.array([0.0, -np.inf, -0.5]), np.array([1.0, np.inf, 0.5])
    boxed = EnKF(model, rx.paper.Q, rx.paper.R, xi_bounds=(low, high)).update(pred, u, y, e_v)
    xi = boxed.psi[..., 6:]
    assert np.all((xi >= low) & (xi <= high))
    np.testing.assert_array_equal(xi, np.clip(free.psi[..., 6:], low, high))
    np.testing.assert_array_equal(boxed.psi[..., :6], free.psi[..., :6])
    assert np.any(free.psi[..., 6:] != xi)                   # the case does leave the box
    np.testing.assert_allclose(boxed.filt_mean, boxed.psi.mean(axis=-2), atol=1e-12)
    np.testing.assert_allclose(boxed.filt_std[..., 6:], xi.std(axis=-2, ddof=1), atol=1e-12)
    unbounded = EnKF(model, rx.paper.Q, rx.paper.R, xi_bounds=(np.full(3, -np.inf), np.full(3, np.inf)))
    assert unbounded.xi_bounds is None
    np.testing.assert_array_equal(unbounded.update(pred, u, y, e_v).psi, free.psi)
    with pytest.raises(ValueError, match="xi_bounds: low .* must be <= high"):
        EnKF(model, rx.paper.Q, rx.paper.R, xi_bounds=(np.ones(3), np.zeros(3)))


def test_xi_support_follows_the_plant_file_through_the_truth_map():
    from rdsexp.numerics import distributions as D
    from rdsexp.numerics.enkf import xi_support
    A = [np.eye(2) * 0.5, np.diag([1.0, 0.0]), np.diag([0.0, 1.0])]
    B = [np.array([[0.0], [1.0]]), np.zeros((2, 1)), np.zeros((2, 1))]
    plant = rx.AffineRandomSystem(A=A, B=B, C=[np.eye(2)], D=None,
                                  xi_dist=D.Independent([D.Bernoulli([0.9]), D.Uniform([-0.2], [0.3])]))
    low, high = xi_support(plant, plant)
    np.testing.assert_array_equal(low, [0.0, -0.2])
    np.testing.assert_array_equal(high, [1.0, 0.3])
    # a model whose xi_0 = 2 s_0 - 1 and xi_1 = s_0 + s_1 (two parameters: left free)
    M1 = (A[1] - A[2]) / 2                     # A0 + xi_0 M1 + xi_1 A2 = A0 + M1 + s_0 A1 + s_1 A2
    model = rx.AffineRandomSystem(A=[A[0] + M1, M1, A[2]], B=B, C=[np.eye(2)], D=None)
    low, high = xi_support(model, plant)
    np.testing.assert_allclose(low, [-1.0, -np.inf])
    np.testing.assert_allclose(high, [1.0, np.inf])
    # the paper: a normal plant, nothing bounded (the reproduction is unchanged)
    low, high = xi_support(rx.paper.model(), rx.paper.plant())
    assert np.all(np.isinf(low)) and np.all(np.isinf(high))


def test_xi_ends_marks_the_components_whose_law_takes_only_their_two_ends():
    """`distributions.two_point` per family (a Bernoulli, a discrete column of two values; not a uniform, a normal
    or a discrete column of three), and `xi_ends` through the truth map: xi_0 = 2 s_0 - 1 keeps it, a component
    of two parameters does not."""
    from rdsexp.numerics import distributions as D
    from rdsexp.numerics.enkf import xi_ends
    assert D.two_point(D.Bernoulli([0.9, 0.5])).tolist() == [True, True]
    assert D.two_point(D.Uniform([0.0], [1.0])).tolist() == [False]
    assert D.two_point(rx.MomentModel(mean=[0.0], cov=[[1.0]])).tolist() == [False]
    two_three = D.Discrete(values=[[0.0, 1.0], [2.0, 2.0], [0.0, 3.0]], probs=[0.2, 0.3, 0.5])
    assert D.two_point(two_three).tolist() == [True, False]
    assert D.two_point(D.Independent([D.Uniform([0.0], [1.0]), two_three])).tolist() == [False, True, False]
    A = [np.eye(2) * 0.5, np.diag([1.0, 0.0]), np.diag([0.0, 1.0])]
    B = [np.array([[0.0], [1.0]]), np.zeros((2, 1)), np.zeros((2, 1))]
    plant = rx.AffineRandomSystem(A=A, B=B, C=[np.eye(2)], D=None,
                                  xi_dist=D.Independent([D.Bernoulli([0.9]), D.Uniform([-0.2], [0.3])]))
    assert xi_ends(plant, plant).tolist() == [True, False]
    M1 = (A[1] - A[2]) / 2                     # xi_0 = 2 s_0 - 1, xi_1 = s_0 + s_1 (as above)
    model = rx.AffineRandomSystem(A=[A[0] + M1, M1, A[2]], B=B, C=[np.eye(2)], D=None)
    assert xi_ends(model, plant).tolist() == [True, False]
    swapped = rx.AffineRandomSystem(A=[A[0], A[2], A[1]], B=B, C=[np.eye(2)], D=None)     # xi_0 = s_1, xi_1 = s_0
    assert xi_ends(swapped, plant).tolist() == [False, True]
    assert not xi_ends(rx.paper.model(), rx.paper.plant()).any()


def test_xi_prior_draws_the_predicted_xi_from_the_model():
    """With xi_prior the predicted xi of every member is mean + S^(1/2) e (the xi part of e_w) and its x
    part moves with that drawn xi (the coefficient the next output then estimates): the random walk's
    prediction from the same members with their xi replaced by the draws."""
    from rdsexp.numerics.enkf import sqrtm_psd
    rng = np.random.default_rng(5)
    model = rx.paper.model()
    prior = rx.MomentModel(mean=[0.4, 0.2, 0.5], cov=[[0.04, 0.01, 0], [0.01, 0.09, 0], [0, 0, 0.01]])
    P, M = 3, 6
    psi, u, e_w = rng.normal(size=(P, M, 9)), rng.normal(size=(P, 1)), rng.normal(size=(P, M, 9))
    drawn = EnKF(model, rx.paper.Q, rx.paper.R, xi_prior=prior).predict(psi, u, e_w)
    draws = prior.mean + e_w[..., 6:] @ sqrtm_psd(prior.cov).T
    np.testing.assert_allclose(drawn[..., 6:], draws, atol=1e-14)
    walk = EnKF(model, rx.paper.Q, rx.paper.R).predict(np.concatenate([psi[..., :6], draws], axis=-1), u, e_w)
    np.testing.assert_allclose(drawn[..., :6], walk[..., :6], rtol=1e-13, atol=1e-13)
    # over many members the predicted xi has the prior's moments (Monte Carlo, 5 standard errors)
    big = rng.normal(size=(1, 40_000, 9))
    xi = EnKF(model, rx.paper.Q, rx.paper.R, xi_prior=prior).predict(np.zeros((1, 40_000, 9)), np.zeros((1, 1)),
                                                                     big)[0, :, 6:]
    se = np.sqrt(np.diag(prior.cov) / xi.shape[0])
    assert np.all(np.abs(xi.mean(0) - prior.mean) < 5 * se)
    np.testing.assert_allclose(np.cov(xi.T), prior.cov, atol=5 * 0.09 * np.sqrt(2 / xi.shape[0]))
    with pytest.raises(ValueError, match="xi_prior: p = 2 does not match"):
        EnKF(model, rx.paper.Q, rx.paper.R, xi_prior=rx.MomentModel(mean=[0, 0], cov=np.eye(2)))


def test_xi_prior_draws_are_projected_onto_the_support():
    rng = np.random.default_rng(6)
    model = rx.paper.model()
    prior = rx.MomentModel(mean=[0.9, 0.2, 0.5], cov=np.diag([0.04, 0.09, 0.01]))
    low, high = np.array([0.0, -np.inf, -np.inf]), np.array([1.0, np.inf, np.inf])
    e_w = rng.normal(size=(2, 500, 9))
    free = EnKF(model, rx.paper.Q, rx.paper.R, xi_prior=prior).predict(np.zeros((2, 500, 9)), np.zeros((2, 1)), e_w)
    boxed = EnKF(model, rx.paper.Q, rx.paper.R, xi_prior=prior, xi_bounds=(low, high)).predict(
        np.zeros((2, 500, 9)), np.zeros((2, 1)), e_w)
    assert np.any(free[..., 6] > 1)                          # N(0.9, 0.2^2) leaves [0, 1]
    np.testing.assert_array_equal(boxed[..., 6:], np.clip(free[..., 6:], low, high))
